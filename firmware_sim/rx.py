"""RX path of the ECU: E2E check, decode, plant sample assembly and the newest inputs.

Every frame addressed to the ECU passes the `E2EMonitor` (CRC, alive counter, length,
TICK) and `decode`; rejected frames are dropped and flagged for FAULTS bit 1. The three
plant frames of one instant share their alive counter; a sample is assembled only when
VEH_DYN, VEH_POSE_XY and VEH_POSE_YAW with one counter have all arrived. A counter that
moves on before its set is complete marks the old set as torn (FAULTS bit 0) and it is
never used.

Arrival times are integer ns. In lockstep they are not known when a frame arrives (the
frames of tick t come before HIL_SYNC t), so they are left ``None`` and stamped with the
TICK by `RxState.stamp_pending`.
"""
from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

from can_defs.codec import decode
from can_defs.e2e import E2EMonitor, E2EStatus
from can_defs.errors import CanDefsError
from can_defs.frames import (HANDSHAKE_TICK, PLANT_SAMPLE_FRAME_IDS, TICK_STEP_MS, FrameId,
                             PlannerReq, VehDyn, VehPoseXY, VehPoseYaw)

from models.measurement import VehicleMeasurement

_LOG = logging.getLogger(__name__)

#: IDs the ECU receives; anything else on the bus is somebody else's traffic.
RX_IDS = frozenset({FrameId.HIL_SYNC, FrameId.VEH_DYN, FrameId.VEH_POSE_XY,
                    FrameId.VEH_POSE_YAW, FrameId.PLANNER_REQ})
PLANT_IDS = PLANT_SAMPLE_FRAME_IDS


@dataclass(frozen=True)
class PlantMeasurement(VehicleMeasurement):
    """One consistent plant sample: the eight measured signals of
    `models.measurement.VehicleMeasurement` (SI units) and ``counter``, the alive counter
    its three frames share."""

    counter: int


@dataclass(frozen=True)
class PlannerRequest:
    """The newest accepted PLANNER_REQ."""

    engage: bool
    target_speed: float
    path_id: int


class SampleAssembler:
    """Collects the three plant frames of one alive counter value into one measurement."""

    def __init__(self) -> None:
        self._counter: int | None = None
        self._parts: dict[FrameId, object] = {}
        self._completed = False

    def reset(self) -> None:
        """Forget any partial set."""
        self._counter = None
        self._parts = {}
        self._completed = False

    def add(self, frame_id: FrameId, frame: object, counter: int) -> tuple[PlantMeasurement | None, bool]:
        """Add one accepted plant frame; returns (completed measurement or None, torn).

        ``torn`` is True when this frame's counter starts a new set while the previous set
        was incomplete: that previous set is dropped.
        """
        torn = False
        if counter != self._counter:
            torn = bool(self._parts) and not self._completed
            self._counter = counter
            self._parts = {}
            self._completed = False
        if self._completed:
            return None, torn  # late duplicate of a set already used
        self._parts[frame_id] = frame
        if len(self._parts) < len(PLANT_IDS):
            return None, torn
        self._completed = True
        dyn = self._parts[FrameId.VEH_DYN]
        pose_xy = self._parts[FrameId.VEH_POSE_XY]
        pose_yaw = self._parts[FrameId.VEH_POSE_YAW]
        assert isinstance(dyn, VehDyn) and isinstance(pose_xy, VehPoseXY) \
            and isinstance(pose_yaw, VehPoseYaw)
        measurement = PlantMeasurement(
            vx=dyn.vx, vy=dyn.vy, yaw_rate=dyn.yaw_rate, x=pose_xy.pos_x, y=pose_xy.pos_y,
            yaw=pose_yaw.yaw, steer_angle=pose_yaw.steer_angle,
            drive_torque=pose_yaw.drive_torque, counter=counter)
        return measurement, torn


class RxKind(enum.Enum):
    """What one received frame turned out to be."""

    IGNORED = "ignored"      # not addressed to the ECU
    REJECTED = "rejected"    # E2E or decode failure: dropped
    PLANT = "plant"          # plant frame accepted (a sample may have completed)
    PLANNER = "planner"      # PLANNER_REQ accepted
    SYNC = "sync"            # valid HIL_SYNC; ``tick`` set


@dataclass(frozen=True)
class RxOutcome:
    """Result of `RxState.receive`."""

    kind: RxKind
    tick: int | None = None


