"""Per-cycle timing record of the control task: a preallocated numpy ring buffer.

`record` writes one row into arrays allocated once, so the control loop allocates nothing
per cycle for it. `summary` (called off the loop) gives p50 / p99 / p99.9 / max per field.

Fields, all in seconds except ``overruns`` (NaN where not applicable, e.g. the release
jitter in lockstep or the input age before the first sample):

- ``release_jitter``: actual task start minus its ideal release time.
- ``task_time``: the whole control task (perf_counter around it).
- ``solve_time``: the optimiser's own time (``StepDebug.solve_time_s``).
- ``input_age``: task start minus the arrival of the newest consistent plant sample.
- ``rx_to_tx_latency``: arrival of the newest plant sample to the TX of the command.
- ``overruns``: deadline overruns counted so far (not saturated).
"""
from __future__ import annotations

import numpy as np

TIMING_FIELDS = ("release_jitter", "task_time", "solve_time", "input_age",
                 "rx_to_tx_latency", "overruns")
PERCENTILES = (50.0, 99.0, 99.9)


class TimingRecorder:
    """Ring buffer of the last ``capacity`` control cycles, shape (capacity, n_fields)."""

    def __init__(self, capacity: int) -> None:
        if capacity <= 0:
            raise ValueError(f"timing capacity must be positive, got {capacity}")
        self._rows = np.full((capacity, len(TIMING_FIELDS)), np.nan)
        self._next = 0
        self.count = 0  # cycles recorded since start (may exceed capacity)

    @property
    def capacity(self) -> int:
        """Rows kept."""
        return self._rows.shape[0]

    def record(self, release_jitter: float, task_time: float, solve_time: float,
               input_age: float, rx_to_tx_latency: float, overruns: int) -> None:
        """Write one cycle (overwrites the oldest row once full)."""
        row = self._rows[self._next]
        row[0] = release_jitter
        row[1] = task_time
        row[2] = solve_time
        row[3] = input_age
        row[4] = rx_to_tx_latency
        row[5] = overruns
        self._next = (self._next + 1) % self._rows.shape[0]
        self.count += 1

    def rows(self) -> np.ndarray:
        """Recorded cycles, oldest first, shape (n, n_fields) (a copy)."""
        n = min(self.count, self.capacity)
        if self.count <= self.capacity:
            return self._rows[:n].copy()
        return np.concatenate([self._rows[self._next:], self._rows[:self._next]])

    def column(self, name: str) -> np.ndarray:
        """One field over the recorded cycles, shape (n,)."""
        return self.rows()[:, TIMING_FIELDS.index(name)]

    def summary(self) -> dict[str, dict[str, float]]:
        """Per field: ``n`` (finite values), ``p50``, ``p99``, ``p99.9``, ``max`` (NaN if none)."""
        rows = self.rows()
        result: dict[str, dict[str, float]] = {}
        for index, name in enumerate(TIMING_FIELDS):
            values = rows[:, index]
            values = values[np.isfinite(values)]
            stats: dict[str, float] = {"n": float(values.size)}
            for q in PERCENTILES:
                stats[f"p{q:g}"] = float(np.percentile(values, q)) if values.size else float("nan")
            stats["max"] = float(values.max()) if values.size else float("nan")
            result[name] = stats
        return result
