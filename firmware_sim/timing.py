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

Beside each row, optional context (`CONTEXT_FIELDS`, kept apart so that `rows` and
`summary` keep their shape): ``start_time`` (task start on the ECU's clock, s; virtual
time in lockstep; lets a benchmark join cycles with other processes' CLOCK_MONOTONIC
stamps) and ``mode`` (CTRL_MODE after the transition, -1 if not given). `save` /
`load_timing` move the record through an ``.npz`` file (the ECU process writes it on exit
with ``--timing-out``), `apply_realtime_policy` pins a process to a core and raises it
to SCHED_FIFO where the OS permits, and `freeze_start_up_objects` keeps the garbage
collector's full collections short in the real-time loop.
"""
from __future__ import annotations

import gc
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TIMING_FIELDS = ("release_jitter", "task_time", "solve_time", "input_age",
                 "rx_to_tx_latency", "overruns")
PERCENTILES = (50.0, 99.0, 99.9)
CONTEXT_FIELDS = ("start_time", "mode")


class TimingRecorder:
    """Ring buffer of the last ``capacity`` control cycles, shape (capacity, n_fields)."""

    def __init__(self, capacity: int) -> None:
        if capacity <= 0:
            raise ValueError(f"timing capacity must be positive, got {capacity}")
        self._rows = np.full((capacity, len(TIMING_FIELDS)), np.nan)
        self._context = np.full((capacity, len(CONTEXT_FIELDS)), np.nan)
        self._next = 0
        self.count = 0  # cycles recorded since start (may exceed capacity)

    @property
    def capacity(self) -> int:
        """Rows kept."""
        return self._rows.shape[0]

    def record(self, release_jitter: float, task_time: float, solve_time: float,
               input_age: float, rx_to_tx_latency: float, overruns: int, *,
               start_time: float = math.nan, mode: int = -1) -> None:
        """Write one cycle (overwrites the oldest row once full)."""
        context = self._context[self._next]
        context[0] = start_time
        context[1] = mode
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

    def context_rows(self) -> np.ndarray:
        """Context of the recorded cycles (`CONTEXT_FIELDS`), oldest first, shape (n, 2)."""
        n = min(self.count, self.capacity)
        if self.count <= self.capacity:
            return self._context[:n].copy()
        return np.concatenate([self._context[self._next:], self._context[:self._next]])

    def save(self, path: str | Path) -> Path:
        """Write the record to ``path`` (``.npz``: ``rows`` (n, 6), ``context`` (n, 2), the
        field names and ``count``); returns the path. Off the control loop (allocates).
        The folder must exist (a missing one is an error, never created silently)."""
        path = Path(path)
        with path.open("wb") as handle:  # a file object: numpy adds no ".npz" suffix
            np.savez(handle, rows=self.rows(), context=self.context_rows(),
                     fields=np.array(TIMING_FIELDS), context_fields=np.array(CONTEXT_FIELDS),
                     count=np.array(self.count))
        return path

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


@dataclass(frozen=True)
class TimingRecord:
    """A saved timing record: ``columns`` maps every name of `TIMING_FIELDS` and
    `CONTEXT_FIELDS` to an array of shape (n,); ``count`` is the number of cycles run
    (more than n when the ring buffer wrapped)."""

    columns: dict[str, np.ndarray]
    count: int

    def __len__(self) -> int:
        return int(self.columns["task_time"].shape[0])


def load_timing(path: str | Path) -> TimingRecord:
    """Read a record written by `TimingRecorder.save`.

    Raises:
        ValueError: the file is not such a record (names the file and what is missing).
        OSError: it cannot be read.
    """
    with np.load(Path(path), allow_pickle=False) as data:
        missing = {"rows", "context", "fields", "context_fields", "count"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: not a timing record (missing {sorted(missing)})")
        rows, context = data["rows"], data["context"]
        fields, context_fields = [str(f) for f in data["fields"]], [str(f) for f in data["context_fields"]]
        if rows.shape[1:] != (len(fields),) or context.shape != (rows.shape[0], len(context_fields)):
            raise ValueError(f"{path}: rows {rows.shape} / context {context.shape} do not match "
                             f"the field names {fields} / {context_fields}")
        columns = {name: rows[:, i].copy() for i, name in enumerate(fields)}
        columns.update({name: context[:, i].copy() for i, name in enumerate(context_fields)})
        return TimingRecord(columns, int(data["count"]))


@dataclass(frozen=True)
class RealtimePolicy:
    """What `apply_realtime_policy` obtained: the CPUs the process may run on, the
    SCHED_FIFO priority (None: normal scheduling) and why a request was not granted."""

    cpus: tuple[int, ...]
    fifo_priority: int | None
    notes: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line, e.g. ``cpus [0], SCHED_FIFO 50``."""
        policy = f"SCHED_FIFO {self.fifo_priority}" if self.fifo_priority else "SCHED_OTHER"
        text = f"cpus {list(self.cpus)}, {policy}"
        return text + (f" ({'; '.join(self.notes)})" if self.notes else "")


def apply_realtime_policy(cpu: int | None = None, fifo_priority: int | None = None,
                          pid: int = 0) -> RealtimePolicy:
    """Pin process ``pid`` (0: this one) to ``cpu`` and give it SCHED_FIFO ``fifo_priority``.

    Either request is skipped with a note, never an exception, where the OS refuses it
    (no such CPU, not permitted): a benchmark then runs and reports what it got.

    Raises:
        ValueError: ``cpu`` negative or ``fifo_priority`` outside the OS's FIFO range.
    """
    notes: list[str] = []
    if cpu is not None:
        if cpu < 0:
            raise ValueError(f"cpu must be >= 0, got {cpu}")
        try:
            os.sched_setaffinity(pid, {cpu})
        except (OSError, AttributeError) as error:
            notes.append(f"cpu {cpu} not pinned: {error}")
    fifo = None
    if fifo_priority is not None:
        low, high = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
        if not low <= fifo_priority <= high:
            raise ValueError(f"SCHED_FIFO priority must be in {low}..{high}, got {fifo_priority}")
        try:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(fifo_priority))
            fifo = fifo_priority
        except (OSError, AttributeError) as error:
            notes.append(f"SCHED_FIFO not permitted: {error}")
    try:
        cpus = tuple(sorted(os.sched_getaffinity(pid)))
    except (OSError, AttributeError):
        cpus = ()
    return RealtimePolicy(cpus, fifo, tuple(notes))


def freeze_start_up_objects() -> int:
    """Collect once, then move every object alive now into the garbage collector's
    permanent generation (``gc.freeze``); returns how many objects that is.

    Called once after start-up, before the real-time loop. Python's full (generation 2)
    collection scans every tracked object: the modules, numpy, python-can, the model and
    the controller built at start-up, some hundred thousand objects. The plant process
    measured 23-44 ms per full collection before it froze them (docs/timing.md), beyond a
    control task's budget. Frozen, later collections scan only what the loop itself
    created. Objects frozen are never freed, so this is for a process that keeps its
    start-up objects to the end, as the ECU does.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
