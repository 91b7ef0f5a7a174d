"""Log replay: re-run the ECU on the inputs of a recorded CAN log and compare its outputs.

As openpilot's process_replay: a recorded log supplies the ECU's inputs (plant and planner
frames, HIL_SYNC, foreign frames); the ECU (`firmware_sim.ecu.Ecu`, in this process, on a
private virtual CAN channel) answers; its STEER_TORQUE_CMD and CTRL_DIAG frames are
compared with expected ones: the ECU frames recorded in the log, or a reference file
written by an earlier replay (``make replay-refs``).

Time bases:

- lockstep log (has HIL_SYNC): the protocol is respected. Frames are sent in log order;
  after each HIL_SYNC the replay waits for the ECU's HIL_SYNC_ACK of that TICK before it
  sends anything else (the handshake 0xFFFFFFFF too; a log without a handshake gets one
  before its first TICK). The ECU runs `Ecu.run` in a thread, as a node on a bus.
- any other log: the ECU runs in real-time mode on an injected clock that follows the log
  timestamps; the replay calls `Ecu.poll` at the control releases (every 25 ms, phased on
  the first STEER_TORQUE_CMD of the log when it has one) and `Ecu.handle_message` at each
  frame's timestamp, so the control task runs at the right moments whatever the machine.

Comparison: ``exact`` (default for lockstep logs) compares payloads bit for bit except
CTRL_DIAG's measured timing signals (SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS) and its CRC,
which covers them; ``tolerance`` (default otherwise) compares decoded signals with
per-signal tolerances. Frames are paired per ID by time (equal virtual time in lockstep,
within half a control period otherwise) and order.
"""
from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import can

from can_defs.codec import decode
from can_defs.crc import e2e_crc
from can_defs.dbc import load_database
from can_defs.errors import CanDefsError
from can_defs.frames import (HANDSHAKE_TICK, TICK_STEP_MS, CtrlMode, FrameId, HilSync,
                             PlannerReq, QpStatus)
from hil.bus import private_virtual_channel
from hil.errors import HilError
from hil.logio import (ECU_OUTPUT_IDS, LogContents, frame_times, is_contract_data_frame,
                       read_log, sync_tick)

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

CONTROL_PERIOD_NS = 25_000_000
#: Wall-clock wait for one HIL_SYNC_ACK.
DEFAULT_ACK_TIMEOUT_S = 10.0
_NS_PER_S = 1_000_000_000


class ReplayError(HilError):
    """The replay cannot run (unknown controller, ECU failed to start, bad reference)."""


@dataclass(frozen=True)
class OutputFrame:
    """One ECU frame at a replay time (s): virtual time in lockstep, log time otherwise."""

    time_s: float
    arbitration_id: int
    data: bytes


@dataclass
class ReplayRun:
    """What feeding a log into the ECU produced."""

    outputs: list[OutputFrame]
    lockstep: bool
    frames_fed: int = 0
    acks: int = 0
    control_releases: int = 0
    aborted: str | None = None
    notes: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0


class ReplayClock:
    """Monotonic clock (s) the replay sets: the ECU reads the log's time from it."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


# --- feeding the ECU ------------------------------------------------------------------


def _copy_for_bus(message: can.Message) -> can.Message:
    """A log frame as it goes out again (no channel, no timestamp, same bits)."""
    return can.Message(arbitration_id=message.arbitration_id, data=bytes(message.data or b""),
                       is_extended_id=message.is_extended_id,
                       is_remote_frame=message.is_remote_frame,
                       is_error_frame=message.is_error_frame, dlc=message.dlc,
                       is_fd=message.is_fd)


def _input_frames(contents: LogContents) -> tuple[list[can.Message], list[float]]:
    """The ECU's inputs (every frame it did not send) and their times (s)."""
    times, _ = frame_times(contents.messages)
    inputs, input_times = [], []
    for message, time_s in zip(contents.messages, times):
        if is_contract_data_frame(message) and message.arbitration_id in ECU_OUTPUT_IDS:
            continue
        inputs.append(message)
        input_times.append(time_s)
    return inputs, input_times


def expected_from_log(contents: LogContents) -> list[OutputFrame]:
    """The ECU frames recorded in a log, on the log's time base (`frame_times`)."""
    times, _ = frame_times(contents.messages)
    return [OutputFrame(time_s, m.arbitration_id, bytes(m.data))
            for m, time_s in zip(contents.messages, times)
            if is_contract_data_frame(m) and m.arbitration_id in COMPARED_IDS]


