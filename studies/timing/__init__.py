"""The real-time test of the ECU as on a vehicle (issue 9): `make timing`.

The bus nodes they start live in `hil.timing` (`hub`: the socketcand-protocol CAN bus
between processes; `plant_side`: the plant process).

- `paths`: a long reference path (repeated double lane changes) for minutes-long runs.
- `stress`: busy-loop load processes, one per core.
- `runner`: one run, ECU and plant as separate processes on separate cores.
- `bench`: ``python -m studies.timing.bench`` (`make timing`), ECU and plant pinned to
  separate cores, idle and under stress, per controller -> results/timing.md + PNGs.
- `report`: the tables and histograms of those runs.

The compute time per step of the controllers is `studies.bench` (`make bench`).
"""
