"""Log replay: re-run the ECU on the inputs of a recorded CAN log and compare its outputs.

As openpilot's process_replay: a recorded log supplies the ECU's inputs (plant and planner
frames, HIL_SYNC, foreign frames); the ECU (`firmware_sim.ecu.Ecu`, in this process, on a
private virtual CAN channel) answers; its STEER_TORQUE_CMD and CTRL_DIAG frames are
compared with expected ones: the ECU frames recorded in the log, or a reference file
written by an earlier replay (``make replay-refs``).

The pieces: `hil.replay_feed` feeds the log into the ECU on the log's time base (lockstep
or time-stamped) and collects its frames; `hil.replay_outputs` holds the compared frames,
the reference files and the comparison (``exact`` / ``tolerance``); this module runs the
whole replay (`run_replay`) and reports it (`ReplayReport`). The names of both are
re-exported here, so ``hil.replay`` stays the one module to import.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can_defs.codec import decode
from can_defs.errors import CanDefsError
from can_defs.frames import FrameId, PlannerReq
from hil.logio import ECU_OUTPUT_IDS, LogContents, frame_times, is_contract_data_frame
from hil.replay_feed import (CONTROL_PERIOD_NS, DEFAULT_ACK_TIMEOUT_S, NS_PER_S, InputWrapper,
                             ReplayClock, ReplayRun, expected_from_log, replay_log)
from hil.replay_outputs import (COMPARED_IDS, COMPARED_SIGNALS, DEFAULT_TOLERANCES,
                                MEASURED_TIMING_SIGNALS, SIGNAL_UNITS, Comparison, Divergence,
                                OutputFrame, ReplayError, SignalDiff, compare_outputs,
                                exact_masks, normalise_timing, read_reference,
                                reference_path_for, write_reference)

__all__ = [
    "COMPARED_IDS", "COMPARED_SIGNALS", "CONTROL_PERIOD_NS", "DEFAULT_ACK_TIMEOUT_S",
    "DEFAULT_TOLERANCES", "MEASURED_TIMING_SIGNALS", "SIGNAL_UNITS", "Comparison", "Divergence",
    "InputWrapper", "OutputFrame", "ReplayClock", "ReplayError", "ReplayReport", "ReplayRun", "SignalDiff",
    "check_has_inputs", "compare_outputs", "default_paths_for", "exact_masks", "expected_from_log",
    "normalise_timing", "read_reference", "reference_path_for", "replay_log", "run_replay",
    "write_reference",
]


@dataclass
class ReplayReport:
    """Outcome of replaying one log: where things came from, the run and the comparison."""

    log: str
    controller: str
    controller_source: str
    paths: dict[int, str]
    paths_source: str
    time_base: str
    expected_source: str
    run: ReplayRun
    comparison: Comparison
    log_contents: LogContents
    notes: list[str] = field(default_factory=list)
    #: The ECU's other inputs and where they came from ("model: FILE (from the sidecar)").
    setup: list[str] = field(default_factory=list)
    #: How the report counts and names the log's frames (``--dbc``): a cantools database
    #: and its name, None for the contract's DBC. Never what the replayed ECU uses.
    display_database: Any = None
    dbc_name: str = ""

    @property
    def match(self) -> bool:
        """True when the replayed frames match the expected ones (and the replay ran through)."""
        return self.comparison.match and self.run.aborted is None

    def text(self, writing: bool = False) -> str:
        """The human-readable report; ``writing``: the replay wrote reference outputs and
        the comparison is for information."""
        c = self.comparison
        lines = [f"replay of {self.log}",
                 f"  controller: {self.controller} ({self.controller_source})",
                 "  paths: " + ", ".join(f"{k}={v}" for k, v in sorted(self.paths.items()))
                 + f" ({self.paths_source})",
                 *(f"  {line}" for line in self.setup),
                 f"  time base: {self.time_base}",
                 f"  fed {self.run.frames_fed} frames"
                 + (f", {self.run.acks} HIL_SYNC acknowledged" if self.run.lockstep
                    else f", {self.run.control_releases} control releases")
                 + f", in {self.run.wall_time_s:.2f} s of wall clock (ECU start-up included)",
                 f"  compared with: {self.expected_source}",
                 f"  comparison: {_mode_text(c.mode)}",
                 f"  frames: expected {c.expected}, replayed {c.replayed}, paired {c.paired}, "
                 f"missing {c.missing}, extra {c.extra}, mismatched {c.mismatched_frames}"
                 + (f" ({c.extra_ignored} replayed after the end of the cut log not counted)"
                    if c.extra_ignored else "")]
        lines.append("  max |replayed - expected| per signal:")
        for signal, stats in c.signals.items():
            unit = SIGNAL_UNITS.get(signal.split(".")[1], "")
            beyond = f", {stats.mismatches} frame(s) differ" if stats.mismatches else ""
            lines.append(f"    {signal:<34} {stats.max_abs_diff:.6g} {unit}".rstrip()
                         + f"  ({stats.compared} compared{beyond})")
        lines.append("    not compared (measured timing): CTRL_DIAG."
                     + ", CTRL_DIAG.".join(s.lower() for s in MEASURED_TIMING_SIGNALS))
        lines.append("  first divergence: "
                     + (c.first_divergence.text() if c.first_divergence else "none"))
        for note in self.run.notes + self.notes:
            lines.append(f"  note: {note}")
        if self.run.aborted:
            lines.append(f"  replay aborted: {self.run.aborted}")
        if self.log_contents.warnings:
            lines.append(f"  log: {len(self.log_contents.warnings)} warning(s), printed on "
                         "stderr and in the JSON report")
        if self.display_database is not None:
            lines.extend("  log " + line.strip() for line in self.log_contents.summary_lines(
                self.display_database, self.dbc_name)[1:])
        if self.log_contents.unknown_ids:
            lines.append(f"  log: {sum(self.log_contents.unknown_ids.values())} frame(s) with IDs "
                         "outside the contract's DBC were fed as they are")
        result = "MATCH" if self.match else "DIFFERENT"
        if not self.log_contents.complete:
            result += " (the log is incomplete: compared up to where it ends)"
        if writing:
            lines.append(f"  result: reference outputs written; compared with "
                         f"{self.expected_source}: {result} (for information)")
        else:
            lines.append(f"  result: {result}")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""
        c = self.comparison
        first = c.first_divergence
        return {
            "log": self.log, "controller": self.controller, "setup": list(self.setup),
            "time_base": self.time_base,
            "compared_with": self.expected_source, "mode": c.mode, "match": self.match,
            "frames": {"expected": c.expected, "replayed": c.replayed, "paired": c.paired,
                       "missing": c.missing, "extra": c.extra,
                       "mismatched": c.mismatched_frames},
            "max_abs_diff": {k: v.max_abs_diff for k, v in c.signals.items()},
            "first_divergence": None if first is None else {
                "time_s": first.time_s, "frame": first.frame, "signal": first.signal,
                "expected": str(first.expected), "replayed": str(first.actual)},
            "aborted": self.run.aborted, "wall_time_s": self.run.wall_time_s,
            "log_complete": self.log_contents.complete,
            "log_warnings": list(self.log_contents.warnings),
            "notes": self.run.notes + self.notes,
        }


def _mode_text(mode: str) -> str:
    if mode == "exact":
        return ("bit for bit, except CTRL_DIAG " + ", ".join(MEASURED_TIMING_SIGNALS)
                + " and its CRC")
    return "per signal with tolerances"


def default_paths_for(contents: LogContents, default_file: Path) -> dict[int, Path]:
    """PATH_ID -> ``default_file`` for every PATH_ID the log's planner requested (1 when
    it requested none)."""
    ids = set()
    for message in contents.messages:
        if (is_contract_data_frame(message) and message.arbitration_id == FrameId.PLANNER_REQ
                and len(message.data) == 8):
            try:
                frame = decode(FrameId.PLANNER_REQ, bytes(message.data)).frame
            except CanDefsError:
                continue
            if isinstance(frame, PlannerReq):
                ids.add(frame.path_id)
    return {path_id: default_file for path_id in sorted(ids or {1})}


def check_has_inputs(contents: LogContents) -> None:
    """Refuse a log without any of the ECU's inputs: replaying it would feed the ECU
    nothing and compare nothing it computed.

    Raises:
        ReplayError: no contract frame other than the ECU's own (HIL_SYNC_ACK,
            STEER_TORQUE_CMD, CTRL_DIAG) is in the log.
    """
    if any(fid not in ECU_OUTPUT_IDS for fid in contents.frames_by_id):
        return
    wanted = ", ".join(fid.name for fid in FrameId if fid not in ECU_OUTPUT_IDS)
    raise ReplayError(
        f"{contents.path}: the log holds none of the ECU's input frames ({wanted}): nothing "
        "to replay (a log of another bus? show it with: eso-hil decode LOG --dbc ITS.dbc)")


def run_replay(contents: LogContents, controller: str, paths: Mapping[int, Path], *,
               controller_source: str = "given", paths_source: str = "given",
               reference: str | Path | None = None, mode: str | None = None,
               tolerances: Mapping[str, float] | None = None, realtime: bool = False,
               ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
               controller_factory: Callable[[str], Any] | None = None, excitation: Any = None,
               allow_no_expected: bool = False, display_database: Any = None,
               dbc_name: str = "", wrap_inputs: InputWrapper | None = None) -> ReplayReport:
    """Replay a log and compare: with ``reference`` (a file of `write_reference`) when
    given, else with the ECU frames recorded in the log. ``display_database`` /
    ``dbc_name``: how the report counts the log's frames (``--dbc``); ``wrap_inputs``:
    wraps the frames as they are fed (a progress bar); ``controller_factory`` and
    ``excitation``: the ECU's ``--model`` and ``--excite`` (`replay_log`).

    Raises:
        ReplayError: the log holds none of the ECU's inputs (nothing to replay), nothing
            to compare with (no ECU frames in the log and no reference, unless
            ``allow_no_expected``: writing references), the ECU could not start, a bad
            comparison mode.
    """
    check_has_inputs(contents)
    notes: list[str] = []
    _, time_base = frame_times(contents.messages)
    if reference is not None:
        expected, reference_contents = read_reference(reference)
        expected_source = f"reference outputs {reference}"
        notes.extend(f"reference: {w}" for w in reference_contents.warnings)
    else:
        expected = expected_from_log(contents)
        if not expected and allow_no_expected:
            expected_source = "nothing (the log holds no ECU frames)"
        elif not expected:
            raise ReplayError(
                f"{contents.path}: the log holds no STEER_TORQUE_CMD or CTRL_DIAG frame to "
                "compare with; pass --ref FILE (reference outputs), or --write-ref FILE to "
                "record this replay's outputs")
        else:
            expected_source = "the ECU frames recorded in the log"
    # A reference was written by a replay, which is deterministic on either time base.
    mode = mode or ("exact" if contents.is_lockstep or reference is not None else "tolerance")
    if mode not in ("exact", "tolerance"):
        raise ReplayError(f"comparison mode must be 'exact' or 'tolerance', got {mode!r}")
    expected_end = max((f.time_s for f in expected), default=None)
    run = replay_log(contents, controller, paths, realtime=realtime, ack_timeout_s=ack_timeout_s,
                     expected_end_s=expected_end, controller_factory=controller_factory,
                     excitation=excitation,
                     wrap_inputs=wrap_inputs)
    cut_short = not contents.complete or run.aborted is not None
    if reference is None and not contents.is_lockstep:
        notes.append("without HIL_SYNC the recorded ECU's control instants and input ages are only "
                     "known from the timestamps: differences within the tolerances are expected")
    comparison = compare_outputs(
        expected, run.outputs, mode=mode, tolerances=tolerances,
        window_s=0.0 if contents.is_lockstep else CONTROL_PERIOD_NS / NS_PER_S / 2,
        ignore_extra_after_s=expected_end if cut_short else None)
    return ReplayReport(
        log=str(contents.path), controller=controller, controller_source=controller_source,
        paths={k: str(v) for k, v in paths.items()}, paths_source=paths_source,
        time_base=time_base + ("; ECU in lockstep" if contents.is_lockstep
                               else "; ECU on an injected clock"),
        expected_source=expected_source, run=run, comparison=comparison,
        log_contents=contents, notes=notes, display_database=display_database,
        dbc_name=dbc_name)