def _make_ecu(bus: can.BusABC, controller: str, paths: Mapping[int, Path], lockstep: bool,
              clock: Callable[[], float], controller_factory: Any) -> Any:
    from firmware_sim.ecu import Ecu  # the ECU package, only needed to replay

    kwargs = {} if controller_factory is None else {"controller_factory": controller_factory}
    try:
        ecu = Ecu(bus, controller, dict(paths), lockstep=lockstep, clock=clock, **kwargs)
    except Exception as error:
        raise ReplayError(f"cannot start the ECU with controller {controller!r}: {error}") from error
    if ecu.load_error:
        ecu.close()
        raise ReplayError(f"the ECU latched FAULT at start-up: {ecu.load_error}")
    return ecu


def replay_log(contents: LogContents, controller: str, paths: Mapping[int, Path], *,
               realtime: bool = False, ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
               expected_end_s: float | None = None,
               controller_factory: Callable[[str], Any] | None = None) -> ReplayRun:
    """Feed the log's inputs into a fresh ECU and collect its frames (module docstring).

    Args:
        contents: the log.
        controller: registry name of the ECU's controller.
        paths: PATH_ID -> reference path CSV loaded by the ECU.
        realtime: pace the frames by the log's timestamps on the wall clock.
        ack_timeout_s: lockstep: wall-clock wait for each HIL_SYNC_ACK.
        expected_end_s: time-stamped logs: run the control releases up to this time (the
            last recorded ECU frame) after the last input, then stop the ECU there.
        controller_factory: replaces the controller registry (tests).

    Raises:
        ReplayError: the ECU could not start. A missing ACK ends the replay early with
        ``aborted`` set and the outputs so far.
    """
    channel = private_virtual_channel("replay")
    started = time.perf_counter()
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    feeder = can.Bus(interface="virtual", channel=channel)
    try:
        if contents.is_lockstep:
            run = _replay_lockstep(contents, controller, paths, ecu_bus, feeder, realtime,
                                   ack_timeout_s, controller_factory)
        else:
            run = _replay_timestamped(contents, controller, paths, ecu_bus, feeder, realtime,
                                      expected_end_s, controller_factory)
        run.wall_time_s = time.perf_counter() - started
        return run
    finally:
        feeder.shutdown()
        ecu_bus.shutdown()


class _Pacer:
    """Sleeps until a log time on the wall clock (``--realtime``), or does nothing."""

    def __init__(self, enabled: bool, first_timestamp: float) -> None:
        self.enabled = enabled
        self.first_timestamp = first_timestamp
        self.wall_start = time.monotonic()

    def wait_for(self, timestamp: float) -> None:
        if self.enabled:
            delay = self.wall_start + (timestamp - self.first_timestamp) - time.monotonic()
            if delay > 0:
                time.sleep(delay)


