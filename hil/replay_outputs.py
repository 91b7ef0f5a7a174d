"""The ECU's output frames in a replay: what is compared, reference files, the comparison.

Comparison: ``exact`` (default for lockstep logs) compares payloads bit for bit except
CTRL_DIAG's measured timing signals (SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS) and its CRC,
which covers them; ``tolerance`` (default otherwise) compares decoded signals with
per-signal tolerances. Frames are paired per ID by time (equal virtual time in lockstep,
within half a control period otherwise) and order.

Reference files (``make replay-refs``) are candump logs of earlier replays' outputs, with
the measured timing of CTRL_DIAG zeroed. The replay itself is `hil.replay`.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import can

from can_defs.codec import decode
from can_defs.crc import e2e_crc
from can_defs.dbc import load_database
from can_defs.errors import CanDefsError
from can_defs.frames import CtrlMode, FrameId, QpStatus
from hil.errors import HilError
from hil.logio import LogContents, is_contract_data_frame, read_log

#: ECU frames whose payloads are compared.
COMPARED_IDS: tuple[FrameId, ...] = (FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG)

#: Signals compared per frame (decoded, snake case), in report order.
COMPARED_SIGNALS: dict[FrameId, tuple[str, ...]] = {
    FrameId.STEER_TORQUE_CMD: ("ctrl_mode", "cmd_valid", "steer_angle_cmd", "drive_torque_cmd"),
    FrameId.CTRL_DIAG: ("qp_status", "qp_iter", "faults"),
}

#: CTRL_DIAG signals that report wall-clock work: never repeatable (contract, "Timing
#: semantics"), so never compared; the CRC covers them and is excluded with them.
MEASURED_TIMING_SIGNALS: tuple[str, ...] = ("SOLVE_TIME_US", "CYCLE_TIME_US", "OVERRUNS")

#: Default per-signal tolerances of the ``tolerance`` comparison (absolute, physical units).
#: Modes, validity, solver status and FAULTS must match; the iteration count depends on the
#: warm start, i.e. on the whole history, and is reported but not judged.
DEFAULT_TOLERANCES: dict[str, float] = {
    "ctrl_mode": 0.0, "cmd_valid": 0.0, "steer_angle_cmd": 2e-3, "drive_torque_cmd": 20.0,
    "qp_status": 0.0, "qp_iter": math.inf, "faults": 0.0,
}

#: Units of the compared signals, for the report.
SIGNAL_UNITS: dict[str, str] = {"steer_angle_cmd": "rad", "drive_torque_cmd": "N m"}


class ReplayError(HilError):
    """The replay cannot run (unknown controller, ECU failed to start, bad reference)."""


@dataclass(frozen=True)
class OutputFrame:
    """One ECU frame at a replay time (s): virtual time in lockstep, log time otherwise."""

    time_s: float
    arbitration_id: int
    data: bytes


# --- reference files ------------------------------------------------------------------


def reference_path_for(log_path: str | Path) -> Path:
    """Where a log's reference outputs live: ``<log name without format suffix>.ref.log``."""
    log_path = Path(log_path)
    name = log_path.name
    for suffix in reversed(log_path.suffixes):
        name = name[: -len(suffix)]
    return log_path.with_name(name + ".ref.log")


def normalise_timing(frame: OutputFrame) -> OutputFrame:
    """CTRL_DIAG with its measured timing signals set to 0 and the CRC recomputed; other
    frames unchanged. A regenerated reference then differs only where behaviour did."""
    if frame.arbitration_id != FrameId.CTRL_DIAG or len(frame.data) != 8:
        return frame
    mask = exact_masks()[int(FrameId.CTRL_DIAG)]
    data = bytearray(b & m for b, m in zip(frame.data, mask))
    data[0] = e2e_crc(FrameId.CTRL_DIAG, bytes(data))
    return OutputFrame(frame.time_s, frame.arbitration_id, bytes(data))


