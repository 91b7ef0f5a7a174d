"""Frames of other kinds on the ECU's receive IDs, for tests/test_vcan_odd_frames.py: the
time master's send hook that adds them, a probe socket that checks vcan0 carried them,
and (run as a script, inside user-mode Linux) the lockstep driver that does both.

The schedule is a row of windows of virtual time, one frame kind each; inside a window,
every frame the plant and the planner send at a tick is followed by one odd frame of the
same ID number, and each tick adds one odd HIL_SYNC carrying the handshake TICK
0xFFFFFFFF (sent before the tick's own HIL_SYNC, so an ECU that took it would restart its
virtual clock). Kinds:

- ``fd`` / ``fd_brs``: a CAN FD frame (without / with bit-rate switch) carrying the real
  frame with the next alive counter and a valid CRC (`hil.fault_frames.lookalike`): taken for
  the contract frame, it would make the real next frame a repeat (stale, FAULTS bit 1).
- ``remote``: a remote frame (RTR) asking for 8 bytes.
- ``error``: an error frame whose ID bits (the error class) are the contract ID's number,
  with the real frame's bytes.
- ``wrong_dlc``: a classic data frame of 0..7 bytes (cycling with the tick): the real
  frame with the next counter, cut short; the HIL_SYNC one is 4 bytes of 0xFFFFFFFF.

The contract (rev. 2, "Receiving rules") ignores the first four kinds before any other
rule, never setting a FAULTS bit; the fifth are contract frames of the wrong length:
discarded and counted as E2E errors (FAULTS bit 1 in the next CTRL_DIAG).
"""
from __future__ import annotations

import json
import sys
from collections import Counter
from collections.abc import Sequence

import can

from can_defs.codec import encode
from can_defs.frames import FRAME_LENGTH, HANDSHAKE_TICK, TICK_STEP_MS, FrameId, HilSync
from hil.fault_frames import lookalike

#: The ECU's receive IDs (the probe listens to these).
RECEIVE_IDS = (int(FrameId.HIL_SYNC), int(FrameId.VEH_DYN), int(FrameId.VEH_POSE_XY),
               int(FrameId.VEH_POSE_YAW), int(FrameId.PLANNER_REQ))
#: (kind, first tick ms, end tick ms exclusive): one kind per window, the ECU ACTIVE from
#: its second cycle (25 ms), clean cycles after the last window.
WINDOWS: tuple[tuple[str, int, int], ...] = (
    ("fd", 100, 300), ("fd_brs", 300, 500), ("remote", 500, 700), ("error", 700, 900),
    ("wrong_dlc", 900, 1100))
KINDS = tuple(kind for kind, _, _ in WINDOWS)
#: Printed by the driver before a JSON object {"sent": {kind: n}, "seen": {kind: n}}.
REPORT_PREFIX = "ODD-FRAMES "


def window_kind(tick_ms: int) -> str | None:
    """The odd frame kind injected at ``tick_ms`` (None: a clean tick)."""
    return next((kind for kind, start, end in WINDOWS if start <= tick_ms < end), None)


def odd_frame(message: can.Message, kind: str, tick_ms: int) -> can.Message:
    """``message`` (a contract frame of the plant, planner or time master) as a frame of
    ``kind`` with the same ID number (see the module docstring)."""
    if kind in ("fd", "fd_brs", "remote", "error"):
        odd = lookalike(message, "fd" if kind == "fd_brs" else kind)
        odd.bitrate_switch = kind == "fd_brs"
        return odd
    assert kind == "wrong_dlc", kind
    if message.arbitration_id == FrameId.HIL_SYNC:
        return can.Message(arbitration_id=message.arbitration_id, is_extended_id=False,
                           data=HANDSHAKE_TICK.to_bytes(4, "little"))
    next_frame = bytes(lookalike(message, "fd").data)    # next counter, valid CRC
    length = (tick_ms // TICK_STEP_MS + message.arbitration_id) % FRAME_LENGTH
    return can.Message(arbitration_id=message.arbitration_id, is_extended_id=False,
                       data=next_frame[:length])


def classify(message: can.Message) -> str | None:
    """The odd kind of a received frame, None for a classic 8-byte data frame."""
    if message.is_error_frame:
        return "error"
    if message.is_remote_frame:
        return "remote"
    if message.is_fd:
        return "fd_brs" if message.bitrate_switch else "fd"
    return "wrong_dlc" if len(message.data) != FRAME_LENGTH else None


class OddFrameInjector:
    """The time master's send hook (`hil.time_master.SendHook`) adding the odd frames of
    `WINDOWS`, and the count of what a probe socket on the same bus received of them.

    Args:
        probe: a bus that receives CAN FD, remote and error frames of `RECEIVE_IDS`; read
            without waiting at each tick (so it wakes nothing while the plant integrates).
    """

    def __init__(self, probe: can.BusABC) -> None:
        self.probe = probe
        self.sent: Counter[str] = Counter()
        self.seen: Counter[str] = Counter()

    def outgoing(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        """``frames`` with the odd frames of ``tick_ms``'s window after each, plus one odd
        HIL_SYNC carrying the handshake TICK."""
        self.drain()
        kind = window_kind(tick_ms)
        if kind is None:
            return frames
        handshake = can.Message(arbitration_id=int(FrameId.HIL_SYNC), is_extended_id=False,
                                data=encode(HilSync(HANDSHAKE_TICK)))
        out = [odd_frame(handshake, kind, tick_ms)]
        for message in frames:
            out += [message, odd_frame(message, kind, tick_ms)]
        self.sent[kind] += len(out) - len(frames)
        return out

    def drain(self) -> None:
        """Count the odd frames the probe has received so far."""
        while (message := self.probe.recv(timeout=0)) is not None:
            kind = classify(message)
            if kind is not None:
                self.seen[kind] += 1

    def report(self) -> str:
        """One line: `REPORT_PREFIX` and {"sent": ..., "seen": ...} per kind."""
        return REPORT_PREFIX + json.dumps({"sent": dict(self.sent), "seen": dict(self.seen)})


def main(argv: Sequence[str]) -> int:
    """``python tests/vcan_odd_frames.py SCENARIO CONTROLLER ECU_PROGRAM...``: the lockstep
    run of `vcan_support.drive_lockstep` with the odd frames injected and probed; prints
    `OddFrameInjector.report` and exits with the ECU's status."""
    from vcan_support import drive_lockstep

    filters = [{"can_id": frame_id, "can_mask": 0x7FF, "extended": False} for frame_id in RECEIVE_IDS]
    probe = can.Bus(interface="socketcan", channel="vcan0", fd=True, can_filters=filters)
    try:
        injector = OddFrameInjector(probe)
        status = drive_lockstep(argv[0], argv[1], argv[2:], send_hook=injector.outgoing, fd=True)
        injector.drain()
    finally:
        probe.shutdown()
    print(injector.report())
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
