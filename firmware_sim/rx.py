"""RX path of the ECU: E2E check, decode, plant sample assembly and the newest inputs.

Every frame addressed to the ECU passes the `E2EMonitor` (CRC, alive counter, length,
TICK) and `decode`; rejected frames are dropped and flagged for FAULTS bit 1. The three
plant frames of one instant share their alive counter; a sample is assembled
(`models.plant_sample.PlantSampleAssembler`, one set open at a time) only when VEH_DYN,
VEH_POSE_XY and VEH_POSE_YAW with one counter have all arrived. A counter that moves on
before its set is complete marks the old set as torn (FAULTS bit 0) and it is never used.

A complete sample is then checked for plausibility (contract, rev. 2): ranges of VX, VY,
YAW_RATE and YAW, and a position continuous with the last good sample (elapsed time from
the counters, never from arrival times). A sample that fails is not a good sample: it is
counted, flagged for FAULTS bit 0 like a torn one, and never used.

Arrival times are integer ns. In lockstep they are not known when a frame arrives (the
frames of tick t come before HIL_SYNC t), so they are left ``None`` and stamped with the
TICK by `RxState.stamp_pending`.
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

from can_defs.codec import decode
from can_defs.e2e import E2EMonitor, E2EStatus
from can_defs.errors import CanDefsError
from can_defs.frames import (HANDSHAKE_TICK, PLANT_SAMPLE_FRAME_IDS, TICK_STEP_MS, FrameId,
                             PlannerReq)

from firmware_sim.config import NS_PER_MS, Plausibility
from firmware_sim.ratelimit import RateLimitedLog
from models.plant_sample import PlantMeasurement, PlantSampleAssembler

_LOG = logging.getLogger(__name__)

#: IDs the ECU receives; anything else on the bus is somebody else's traffic.
RX_IDS = frozenset({FrameId.HIL_SYNC, FrameId.VEH_DYN, FrameId.VEH_POSE_XY,
                    FrameId.VEH_POSE_YAW, FrameId.PLANNER_REQ})
PLANT_IDS = PLANT_SAMPLE_FRAME_IDS


@dataclass(frozen=True)
class PlannerRequest:
    """The newest accepted PLANNER_REQ."""

    engage: bool
    target_speed: float
    path_id: int


def implausibility(sample: PlantMeasurement, last_good: PlantMeasurement | None,
                   last_good_age_ns: int | None, limits: Plausibility) -> str | None:
    """Why ``sample`` is not plausible (contract, rev. 2), or None when it is.

    ``last_good`` / ``last_good_age_ns``: the last good sample and its age; the position
    continuity check applies only when it is at most ``limits.continuity_window_ms`` old.
    """
    if not limits.vx_min_mps <= sample.vx <= limits.vx_max_mps:
        return f"VX {sample.vx:g} m/s outside [{limits.vx_min_mps:g}, {limits.vx_max_mps:g}]"
    if abs(sample.vy) > limits.vy_max_mps:
        return f"|VY| {abs(sample.vy):g} m/s > {limits.vy_max_mps:g}"
    if abs(sample.yaw_rate) > limits.yaw_rate_max_rad_s:
        return f"|YAW_RATE| {abs(sample.yaw_rate):g} rad/s > {limits.yaw_rate_max_rad_s:g}"
    if abs(sample.yaw) > limits.yaw_max_rad:
        return f"|YAW| {abs(sample.yaw):g} rad > pi + 0.0001"
    if last_good is None or last_good_age_ns is None \
            or last_good_age_ns > limits.continuity_window_ms * NS_PER_MS:
        return None
    elapsed_s = limits.sample_period_ms / 1000.0 * ((sample.counter - last_good.counter) % 16)
    speed = max(math.hypot(sample.vx, sample.vy), math.hypot(last_good.vx, last_good.vy))
    allowed = (speed + limits.speed_margin_mps) * elapsed_s + limits.position_slack_m
    distance = math.hypot(sample.x - last_good.x, sample.y - last_good.y)
    if distance > allowed:
        return (f"position moved {distance:.3f} m in {elapsed_s * 1000:.0f} ms "
                f"(at most {allowed:.3f} m)")
    return None


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
        e2e_error / torn / stale / implausible: conditions since the last
            `clear_cycle_flags`.
        planner_disengaged_seen: an accepted PLANNER_REQ with ENGAGE = 0 since the last
            `clear_disengage_latch`.
    """

    def __init__(self, plausibility: Plausibility | None = None,
                 log: RateLimitedLog | None = None) -> None:
        self._plausibility = plausibility or Plausibility()
        self._log = log or RateLimitedLog(_LOG)
        self.reset()

    def reset(self) -> None:
        """Fresh E2E receivers and no inputs (start-up and lockstep handshake)."""
        self._monitor = E2EMonitor()
        self._assembler = PlantSampleAssembler()
        self.newest_sample: PlantMeasurement | None = None
        self.newest_sample_arrival_ns: int | None = None
        self.newest_planner: PlannerRequest | None = None
        self.newest_planner_arrival_ns: int | None = None
        self.sample_seen = False
        self.planner_disengaged_seen = False
        self.e2e_error = False
        self.torn = False
        self.stale = False
        self.implausible = False
        self.reference_restarted = False
        self._last_time_ns: int | None = None
        self.counts = {"accepted": 0, "rejected": 0, "torn": 0, "samples": 0,
                       "implausible": 0}

    def drop_sample(self) -> None:
        """Forget the last good sample (a jump of virtual time: no continuity check spans
        it, and the next sample that passes the range checks is the new reference)."""
        self.newest_sample = None
        self.newest_sample_arrival_ns = None
        self._assembler.reset()

    def clear_cycle_flags(self) -> None:
        """Start collecting the conditions of the next cycle."""
        self.e2e_error = False
        self.torn = False
        self.stale = False
        self.implausible = False
        self.reference_restarted = False

    def clear_disengage_latch(self) -> None:
        """Require a fresh ENGAGE = 0 from now on (entering SAFE_STOP)."""
        self.planner_disengaged_seen = False

    def stamp_pending(self, now_ns: int) -> None:
        """Give inputs that arrived before this HIL_SYNC the TICK time (lockstep)."""
        self._last_time_ns = now_ns
        if self.newest_sample is not None and self.newest_sample_arrival_ns is None:
            self.newest_sample_arrival_ns = now_ns
        if self.newest_planner is not None and self.newest_planner_arrival_ns is None:
            self.newest_planner_arrival_ns = now_ns

    def _last_good_age_ns(self, arrival_ns: int | None) -> int | None:
        """Age of the last good sample when a frame arrives at ``arrival_ns``; in lockstep
        (None) the last TICK seen stands for the arrival, at most one tick early."""
        if self.newest_sample is None:
            return None
        last_arrival = self.newest_sample_arrival_ns
        now = arrival_ns if arrival_ns is not None else self._last_time_ns
        if last_arrival is None or now is None:
            return 0  # the last good sample arrived in this same tick
        return max(0, now - last_arrival)

    def _continuity_applies(self, arrival_ns: int | None) -> bool:
        age = self._last_good_age_ns(arrival_ns)
        return age is not None and age <= self._plausibility.continuity_window_ms * NS_PER_MS

    def _check_plausible(self, sample: PlantMeasurement, arrival_ns: int | None) -> str | None:
        """`implausibility` against the last good sample."""
        return implausibility(sample, self.newest_sample, self._last_good_age_ns(arrival_ns),
                              self._plausibility)

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
            if arrival_ns is not None:
                self._last_time_ns = arrival_ns
            why = self._check_plausible(measurement, arrival_ns)
            if why is not None:
                self.implausible = True
                self.counts["implausible"] += 1
                self._log.log("implausible", logging.WARNING,
                              "plant sample CNT %d not plausible: %s; not used",
                              measurement.counter, why)
                return RxOutcome(RxKind.PLANT)
            if self.newest_sample is not None and not self._continuity_applies(arrival_ns):
                # a new position reference after a gap > 100 ms: the ECU must pass through
                # SAFE_STOP / STANDBY before it uses it (contract: "SAFE_STOP by then")
                self.reference_restarted = True
            self.newest_sample = measurement
            self.newest_sample_arrival_ns = arrival_ns
            self.sample_seen = True
            self.counts["samples"] += 1
        return RxOutcome(RxKind.PLANT)