def _replay_lockstep(contents: LogContents, controller: str, paths: Mapping[int, Path],
                     ecu_bus: can.BusABC, feeder: can.BusABC, realtime: bool,
                     ack_timeout_s: float, controller_factory: Any) -> ReplayRun:
    inputs, _ = _input_frames(contents)
    run = ReplayRun(outputs=[], lockstep=True)
    ecu = _make_ecu(ecu_bus, controller, paths, True, time.monotonic, controller_factory)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,), name="replay-ecu", daemon=True)
    thread.start()
    current_tick_s = 0.0
    synchronised = False
    last_tick: int | None = None
    pacer = _Pacer(realtime, inputs[0].timestamp if inputs else 0.0)

    def await_ack(tick: int) -> None:
        give_up = time.monotonic() + ack_timeout_s
        while (remaining := give_up - time.monotonic()) > 0:
            message = feeder.recv(timeout=remaining)
            if message is None:
                break
            if _collect(run, message, current_tick_s) == tick:
                run.acks += 1
                return
        raise _AckMissing(tick)

    try:
        first_sync = next((sync_tick(m) for m in inputs if sync_tick(m) is not None), None)
        if first_sync is not None and first_sync != HANDSHAKE_TICK:
            run.notes.append("the log has no lockstep handshake: one was sent before its first TICK")
            feeder.send(_sync_frame(HANDSHAKE_TICK))
            await_ack(HANDSHAKE_TICK)
            synchronised = True
        for message in inputs:
            pacer.wait_for(message.timestamp)
            feeder.send(_copy_for_bus(message))
            run.frames_fed += 1
            tick = sync_tick(message) if message.arbitration_id == FrameId.HIL_SYNC else None
            if tick is None:
                continue
            if tick == HANDSHAKE_TICK:
                synchronised, last_tick = True, None
                await_ack(tick)
            elif synchronised and tick % TICK_STEP_MS == 0 and (last_tick is None or tick >= last_tick):
                # The contract's ECU answers these (a repeated TICK again, running nothing);
                # ticks before the handshake, backwards or off the 5 ms grid get no ACK.
                current_tick_s = tick / 1000.0
                last_tick = tick
                await_ack(tick)
    except _AckMissing as missing:
        run.aborted = (f"no HIL_SYNC_ACK for TICK={_tick_text(missing.tick)} within "
                       f"{ack_timeout_s:g} s: replay stopped after {run.frames_fed} frames")
    finally:
        stop.set()
        thread.join(timeout=5.0)
        ecu.close()  # its last STEER_TORQUE_CMD (CMD_VALID = 0) is an output too
        while (message := feeder.recv(timeout=0.05)) is not None:
            _collect(run, message, current_tick_s)
    return run


class _AckMissing(Exception):
    def __init__(self, tick: int) -> None:
        super().__init__(tick)
        self.tick = tick


def _tick_text(tick: int) -> str:
    return "0xFFFFFFFF (handshake)" if tick == HANDSHAKE_TICK else f"{tick} ms"


def _sync_frame(tick: int) -> can.Message:
    from can_defs.codec import encode

    return can.Message(arbitration_id=int(FrameId.HIL_SYNC), data=encode(HilSync(tick)),
                       is_extended_id=False)


def _collect(run: ReplayRun, message: can.Message, time_s: float) -> int | None:
    """Keep an ECU frame; returns the TICK when it is a HIL_SYNC_ACK."""
    if not is_contract_data_frame(message):
        return None
    if message.arbitration_id == FrameId.HIL_SYNC_ACK:
        return sync_tick(message)
    if message.arbitration_id in COMPARED_IDS:
        run.outputs.append(OutputFrame(time_s, message.arbitration_id, bytes(message.data)))
    return None


