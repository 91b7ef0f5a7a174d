"""The sample's age the ECUs hand to the control law (``VehicleSample.sample_age_s``; in C
``ecu_core_step_aged``): the task start minus the time the newest sample set was complete,
on the ECU's own clock, which only the delay compensation reads
(``MpcTuning.delay_compensation_s``, controller/delay_compensation.py).

The Python ECU with the scripted controller of ``test_ecu_lockstep``: the age each step
receives is the one the ECU measures for its freshness rules, 0 or 5 ms with revision 2's
clock release against a 10 ms plant, 0 with revision 3's sample release, and 0 in DEGRADED
(dead reckoning moved the sample to the task start). Then ESO-DKMPC with 30 ms compensation
on dlc_smoke in lockstep, where the age is virtual time and so deterministic: the Python
ECU, the Python ECU with the C core (``--native``, ``ecu_step_aged``) and the C ECU send the
same frames, with either release. The C side is the firmware that
tests/test_firmware_c_actuator.py generates (build/firmware-actuator: the rate rows on),
its data file written for that tuning with the compensation on.
"""
from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest
from can_defs.frames import CtrlMode

from firmware_sim.config import NS_PER_MS, NS_PER_S, EcuConfig
from test_ecu_lockstep import Rig, buses  # noqa: F401 (buses: the fixture)
from test_firmware_c_actuator import (BUILD, DELAY, RATE_LIMIT, actuator_build,  # noqa: F401 (the fixture)
                                      tuning_text, write_if_changed)

ROOT = Path(__file__).resolve().parent.parent
CONTROLLER = "eso-dkmpc"
SAMPLE_RELEASE = ("--release", "sample")


# ------------------------------------------------------------------ the age the law receives

def record_ages(rig: Rig) -> list[tuple[int, float, CtrlMode]]:
    """Wraps the ECU's control task: for each task that stepped the controller, (the age
    the ECU measured: task start - the newest sample's arrival, ns; the ``sample_age_s``
    the controller received; the mode)."""
    records: list[tuple[int, float, CtrlMode]] = []
    task = rig.ecu._control_task

    def probe(now_ns: int, release_jitter_s: float) -> None:
        arrival = rig.ecu._rx.newest_sample_arrival_ns
        steps = len(rig.controller.samples)
        task(now_ns, release_jitter_s)
        if len(rig.controller.samples) > steps:
            records.append((now_ns - arrival, rig.controller.samples[-1].sample_age_s, rig.ecu.mode))

    rig.ecu._control_task = probe
    return records


def test_clock_release_hands_the_measured_age_of_0_or_5_ms(buses) -> None:
    """Revision 2: tasks every 25 ms, samples every 10 ms: the law receives the ECU's own
    measured age, in s, alternately 5 and 0 ms."""
    rig = Rig(*buses)
    rig.handshake()
    records = record_ages(rig)
    rig.run(0, 300)
    print("(measured ns, handed s):", [(m, h) for m, h, _ in records])
    assert len(records) >= 10
    assert all(handed == measured / NS_PER_S for measured, handed, _ in records)
    assert {handed for _, handed, _ in records} == {0.0, 0.005}


def test_sample_release_hands_an_age_of_0(buses) -> None:
    """Revision 3 in lockstep: the task runs in the tick of its sample."""
    rig = Rig(*buses, config=EcuConfig(control_release="sample"))
    rig.handshake()
    records = record_ages(rig)
    rig.run(0, 300)
    assert len(records) >= 10
    assert all(measured == 0 and handed == 0.0 for measured, handed, _ in records)