def write_reference(path: str | Path, outputs: Sequence[OutputFrame]) -> Path:
    """Write replay outputs as a candump log whose timestamps are the replay times, with
    the measured timing of CTRL_DIAG zeroed (`normalise_timing`)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = can.Logger(path)
    except (OSError, ValueError) as error:
        raise ReplayError(f"cannot write the reference {path}: {error}") from error
    try:
        for output in map(normalise_timing, outputs):
            writer.on_message_received(can.Message(
                timestamp=output.time_s, arbitration_id=output.arbitration_id,
                data=output.data, is_extended_id=False, channel="ecu"))
    finally:
        writer.stop()
    return path


def read_reference(path: str | Path) -> tuple[list[OutputFrame], LogContents]:
    """Expected outputs from a reference file written by `write_reference`."""
    contents = read_log(path)
    outputs = [OutputFrame(m.timestamp, m.arbitration_id, bytes(m.data))
               for m in contents.messages
               if is_contract_data_frame(m) and m.arbitration_id in COMPARED_IDS]
    if not outputs:
        raise ReplayError(f"{path}: the reference holds no STEER_TORQUE_CMD or CTRL_DIAG frame")
    return outputs, contents


# --- comparison -----------------------------------------------------------------------


@functools.cache
def exact_masks() -> dict[int, bytes]:
    """Per compared frame, the bits compared bit for bit: all but the measured timing
    signals of CTRL_DIAG and its CRC (built from the DBC's little-endian layouts)."""
    database = load_database()
    masks = {}
    for frame_id in COMPARED_IDS:
        message = database.get_message_by_frame_id(int(frame_id))
        mask = (1 << (8 * message.length)) - 1
        if frame_id == FrameId.CTRL_DIAG:
            for signal in message.signals:
                if signal.name in MEASURED_TIMING_SIGNALS or signal.name == "CRC":
                    mask &= ~(((1 << signal.length) - 1) << signal.start)
        masks[int(frame_id)] = mask.to_bytes(message.length, "little")
    return masks


@dataclass(frozen=True)
class Divergence:
    """First difference: time (s), frame name, signal, the expected and the replayed value."""

    time_s: float
    frame: str
    signal: str
    expected: Any
    actual: Any

    def text(self) -> str:
        return (f"t = {self.time_s:.3f} s, {self.frame}.{self.signal}: "
                f"expected {self.expected}, replayed {self.actual}")


@dataclass
class SignalDiff:
    """One signal over all paired frames: max |replayed - expected|, frames beyond the
    tolerance, frames compared."""

    max_abs_diff: float = 0.0
    mismatches: int = 0
    compared: int = 0


@dataclass
class Comparison:
    """Replayed vs expected ECU frames."""

    mode: str
    expected: int
    replayed: int
    paired: int = 0
    missing: int = 0
    extra: int = 0
    extra_ignored: int = 0
    mismatched_frames: int = 0
    first_divergence: Divergence | None = None
    signals: dict[str, SignalDiff] = field(default_factory=dict)
    undecodable: int = 0

    @property
    def match(self) -> bool:
        return (self.mismatched_frames == 0 and self.missing == 0 and self.extra == 0
                and self.paired > 0)

    def _note_divergence(self, divergence: Divergence) -> None:
        if self.first_divergence is None or divergence.time_s < self.first_divergence.time_s:
            self.first_divergence = divergence


def _signal_values(frame: Any, counter: int | None) -> dict[str, float]:
    values: dict[str, float] = {}
    for name in COMPARED_SIGNALS[type(frame).FRAME_ID]:
        values[name] = float(getattr(frame, name))
    if counter is not None:
        values["counter"] = float(counter)
    return values


_ENUM_SIGNALS: dict[str, type[IntEnum]] = {"ctrl_mode": CtrlMode, "qp_status": QpStatus}


def _display(name: str, value: float) -> str:
    """A signal value as the report shows it: choice names, units, integers."""
    enum_type = _ENUM_SIGNALS.get(name)
    if enum_type is not None:
        try:
            label = enum_type(int(value)).name
        except ValueError:
            label = "undefined"
        return f"{int(value)} ({label})"
    if name in SIGNAL_UNITS:
        return f"{value:.4f} {SIGNAL_UNITS[name]}"
    return str(int(value))


def _pairs(expected: list[OutputFrame], actual: list[OutputFrame], window_s: float
           ) -> tuple[list[tuple[OutputFrame, OutputFrame]], list[OutputFrame], list[OutputFrame]]:
    """Pair two time-ordered frame lists of one ID: by time within ``window_s``, in order."""
    pairs, missing, extra = [], [], []
    i = j = 0
    while i < len(expected) and j < len(actual):
        difference = actual[j].time_s - expected[i].time_s
        if abs(difference) <= window_s + 1e-9:
            pairs.append((expected[i], actual[j]))
            i += 1
            j += 1
        elif difference > 0:
            missing.append(expected[i])
            i += 1
        else:
            extra.append(actual[j])
            j += 1
    missing.extend(expected[i:])
    extra.extend(actual[j:])
    return pairs, missing, extra


def compare_outputs(expected: Sequence[OutputFrame], actual: Sequence[OutputFrame], *,
                    mode: str = "exact", tolerances: Mapping[str, float] | None = None,
                    window_s: float = 0.0, ignore_extra_after_s: float | None = None
                    ) -> Comparison:
    """Compare replayed ECU frames with expected ones (module docstring).

    Args:
        expected / actual: frames with their times; only STEER_TORQUE_CMD / CTRL_DIAG count.
        mode: ``exact`` (masked payload bits) or ``tolerance`` (decoded signals).
        tolerances: signal name -> absolute tolerance (``tolerance`` mode), over
            `DEFAULT_TOLERANCES`.
        window_s: how far apart in time two frames may be and still pair.
        ignore_extra_after_s: replayed frames after this time are not counted as extra
            (the expected log was cut short).
    """
    if mode not in ("exact", "tolerance"):
        raise ReplayError(f"comparison mode must be 'exact' or 'tolerance', got {mode!r}")
    limits = dict(DEFAULT_TOLERANCES)
    limits.update(tolerances or {})
    masks = exact_masks()
    result = Comparison(mode=mode, expected=len(expected), replayed=len(actual))
    for frame_id in COMPARED_IDS:
        name = frame_id.name
        for signal in COMPARED_SIGNALS[frame_id]:
            result.signals[f"{name}.{signal}"] = SignalDiff()
        mine = [f for f in expected if f.arbitration_id == frame_id]
        theirs = [f for f in actual if f.arbitration_id == frame_id]
        pairs, missing, extra = _pairs(mine, theirs, window_s)
        if ignore_extra_after_s is not None:
            kept = [f for f in extra if f.time_s < ignore_extra_after_s - 1e-9]
            result.extra_ignored += len(extra) - len(kept)
            extra = kept
        result.missing += len(missing)
        result.extra += len(extra)
        for frame in missing[:1]:
            result._note_divergence(Divergence(frame.time_s, name, "(frame)", "sent", "not sent"))
        for frame in extra[:1]:
            result._note_divergence(Divergence(frame.time_s, name, "(frame)", "not sent", "sent"))
        mask = masks[int(frame_id)]
        for want, got in pairs:
            result.paired += 1
            _compare_pair(result, frame_id, want, got, mode, limits, mask)
    return result


def _compare_pair(result: Comparison, frame_id: FrameId, want: OutputFrame, got: OutputFrame,
                  mode: str, limits: Mapping[str, float], mask: bytes) -> None:
    name = frame_id.name
    try:
        want_decoded, got_decoded = decode(frame_id, want.data), decode(frame_id, got.data)
    except CanDefsError as error:
        result.undecodable += 1
        result.mismatched_frames += 1
        result._note_divergence(Divergence(want.time_s, name, "(payload)", want.data.hex(),
                                   f"{got.data.hex()} ({error})"))
        return
    counters = mode == "exact"
    want_values = _signal_values(want_decoded.frame, want_decoded.counter if counters else None)
    got_values = _signal_values(got_decoded.frame, got_decoded.counter if counters else None)
    differing = []
    for signal, expected_value in want_values.items():
        difference = abs(got_values[signal] - expected_value)
        if signal != "counter":
            stats = result.signals[f"{name}.{signal}"]
            stats.compared += 1
            stats.max_abs_diff = max(stats.max_abs_diff, difference)
        if mode == "tolerance":
            if difference > limits.get(signal, 0.0):
                differing.append(signal)
                result.signals[f"{name}.{signal}"].mismatches += 1
        elif difference > 0:
            differing.append(signal)
            if signal != "counter":
                result.signals[f"{name}.{signal}"].mismatches += 1
    if mode == "exact":
        same_bits = all((a ^ b) & m == 0 for a, b, m in zip(want.data, got.data, mask)) \
            and len(want.data) == len(got.data)
        if same_bits:
            return
        if not differing:
            differing.append("(reserved bits)")
    if not differing:
        return
    result.mismatched_frames += 1
    signal = differing[0]
    if signal.startswith("("):
        result._note_divergence(Divergence(want.time_s, name, signal, want.data.hex(), got.data.hex()))
    else:
        result._note_divergence(Divergence(want.time_s, name, signal,
                                   _display(signal, want_values[signal]),
                                   _display(signal, got_values[signal])))