def _replay_timestamped(contents: LogContents, controller: str, paths: Mapping[int, Path],
                        ecu_bus: can.BusABC, feeder: can.BusABC, realtime: bool,
                        expected_end_s: float | None, controller_factory: Any) -> ReplayRun:
    inputs, input_times = _input_frames(contents)
    run = ReplayRun(outputs=[], lockstep=False)
    clock = ReplayClock()
    ecu = _make_ecu(ecu_bus, controller, paths, False, clock, controller_factory)
    recorded_commands = [t for m, t in zip(contents.messages, frame_times(contents.messages)[0])
                         if is_contract_data_frame(m) and m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    # The recorded ECU ran its first control task just before its first command: phase the
    # releases on it, so each task sees the inputs the recorded one saw.
    first_release_s = recorded_commands[0] if recorded_commands else (input_times[0] if input_times else 0.0)
    release_ns = round(first_release_s * _NS_PER_S)
    run.notes.append(f"no HIL_SYNC in the log: the ECU ran in real-time mode on a clock that "
                     f"follows the log timestamps; control releases every 25 ms from "
                     f"t = {first_release_s:.6f} s"
                     + (" (the log's first STEER_TORQUE_CMD)" if recorded_commands else ""))
    pacer = _Pacer(realtime, 0.0)
    now_s = 0.0

    def release_until(limit_ns: int) -> None:
        """Run the control releases before ``limit_ns``: a frame stamped at a release
        instant counts as received before it (as frames before a HIL_SYNC in lockstep)."""
        nonlocal release_ns
        while release_ns < limit_ns:
            clock.now_s = release_ns / _NS_PER_S
            ecu.poll()
            run.control_releases += 1
            _drain(feeder, run, clock.now_s)
            release_ns += CONTROL_PERIOD_NS

    try:
        for message, time_s in zip(inputs, input_times):
            # A monotonic clock never goes back: a frame stamped earlier than the one
            # before it (threads of the recorder) is taken as arriving with it.
            time_s = max(time_s, now_s)
            pacer.wait_for(time_s)
            release_until(round(time_s * _NS_PER_S))
            now_s = clock.now_s = time_s
            ecu.handle_message(_copy_for_bus(message))
            run.frames_fed += 1
            _drain(feeder, run, now_s)
        end_s = max(now_s, expected_end_s if expected_end_s is not None else now_s)
        # The recorded ECU's last frame is its shutdown command: release the control task up
        # to just before it, then stop the ECU at that time.
        release_until(round(end_s * _NS_PER_S))
        clock.now_s = end_s
    finally:
        ecu.close()
        _drain(feeder, run, clock.now_s)
    return run


def _drain(feeder: can.BusABC, run: ReplayRun, time_s: float) -> None:
    while (message := feeder.recv(timeout=0.0)) is not None:
        _collect(run, message, time_s)


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


# --- the whole replay -----------------------------------------------------------------


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

    @property
    def match(self) -> bool:
        """True when the replayed frames match the expected ones (and the replay ran through)."""
        return self.comparison.match and self.run.aborted is None

    def text(self) -> str:
        """The human-readable report."""
        c = self.comparison
        lines = [f"replay of {self.log}",
                 f"  controller: {self.controller} ({self.controller_source})",
                 "  paths: " + ", ".join(f"{k}={v}" for k, v in sorted(self.paths.items()))
                 + f" ({self.paths_source})",
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
        for warning in self.log_contents.warnings:
            lines.append(f"  log warning: {warning}")
        if self.log_contents.unknown_ids:
            lines.append(f"  log: {sum(self.log_contents.unknown_ids.values())} frame(s) with IDs "
                         "outside the DBC were fed as they are")
        lines.append("  result: " + ("MATCH" if self.match else "DIFFERENT"))
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""
        c = self.comparison
        first = c.first_divergence
        return {
            "log": self.log, "controller": self.controller, "time_base": self.time_base,
            "compared_with": self.expected_source, "mode": c.mode, "match": self.match,
            "frames": {"expected": c.expected, "replayed": c.replayed, "paired": c.paired,
                       "missing": c.missing, "extra": c.extra,
                       "mismatched": c.mismatched_frames},
            "max_abs_diff": {k: v.max_abs_diff for k, v in c.signals.items()},
            "first_divergence": None if first is None else {
                "time_s": first.time_s, "frame": first.frame, "signal": first.signal,
                "expected": str(first.expected), "replayed": str(first.actual)},
            "aborted": self.run.aborted, "wall_time_s": self.run.wall_time_s,
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


def run_replay(contents: LogContents, controller: str, paths: Mapping[int, Path], *,
               controller_source: str = "given", paths_source: str = "given",
               reference: str | Path | None = None, mode: str | None = None,
               tolerances: Mapping[str, float] | None = None, realtime: bool = False,
               ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
               controller_factory: Callable[[str], Any] | None = None,
               allow_no_expected: bool = False) -> ReplayReport:
    """Replay a log and compare: with ``reference`` (a file of `write_reference`) when
    given, else with the ECU frames recorded in the log.

    Raises:
        ReplayError: nothing to compare with (no ECU frames in the log and no reference,
            unless ``allow_no_expected``: writing references), the ECU could not start, a
            bad comparison mode.
    """
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
                     expected_end_s=expected_end, controller_factory=controller_factory)
    cut_short = not contents.complete or run.aborted is not None
    if reference is None and not contents.is_lockstep:
        notes.append("without HIL_SYNC the recorded ECU's control instants and input ages are only "
                     "known from the timestamps: differences within the tolerances are expected")
    comparison = compare_outputs(
        expected, run.outputs, mode=mode, tolerances=tolerances,
        window_s=0.0 if contents.is_lockstep else CONTROL_PERIOD_NS / _NS_PER_S / 2,
        ignore_extra_after_s=expected_end if cut_short else None)
    return ReplayReport(
        log=str(contents.path), controller=controller, controller_source=controller_source,
        paths={k: str(v) for k, v in paths.items()}, paths_source=paths_source,
        time_base=time_base + ("; ECU in lockstep" if contents.is_lockstep
                               else "; ECU on an injected clock"),
        expected_source=expected_source, run=run, comparison=comparison,
        log_contents=contents, notes=notes)
