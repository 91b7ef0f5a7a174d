"""Hardware-in-the-loop emulation around the ECU: plant emulator, planner and time master
nodes on a CAN bus (``python -m hil run``, ``make run``), scenarios, metrics, reports, the
frame recorder and the user-mode Linux launcher for a real SocketCAN ``vcan0``.

The HIL holds no control math: it talks to the ECU (``firmware_sim``) only through the
frames of ``can_defs/vehicle.dbc``.
"""
