"""Feeding a recorded CAN log into a fresh ECU and collecting its output frames.

The ECU (`firmware_sim.ecu.Ecu`, in this process, on a private virtual CAN channel) gets
the log's inputs (plant and planner frames, HIL_SYNC, foreign frames) and answers.

Time bases:

- lockstep log (has HIL_SYNC): the protocol is respected. Frames are sent in log order;
  after each HIL_SYNC the replay waits for the ECU's HIL_SYNC_ACK of that TICK before it
  sends anything else (the handshake 0xFFFFFFFF too; a log without a handshake gets one
  before its first TICK). The ECU runs `Ecu.run` in a thread, as a node on a bus.
- any other log: the ECU runs in real-time mode on an injected clock that follows the log
  timestamps; the replay calls `Ecu.poll` at the control releases (every 25 ms, phased on
  the first STEER_TORQUE_CMD of the log when it has one) and `Ecu.handle_message` at each
  frame's timestamp, so the control task runs at the right moments whatever the machine.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from can_defs.frames import HANDSHAKE_TICK, TICK_STEP_MS, FrameId, HilSync
from hil.bus import BusConfig, open_bus, private_virtual_channel
from hil.logio import ECU_OUTPUT_IDS, LogContents, frame_times, is_contract_data_frame, sync_tick
from hil.replay_outputs import COMPARED_IDS, OutputFrame, ReplayError

CONTROL_PERIOD_NS = 25_000_000
#: Wall-clock wait for one HIL_SYNC_ACK.
DEFAULT_ACK_TIMEOUT_S = 10.0
NS_PER_S = 1_000_000_000


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
              clock: Callable[[], float], ecu_options: Mapping[str, Any]) -> Any:
    from firmware_sim.ecu import Ecu  # the ECU package, only needed to replay

    try:
        ecu = Ecu(bus, controller, dict(paths), lockstep=lockstep, clock=clock, **ecu_options)
    except Exception as error:
        raise ReplayError(f"cannot start the ECU with controller {controller!r}: {error}") from error
    if ecu.load_error:
        ecu.close()
        raise ReplayError(f"the ECU latched FAULT at start-up: {ecu.load_error}")
    return ecu


def replay_log(contents: LogContents, controller: str, paths: Mapping[int, Path], *,
               realtime: bool = False, ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
               expected_end_s: float | None = None,
               controller_factory: Callable[[str], Any] | None = None,
               excitation: Any = None,
               wrap_inputs: InputWrapper | None = None) -> ReplayRun:
    """Feed the log's inputs into a fresh ECU and collect its frames (module docstring).

    Args:
        contents: the log.
        controller: registry name of the ECU's controller.
        paths: PATH_ID -> reference path CSV loaded by the ECU.
        realtime: pace the frames by the log's timestamps on the wall clock.
        ack_timeout_s: lockstep: wall-clock wait for each HIL_SYNC_ACK.
        expected_end_s: time-stamped logs: run the control releases up to this time (the
            last recorded ECU frame) after the last input, then stop the ECU there.
        controller_factory: replaces the controller registry (another model file,
            ``firmware_sim.controller_factory.model_controller_factory``; tests).
        excitation: the ECU's identification excitation program
            (``firmware_sim.excitation.load_excitation``), None for none.
        wrap_inputs: wraps the sequence of input frames as it is fed (a progress bar).

    Raises:
        ReplayError: the ECU could not start. A missing ACK ends the replay early with
        ``aborted`` set and the outputs so far.
    """
    bus = BusConfig("virtual", private_virtual_channel("replay"))
    started = time.perf_counter()
    ecu_bus = open_bus(bus)
    feeder = open_bus(bus)
    ecu_options = {name: value for name, value in (("controller_factory", controller_factory),
                                                   ("excitation", excitation)) if value is not None}
    try:
        if contents.is_lockstep:
            run = _replay_lockstep(contents, controller, paths, ecu_bus, feeder, realtime,
                                   ack_timeout_s, ecu_options, wrap_inputs or _as_is)
        else:
            run = _replay_timestamped(contents, controller, paths, ecu_bus, feeder, realtime,
                                      expected_end_s, ecu_options, wrap_inputs or _as_is)
        run.wall_time_s = time.perf_counter() - started
        return run
    finally:
        feeder.shutdown()
        ecu_bus.shutdown()


#: Wraps the input frames as they are fed (e.g. a progress bar); must yield them unchanged.
InputWrapper = Callable[[Sequence[can.Message]], Iterable[can.Message]]


def _as_is(frames: Sequence[can.Message]) -> Iterable[can.Message]:
    return frames


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
                     ack_timeout_s: float, ecu_options: Mapping[str, Any],
                     wrap_inputs: InputWrapper) -> ReplayRun:
    inputs, _ = _input_frames(contents)
    run = ReplayRun(outputs=[], lockstep=True)
    ecu = _make_ecu(ecu_bus, controller, paths, True, time.monotonic, ecu_options)
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
        for message in wrap_inputs(inputs):
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
                        expected_end_s: float | None, ecu_options: Mapping[str, Any],
                        wrap_inputs: InputWrapper) -> ReplayRun:
    inputs, input_times = _input_frames(contents)
    run = ReplayRun(outputs=[], lockstep=False)
    clock = ReplayClock()
    ecu = _make_ecu(ecu_bus, controller, paths, False, clock, ecu_options)
    recorded_commands = [t for m, t in zip(contents.messages, frame_times(contents.messages)[0])
                         if is_contract_data_frame(m) and m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    # The recorded ECU ran its first control task just before its first command: phase the
    # releases on it, so each task sees the inputs the recorded one saw.
    first_release_s = recorded_commands[0] if recorded_commands else (input_times[0] if input_times else 0.0)
    release_ns = round(first_release_s * NS_PER_S)
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
            clock.now_s = release_ns / NS_PER_S
            ecu.poll()
            run.control_releases += 1
            _drain(feeder, run, clock.now_s)
            release_ns += CONTROL_PERIOD_NS

    try:
        for message, time_s in zip(wrap_inputs(inputs), input_times):
            # A monotonic clock never goes back: a frame stamped earlier than the one
            # before it (threads of the recorder) is taken as arriving with it.
            time_s = max(time_s, now_s)
            pacer.wait_for(time_s)
            release_until(round(time_s * NS_PER_S))
            now_s = clock.now_s = time_s
            ecu.handle_message(_copy_for_bus(message))
            run.frames_fed += 1
            _drain(feeder, run, now_s)
        end_s = max(now_s, expected_end_s if expected_end_s is not None else now_s)
        # The recorded ECU's last frame is its shutdown command: release the control task up
        # to just before it, then stop the ECU at that time.
        release_until(round(end_s * NS_PER_S))
        clock.now_s = end_s
    finally:
        ecu.close()
        _drain(feeder, run, clock.now_s)
    return run


def _drain(feeder: can.BusABC, run: ReplayRun, time_s: float) -> None:
    while (message := feeder.recv(timeout=0.0)) is not None:
        _collect(run, message, time_s)