def test_an_old_sample_hands_its_age_and_a_dead_reckoned_one_0(buses) -> None:
    """Revision 3, the samples of 100 to 140 ms lost (as test_ecu_rev3): the watchdog's task
    on the 20 ms old sample hands 20 ms; in DEGRADED (45 ms) the sample is moved to the task
    start, so it hands 0; the next fresh sample 0."""
    rig = Rig(*buses, config=EcuConfig(control_release="sample"))
    rig.handshake()
    records = record_ages(rig)
    rig.run(0, 200, plant=lambda t: None if 100 <= t <= 140 else {"vx": 10.0, "x": 1.0, "y": 0.0})
    print("(measured ns, handed s, mode):", records)
    assert [(m // NS_PER_MS, h, mode) for m, h, mode in records[3:6]] == [
        (20, 0.02, CtrlMode.ACTIVE), (45, 0.0, CtrlMode.DEGRADED), (0, 0.0, CtrlMode.ACTIVE)]


# ------------------------------------------------------------------ both ECUs, compensation on

@pytest.fixture(scope="module")
def delay_files(actuator_build: Path) -> tuple[Path, Path]:
    """(the tuning with the rate rows and 30 ms compensation on for the QP MPCs, its C data
    file for build/firmware-actuator)."""
    sys.path.insert(0, str(ROOT / "firmware" / "tools"))
    from ecu_data import collect, write_data  # noqa: E402 (the build tool)

    tuning = actuator_build / "tuning_delay.toml"
    write_if_changed(tuning, tuning_text({"qp_steer_rate_limit": RATE_LIMIT, "delay_compensation_s": DELAY}))
    data = actuator_build / "ecu_data_delay.bin"
    write_data(collect(tuning, ROOT / "models" / "artifacts" / "dk_d5"), data)
    return tuning, data


def python_ecu_frames(controller_factory, release: str, monkeypatch: pytest.MonkeyPatch) -> tuple[list, list]:
    """dlc_smoke with the in-process Python ECU on ``controller_factory``'s law and the
    control release ``release``: (commands, diagnoses) as ``commands_and_diags``."""
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil
    from test_firmware_c_bus import commands_and_diags

    with monkeypatch.context() as patch:  # the in-process ECU takes the default EcuConfig
        patch.setattr("firmware_sim.ecu.EcuConfig", functools.partial(EcuConfig, control_release=release))
        result = run_hil(load_scenario("dlc_smoke"), default_options(CONTROLLER, controller_factory=controller_factory))
    return commands_and_diags(result.extra["ecu_frames_raw"])


def c_ecu_frames(data: Path, release: str, tmp_path: Path) -> tuple[list, list]:
    """dlc_smoke with the C ECU of build/firmware-actuator on ``data``."""
    from studies.bench_native import run_on_hub
    from test_firmware_c_bus import commands_and_diags

    raw, _, status, output = run_on_hub("c", "dlc_smoke", CONTROLLER, tmp_path / f"c-{data.stem}-{release}.log",
                                        executable=BUILD / "ecu", extra=("--data", str(data), "--release", release))
    assert status == 0, output[-2000:]
    return commands_and_diags(raw)


@pytest.mark.parametrize("release", ["clock", "sample"])
def test_both_ecus_send_the_same_frames_with_delay_compensation(delay_files, release: str, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """ESO-DKMPC, 30 ms compensation plus the sample's age: the Python ECU and the C ECU send
    the same STEER_TORQUE_CMD frames byte for byte and the same CTRL_DIAG (but its wall-clock
    fields); the compensation acted (the C ECU without it commands otherwise)."""
    from controller.registry import create_controller

    tuning, data = delay_files
    python = python_ecu_frames(lambda name: create_controller(name, tuning_path=tuning), release, monkeypatch)
    c_ecu = c_ecu_frames(data, release, tmp_path)
    uncompensated = c_ecu_frames(BUILD / "ecu_data.bin", release, tmp_path)
    commands = python[0]
    print(f"{release}: {len(commands)} commands; without compensation "
          f"{sum(a != b for a, b in zip(commands, uncompensated[0]))} differ")
    assert len(commands) >= 150
    first = next((i for i, (a, b) in enumerate(zip(commands, c_ecu[0])) if a != b), None)
    assert first is None, f"first differing STEER_TORQUE_CMD at tick {commands[first][0]} ms"
    assert c_ecu == python
    assert uncompensated[0] != commands


def test_native_ecu_passes_the_age_to_the_c_core(delay_files, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--native``: the Python ECU stepping the C core (``ecu_step_aged``) sends the frames
    of the Python law with the compensation on (revision 2's ages of 0 and 5 ms)."""
    from c_twin import native_on
    from controller.registry import create_controller

    tuning, data = delay_files
    python = python_ecu_frames(lambda name: create_controller(name, tuning_path=tuning), "clock", monkeypatch)
    for native in native_on(BUILD / "libecu.so"):
        core = native.NativeController(CONTROLLER, data)
        assert python_ecu_frames(lambda name: core, "clock", monkeypatch) == python
