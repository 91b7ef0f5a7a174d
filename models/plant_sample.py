"""Plant samples from the plant's frames: VEH_DYN, VEH_POSE_XY and VEH_POSE_YAW with one
alive counter value form one `PlantMeasurement` (docs/can-contract.md).

`PlantSampleAssembler` is the one assembler of the two receivers of plant frames, the
ECU (``firmware_sim.rx``) and identification from recorded logs
(``models.can_log_data``). They differ only in when a set of frames ends:

- The ECU (``interleaved=False``): one set is open at a time. A frame of another counter
  value ends it, torn if it is incomplete (the contract's rule, FAULTS bit 0); a repeated
  frame replaces the earlier one; a completed set stays open, so a late frame of its
  counter is recognised as late instead of starting a set that would be torn.
- A recorded log (``interleaved=True``): a recorder may interleave the frames of
  neighbouring counter values, so each value has a set of its own, and a completed set
  closes at once (its value comes back 16 periods later with the next sample). A frame
  that repeats one of an open set's frames, or comes more than `MAX_SET_SPREAD_S` after
  it, belongs to a later wrap of the counter: the open set is torn and the frame starts a
  new one.

It lives in ``models`` because it builds the shared `VehicleMeasurement` record and both
``firmware_sim`` and ``models.can_log_data`` use it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from can_defs.frames import PLANT_SAMPLE_FRAME_IDS, FrameId, VehDyn, VehPoseXY, VehPoseYaw

from models.measurement import VehicleMeasurement

#: Largest time between the frames of one set in a log: half the 160 ms after which the
#: 4-bit counter (10 ms period) repeats a value.
MAX_SET_SPREAD_S = 0.08


@dataclass(frozen=True)
class PlantMeasurement(VehicleMeasurement):
    """One consistent plant sample: the eight measured signals of
    `models.measurement.VehicleMeasurement` (SI units) and ``counter``, the alive counter
    its three frames share."""

    counter: int


@dataclass
class _FrameSet:
    """The plant frames of one counter value received so far (decoded, by frame ID)."""

    parts: dict[int, object] = field(default_factory=dict)
    time: float | None = None     # of the newest frame that came with a time (s)
    completed: bool = False


def plant_measurement(parts: dict[int, object], counter: int) -> PlantMeasurement:
    """The sample of a complete set: ``parts`` maps each plant frame ID to its decoded
    frame (`VehDyn`, `VehPoseXY`, `VehPoseYaw`)."""
    dyn = parts[FrameId.VEH_DYN]
    pose_xy = parts[FrameId.VEH_POSE_XY]
    pose_yaw = parts[FrameId.VEH_POSE_YAW]
    assert isinstance(dyn, VehDyn) and isinstance(pose_xy, VehPoseXY) \
        and isinstance(pose_yaw, VehPoseYaw)
    return PlantMeasurement(
        vx=dyn.vx, vy=dyn.vy, yaw_rate=dyn.yaw_rate, x=pose_xy.pos_x, y=pose_xy.pos_y,
        yaw=pose_yaw.yaw, steer_angle=pose_yaw.steer_angle,
        drive_torque=pose_yaw.drive_torque, counter=counter)


class PlantSampleAssembler:
    """Collects the three plant frames of one alive counter value into one measurement
    (see the module docstring for ``interleaved``).

    Attributes:
        sample_time: time (s) of the last completed sample: the newest time given with
            its frames, None when none came with one.
    """

    def __init__(self, interleaved: bool = False) -> None:
        self.interleaved = interleaved
        self.reset()

    def reset(self) -> None:
        """Forget every partial set (start-up, a handshake, a jump of time)."""
        self._open: dict[int, _FrameSet] = {}
        self.sample_time: float | None = None

    def add(self, frame_id: int, frame: object, counter: int,
            time: float | None = None) -> tuple[PlantMeasurement | None, bool]:
        """Add one accepted plant frame (its decoded form; ``time`` in s, if known);
        returns (completed measurement or None, torn).

        ``torn`` is True when this frame ended an incomplete set: that set is dropped.
        """
        torn = False
        if not self.interleaved:
            for other in [value for value in self._open if value != counter]:
                torn = not self._open.pop(other).completed
        frames = self._open.setdefault(counter, _FrameSet())
        if frames.completed:
            return None, torn  # late frame of a set already used
        if self.interleaved and (frame_id in frames.parts or _too_far(frames.time, time)):
            torn = True
            frames = self._open[counter] = _FrameSet()
        frames.parts[frame_id] = frame
        if time is not None:
            frames.time = time
        if len(frames.parts) < len(PLANT_SAMPLE_FRAME_IDS):
            return None, torn
        if self.interleaved:
            del self._open[counter]
        else:
            frames.completed = True
        self.sample_time = frames.time
        return plant_measurement(frames.parts, counter), torn


def _too_far(set_time: float | None, time: float | None) -> bool:
    """A frame ``time`` too far from its set's for one sample (both known)."""
    return set_time is not None and time is not None and abs(time - set_time) > MAX_SET_SPREAD_S