class RxState:
    """E2E monitor, decoder and the newest inputs, with the flags of the current cycle.

    Attributes:
        newest_sample / newest_sample_arrival_ns: newest consistent plant sample.
        newest_planner / newest_planner_arrival_ns: newest accepted PLANNER_REQ.
        sample_seen: a consistent sample has arrived since the last reset.
        e2e_error / torn / stale: conditions since the last `clear_cycle_flags`.
        planner_disengaged_seen: an accepted PLANNER_REQ with ENGAGE = 0 since the last
            `clear_disengage_latch`.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Fresh E2E receivers and no inputs (start-up and lockstep handshake)."""
        self._monitor = E2EMonitor()
        self._assembler = SampleAssembler()
        self.newest_sample: PlantMeasurement | None = None
        self.newest_sample_arrival_ns: int | None = None
        self.newest_planner: PlannerRequest | None = None
        self.newest_planner_arrival_ns: int | None = None
        self.sample_seen = False
        self.planner_disengaged_seen = False
        self.e2e_error = False
        self.torn = False
        self.stale = False
        self.counts = {"accepted": 0, "rejected": 0, "torn": 0, "samples": 0}

    def clear_cycle_flags(self) -> None:
        """Start collecting the conditions of the next cycle."""
        self.e2e_error = False
        self.torn = False
        self.stale = False

    def clear_disengage_latch(self) -> None:
        """Require a fresh ENGAGE = 0 from now on (entering SAFE_STOP)."""
        self.planner_disengaged_seen = False

    def stamp_pending(self, now_ns: int) -> None:
        """Give inputs that arrived before this HIL_SYNC the TICK time (lockstep)."""
        if self.newest_sample is not None and self.newest_sample_arrival_ns is None:
            self.newest_sample_arrival_ns = now_ns
        if self.newest_planner is not None and self.newest_planner_arrival_ns is None:
            self.newest_planner_arrival_ns = now_ns

    def _reject(self, arbitration_id: int, why: str) -> RxOutcome:
        self.e2e_error = True
        self.counts["rejected"] += 1
        _LOG.debug("frame 0x%03X rejected: %s", arbitration_id, why)
        return RxOutcome(RxKind.REJECTED)

    def receive(self, arbitration_id: int, data: bytes, arrival_ns: int | None) -> RxOutcome:
        """Check, decode and route one frame (``arrival_ns`` None = stamp at next TICK).

        Never raises: every failure is a rejected frame.
        """
        if arbitration_id not in RX_IDS:
            return RxOutcome(RxKind.IGNORED)
        frame_id = FrameId(arbitration_id)
        data = bytes(data)
        try:
            result = self._monitor.check(arbitration_id, data)
        except CanDefsError as error:
            return self._reject(arbitration_id, f"E2E check failed: {error}")
        if frame_id is FrameId.HIL_SYNC:
            # The HIL frames carry no CRC/CNT: only length and TICK are checked.
            if result.status in (E2EStatus.WRONG_LENGTH, E2EStatus.BAD_TICK):
                return self._reject(arbitration_id, result.status.name)
        else:
            # LOST (a jump of 2 or 3) is accepted and is not an E2E error (can_defs.e2e).
            if result.status.is_e2e_error:
                self.e2e_error = True
                if result.status is E2EStatus.REPEATED and frame_id in PLANT_IDS:
                    self.stale = True
            if not result.accepted:
                self.counts["rejected"] += 1
                return RxOutcome(RxKind.REJECTED)
        if len(data) != 8:
            return self._reject(arbitration_id, f"length {len(data)} != 8")
        try:
            decoded = decode(arbitration_id, data)
        except CanDefsError as error:
            return self._reject(arbitration_id, f"decode failed: {error}")
        if frame_id is not FrameId.HIL_SYNC and not decoded.crc_ok:
            return self._reject(arbitration_id, "CRC")
        self.counts["accepted"] += 1
        frame = decoded.frame
        if frame_id is FrameId.HIL_SYNC:
            tick = int(frame.tick)
            if tick != HANDSHAKE_TICK and tick % TICK_STEP_MS:
                return self._reject(arbitration_id, f"TICK {tick} not a multiple of 5 ms")
            return RxOutcome(RxKind.SYNC, tick=tick)
        if frame_id is FrameId.PLANNER_REQ:
            assert isinstance(frame, PlannerReq)
            self.newest_planner = PlannerRequest(bool(frame.engage), float(frame.target_speed),
                                                 int(frame.path_id))
            self.newest_planner_arrival_ns = arrival_ns
            if not frame.engage:
                self.planner_disengaged_seen = True
            return RxOutcome(RxKind.PLANNER)
        assert decoded.counter is not None
        measurement, torn = self._assembler.add(frame_id, frame, decoded.counter)
        if torn:
            self.torn = True
            self.counts["torn"] += 1
        if measurement is not None:
            self.newest_sample = measurement
            self.newest_sample_arrival_ns = arrival_ns
            self.sample_seen = True
            self.counts["samples"] += 1
        return RxOutcome(RxKind.PLANT)
