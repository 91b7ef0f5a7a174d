"""The ESO-DKMPC controller ECU on a CAN bus (``docs/can-contract.md``).

Modules: `ecu` (the node: cyclic executive; its parts `control_task`, one control cycle, and
`bus_loop`, its loop on the bus), `rx` / `tx` (frames in and out), `modes`
(mode state machine), `guard` (last check of every command), `safe_stop`, `clock`
(lockstep TICK clock and real-time schedule), `timing` (per-cycle timing record),
`config`, `errors` and `cli` (``python -m firmware_sim``). Its test harness is
`hil.ecu_harness`, its cost measurement the ECU overhead of `studies.bench`. Importing the package
imports nothing heavy (no torch).
"""
