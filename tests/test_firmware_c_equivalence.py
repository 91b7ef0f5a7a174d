"""Equivalence (a) of issue 18: the Python ECU with the C core's control step (``--native``,
``firmware_sim/native.py``) against the Python ECU, over the virtual bus in lockstep.

STEER_TORQUE_CMD frames must be equal, or differ by at most 1 LSB in at most 1 % of the
frames with the e_Y RMSE within 1 mm. ``dlc_smoke`` runs here (part of ``make test``);
the two full double lane changes run with ECU_EQUIVALENCE_FULL=1
(``make firmware-equivalence``, about a minute per controller).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from can_defs.codec import decode
from can_defs.frames import FrameId
from test_firmware_c_core import native  # noqa: F401 (the fixture: libecu.so built and loaded)

ROOT = Path(__file__).resolve().parent.parent
CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
FULL = os.environ.get("ECU_EQUIVALENCE_FULL") == "1"
#: Raw integer of each physical command signal: value / scale (can_defs/vehicle.dbc).
SCALES = {"steer_angle_cmd": 1e-4, "drive_torque_cmd": 0.1}


def command_frames(result) -> list[tuple[int, object]]:
    """(tick ms, decoded SteerTorqueCmd) of every STEER_TORQUE_CMD the run's ECU sent."""
    return [(tick, decode(frame_id, data).frame) for tick, frame_id, data in result.extra["ecu_frames_raw"]
            if frame_id == FrameId.STEER_TORQUE_CMD]


def compare_runs(python_run, native_run) -> dict[str, float]:
    """Frames, frames differing, largest difference in LSB, e_Y RMSE of both (m)."""
    ours, theirs = command_frames(python_run), command_frames(native_run)
    assert [t for t, _ in ours] == [t for t, _ in theirs], "the two ECUs sent commands in different ticks"
    differing, largest = 0, 0
    for (_, a), (_, b) in zip(ours, theirs):
        assert (a.ctrl_mode, a.cmd_valid) == (b.ctrl_mode, b.cmd_valid)
        lsb = max(abs(round(getattr(a, name) / scale) - round(getattr(b, name) / scale))
                  for name, scale in SCALES.items())
        differing += lsb > 0
        largest = max(largest, lsb)
    return {"frames": len(ours), "differing": differing, "largest_lsb": largest,
            "rmse_python": python_run.tracking.lateral.rmse, "rmse_native": native_run.tracking.lateral.rmse}


def check_equivalent(name: str, scenario: str, native) -> None:
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    python_run = run_hil(load_scenario(scenario), default_options(name))
    native_run = run_hil(load_scenario(scenario),
                         default_options(name, controller_factory=native.native_controller_factory(name)))
    figures = compare_runs(python_run, native_run)
    print(f"{name} on {scenario}: {figures}")
    assert figures["frames"] > 0
    assert figures["largest_lsb"] <= 1
    assert figures["differing"] <= 0.01 * figures["frames"]
    assert abs(figures["rmse_python"] - figures["rmse_native"]) <= 1e-3


@pytest.mark.parametrize("name", CONTROLLERS)
def test_native_ecu_equals_python_ecu_on_dlc_smoke(native, name: str) -> None:
    check_equivalent(name, "dlc_smoke", native)


@pytest.mark.slow
@pytest.mark.skipif(not FULL, reason="the full lane changes: make firmware-equivalence (ECU_EQUIVALENCE_FULL=1)")
@pytest.mark.parametrize("scenario", ["dlc_high_mu", "dlc_low_mu"])
@pytest.mark.parametrize("name", CONTROLLERS)
def test_native_ecu_equals_python_ecu_on_full_lane_changes(native, name: str, scenario: str) -> None:
    check_equivalent(name, scenario, native)


def test_frame_comparison_counts_lsb() -> None:
    """compare_runs counts a 1-LSB steer difference in one frame of two."""
    from types import SimpleNamespace

    from can_defs.codec import encode
    from can_defs.frames import CtrlMode, SteerTorqueCmd

    def run(steers):
        frames = [(25 * i, FrameId.STEER_TORQUE_CMD,
                   encode(SteerTorqueCmd(ctrl_mode=CtrlMode(2), cmd_valid=True, steer_angle_cmd=s,
                                         drive_torque_cmd=10.0), counter=i))
                  for i, s in enumerate(steers)]
        return SimpleNamespace(extra={"ecu_frames_raw": frames},
                               tracking=SimpleNamespace(lateral=SimpleNamespace(rmse=0.01)))

    figures = compare_runs(run([0.01, 0.02]), run([0.01, 0.0201]))
    assert (figures["frames"], figures["differing"], figures["largest_lsb"]) == (2, 1, 1)
