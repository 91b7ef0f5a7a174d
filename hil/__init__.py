"""Hardware-in-the-loop emulation around the ECU: plant emulator, planner and time master
nodes on a CAN bus (``python -m hil run``), scenarios, fault injection, metrics, the frame
recorder, the log tools (``python -m hil replay|decode|play``), the ECU test harness
(`ecu_harness`) and the user-mode Linux launcher for a real SocketCAN ``vcan0``. Studies
and benchmarks that write ``results/`` (``make run``, ``make tables``, ...) are in
``studies``, which builds on this package.

The HIL holds no control math: it talks to the ECU (``firmware_sim``) only through the
frames of ``can_defs/vehicle.dbc``.
"""
