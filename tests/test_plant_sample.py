"""models.plant_sample: the one plant-sample assembler, in the ECU's mode (one set open at
a time; more in test_firmware_units.py) and in the mode for recorded logs (a set per
counter value, tears by repetition and by time)."""
from __future__ import annotations

from can_defs.frames import FrameId, VehDyn, VehPoseXY, VehPoseYaw

from models.plant_sample import MAX_SET_SPREAD_S, PlantMeasurement, PlantSampleAssembler

DYN, XY, YAW = VehDyn(10.0, 0.1, 0.01), VehPoseXY(1.0, 2.0), VehPoseYaw(0.1, 0.02, 50.0)


def test_a_complete_set_is_one_measurement_of_all_eight_signals() -> None:
    assembler = PlantSampleAssembler()
    assembler.add(FrameId.VEH_POSE_YAW, YAW, 7)
    assembler.add(FrameId.VEH_DYN, DYN, 7)
    sample, torn = assembler.add(FrameId.VEH_POSE_XY, XY, 7)
    assert not torn and sample == PlantMeasurement(10.0, 0.1, 0.01, 1.0, 2.0, 0.1, 0.02, 50.0, 7)
    assert assembler.sample_time is None  # the ECU gives no times


def test_the_ecu_mode_takes_a_repeated_frame_in_place_of_the_earlier_one() -> None:
    assembler = PlantSampleAssembler()
    assembler.add(FrameId.VEH_DYN, VehDyn(9.0, 0.0, 0.0), 2)
    assert assembler.add(FrameId.VEH_DYN, DYN, 2) == (None, False)
    assembler.add(FrameId.VEH_POSE_XY, XY, 2)
    sample, torn = assembler.add(FrameId.VEH_POSE_YAW, YAW, 2)
    assert not torn and sample is not None and sample.vx == 10.0


def test_interleaved_counters_each_complete_with_their_time() -> None:
    assembler = PlantSampleAssembler(interleaved=True)
    samples = []
    for frame_id, frame, counter, time in (
            (FrameId.VEH_DYN, DYN, 3, 0.03), (FrameId.VEH_DYN, DYN, 4, 0.04),
            (FrameId.VEH_POSE_XY, XY, 3, None), (FrameId.VEH_POSE_XY, XY, 4, None),
            (FrameId.VEH_POSE_YAW, YAW, 4, None), (FrameId.VEH_POSE_YAW, YAW, 3, None)):
        sample, torn = assembler.add(frame_id, frame, counter, time)
        assert not torn
        if sample is not None:
            samples.append((sample.counter, assembler.sample_time))
    assert samples == [(4, 0.04), (3, 0.03)]


def test_a_repeated_frame_tears_the_open_set_in_a_log() -> None:
    assembler = PlantSampleAssembler(interleaved=True)
    assembler.add(FrameId.VEH_DYN, DYN, 5, 0.05)
    assembler.add(FrameId.VEH_POSE_XY, XY, 5, None)
    assert assembler.add(FrameId.VEH_POSE_XY, XY, 5, None) == (None, True)
    assembler.add(FrameId.VEH_DYN, DYN, 5, 0.21)
    sample, torn = assembler.add(FrameId.VEH_POSE_YAW, YAW, 5, None)
    assert sample is not None and not torn and assembler.sample_time == 0.21


def test_a_frame_of_a_later_counter_wrap_tears_the_open_set_in_a_log() -> None:
    assembler = PlantSampleAssembler(interleaved=True)
    assembler.add(FrameId.VEH_DYN, DYN, 9, 1.0)
    assembler.add(FrameId.VEH_POSE_XY, XY, 9, 1.0)
    # 160 ms later the counter is back at 9: not the same instant
    assert assembler.add(FrameId.VEH_POSE_YAW, YAW, 9, 1.0 + 2 * MAX_SET_SPREAD_S + 1e-3) == (None, True)
    # ... and starts the set of that instant
    assert assembler.add(FrameId.VEH_POSE_XY, XY, 9, 1.161) == (None, False)
    sample, torn = assembler.add(FrameId.VEH_DYN, DYN, 9, 1.161)
    assert sample is not None and not torn and assembler.sample_time == 1.161


def test_a_completed_set_closes_at_once_in_a_log_and_reset_forgets_open_sets() -> None:
    assembler = PlantSampleAssembler(interleaved=True)
    for frame_id, frame in ((FrameId.VEH_DYN, DYN), (FrameId.VEH_POSE_XY, XY), (FrameId.VEH_POSE_YAW, YAW)):
        result = assembler.add(frame_id, frame, 0, 0.0)
    assert result[0] is not None
    # the next set of counter 0 (a wrap later) is a new sample, not a late frame
    assembler.add(FrameId.VEH_DYN, DYN, 0, 0.16)
    assembler.reset()
    assert assembler.add(FrameId.VEH_DYN, DYN, 0, 0.32) == (None, False)
