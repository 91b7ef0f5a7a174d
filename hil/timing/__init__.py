"""Bus nodes of the timing benchmark (`studies.timing`: `make timing`, `make bench`).

- `hub`: a CAN bus between processes over TCP loopback, in socketcand's protocol, so the
  ECU and the plant run as separate processes through python-can's ``socketcand``
  interface (the host kernel has no SocketCAN).
- `plant_side`: the plant process (plant, planner, command audit on a wall-clock master).
"""
