"""Timing benchmarks of the ECU as on a vehicle (issue 9): `make timing`, `make bench`.

- `hub`: a CAN bus between processes over TCP loopback, in socketcand's protocol, so the
  ECU and the plant run as separate processes through python-can's ``socketcand``
  interface (the host kernel has no SocketCAN).
- `paths`: a long reference path (repeated double lane changes) for minutes-long runs.
- `plant_side`: the plant process (plant, planner, command audit on a wall-clock master).
- `stress`: busy-loop load processes, one per core.
- `bench`: ``python -m hil.timing.bench`` (`make timing`), ECU and plant pinned to
  separate cores, idle and under stress, per controller -> results/timing.md + PNGs.
- `report`: the tables and histograms of those runs.
- `compute`: ``python -m hil.timing.compute`` (`make bench`): per-step time of the four
  controllers side by side with the paper's, and a profile of the ESO-DKMPC step.
"""
