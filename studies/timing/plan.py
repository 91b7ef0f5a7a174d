"""Which runs `make timing` makes, in which order, and about how long they take.

Per load condition: the repeated rows first (ESO-DKMPC on the Python and the C ECU, under
every release asked for), interleaved by repeat (repeat 1 of every repeated row, then
repeat 2, ...) so that a slow spell of the shared machine falls on several rows instead of
on all repeats of one; then every other controller once, under the first release asked for
(``clock`` by default, contract revision 2, as before revision 3).
"""
from __future__ import annotations

from dataclasses import dataclass

from studies.timing.runner import ecu_label

#: The ECUs' control-task releases (contract revision 2: clock; revision 3: sample).
RELEASES = ("clock", "sample")
#: The controller whose rows are repeated and measured under every release.
REPEATED_CONTROLLER = "eso-dkmpc"
#: Start and stop of one run beside its seconds of driving (hub, ECU start-up until its
#: ready line, plant start-up, the ECU's exit and its record), s. Measured from a run
#: folder's first file to the ECU's record, 5 s runs on the 2-core machine with a load
#: average of 1.3 from other work: Python ECU 2.5-2.9 s idle and 5.6-6.7 s under stress,
#: C ECU 1.4 s and 3.0-3.2 s; 18 runs took 159 s of wall time for 90 s of driving.
RUN_OVERHEAD_S = 5.0


@dataclass(frozen=True)
class RunSpec:
    """One run: ``controller`` on ``ecu`` ("python" or "c") under ``release`` for
    ``seconds``; ``repeat`` is its number among the repeats of its row (1-based)."""

    controller: str
    ecu: str
    release: str
    repeat: int
    seconds: float

    @property
    def label(self) -> str:
        """The row's controller label: "NAME" or "NAME (C)"."""
        return ecu_label(self.controller, self.ecu)

    def work_name(self, condition: str) -> str:
        """Its folder under ``--work``: ``<load>__<controller>[_c]__<release>__r<repeat>``."""
        suffix = "_c" if self.ecu == "c" else ""
        return f"{condition}__{self.controller}{suffix}__{self.release}__r{self.repeat}"


def parse_releases(text: str) -> list[str]:
    """``clock,sample`` -> ["clock", "sample"].

    Raises:
        ValueError: empty, unknown or repeated names.
    """
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in RELEASES]
    if unknown or not names:
        raise ValueError(f"--release: unknown {unknown or 'empty list'}; choose one or more of "
                         f"{', '.join(RELEASES)}, comma-separated")
    if len(set(names)) != len(names):
        raise ValueError(f"--release: {text!r} names a release twice")
    return names


def plan_runs(controllers: list[str], c_controllers: list[str], releases: list[str],
              repeats: int, seconds: float, nmpc_seconds: float) -> list[RunSpec]:
    """The runs of one load condition, in run order (module docstring); NMPC runs for
    ``min(seconds, nmpc_seconds)``.

    Raises:
        ValueError: ``repeats`` < 1, ``seconds`` or ``nmpc_seconds`` not > 0, no release.
    """
    if repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {repeats}")
    if not (seconds > 0 and nmpc_seconds > 0):
        raise ValueError(f"run lengths must be > 0 s, got --seconds {seconds:g}, "
                         f"--nmpc-seconds {nmpc_seconds:g}")
    if not releases:
        raise ValueError("--release: at least one release")
    rows = [(controller, ecu) for ecu, names in (("python", controllers), ("c", c_controllers))
            for controller in names]
    repeated = [(c, ecu) for c, ecu in rows if c == REPEATED_CONTROLLER]
    plan = [RunSpec(c, ecu, release, repeat, seconds)
            for repeat in range(1, repeats + 1) for c, ecu in repeated for release in releases]
    plan += [RunSpec(c, ecu, releases[0], 1, min(seconds, nmpc_seconds) if c == "nmpc" else seconds)
             for c, ecu in rows if c != REPEATED_CONTROLLER]
    return plan


def estimated_seconds(plan: list[RunSpec], conditions: int,
                      overhead_s: float = RUN_OVERHEAD_S) -> float:
    """Wall time of ``plan`` run under ``conditions`` load conditions, s: the runs' seconds
    plus ``overhead_s`` each."""
    return conditions * sum(spec.seconds + overhead_s for spec in plan)
