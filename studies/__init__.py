"""Studies and benchmarks: everything that writes ``results/`` (the paper's tables and
figures, the HIL runs over CAN, sweeps, the fault campaign, timing and compute-time
benchmarks).

Each module is a command (``python -m studies.<name>``, run by a ``make`` target) built on
the run-time packages: it imports ``can_defs``, ``models``, ``controller``,
``firmware_sim`` and ``hil``, and nothing there imports it back.

- `closed_loop`: closed-loop simulation without CAN (the study's runner); `report`: its
  tables and plots.
- `paper_tables`: ``make tables`` (paper Tables II / III, Figs 8 / 9).
- `run_all`: ``make run`` (the two double lane changes with the four controllers over CAN).
- `tuning_set`: the tuning set (``make tuning-set``); `tuning_sweep`: ``make tune``.
- `fault_campaign`: ``make faults``, ``make faults-c`` (its cases `fault_cases`, runs
  `fault_runs`, harnesses `fault_python_ecu`, `fault_c_ecu`, `fault_relay`, judge
  `fault_verdicts`, report `fault_report`).
- `fig7`: ``make fig7``; `table1`: ``make table1``; `handling`: ``make handling``.
- `bench`: ``make bench``, the one compute-time benchmark (every controller's step on the
  same recorded samples, the ECU's overhead); `machine`: the machine in results headers.
- `timing`: ``make timing``, the real-time test of the ECU.
"""
