"""Contract revision 3 on the bus, both ECUs: the control task released by the plant's
samples (``--release sample``), in lockstep against the plant of revision 2 (10 ms).

The Python ECU (``python -m firmware_sim``) and the C executable each run as a process on
a hub of their own (``studies.bench_native.run_on_hub``), as in ``test_firmware_c_bus``:
two runs of one ECU send the same frames, the two ECUs send the same frames (STEER_TORQUE_CMD
byte for byte, CTRL_DIAG but its wall-clock fields), and the conformance cases of revision 2
(``CONFORMANCE_CASES``) give the same frames in both with the option on. The first cases run
in make test, every case in make firmware-conformance (ECU_CONFORMANCE_FULL=1); real-time runs close.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from can_defs.codec import decode
from can_defs.frames import CtrlMode, FrameId

from studies.bench_native import run_on_hub
from test_firmware_c_bus import (CONFORMANCE_CASES, CONFORMANCE_FULL, ECU, IN_MAKE_TEST,
                                 commands_and_diags)
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)

ROOT = Path(__file__).resolve().parent.parent
SAMPLE_RELEASE = ("--release", "sample")


def run(which: str, tmp_path: Path, name: str, **kwargs) -> tuple[list, list]:
    raw, _, status, output = run_on_hub(which, "dlc_smoke", kwargs.pop("controller", "eso-dkmpc"),
                                        tmp_path / f"{name}.log", executable=ECU,
                                        extra=SAMPLE_RELEASE, **kwargs)
    assert status == 0, output[-2000:]
    return commands_and_diags(raw)


def test_both_ecus_send_the_same_frames_and_each_twice_the_same(native, tmp_path: Path) -> None:
    """ESO-DKMPC on dlc_smoke with the sample release: the commands come in the ticks of the
    fresh samples (0, 30, 50, 80, ...: a 25 ms mean), identical run to run and ECU to ECU."""
    runs = {name: run(name.split("-")[0], tmp_path, name) for name in ("python-1", "python-2", "c-1", "c-2")}
    commands, diags = runs["python-1"]
    ticks = [t for t, _ in commands]
    print(f"{len(commands)} commands, ticks {ticks[:10]} ...")
    assert ticks[:8] == [0, 30, 50, 80, 100, 130, 150, 180]
    assert (ticks[-1] - ticks[0]) / (len(ticks) - 1) == pytest.approx(25.0, abs=0.5)
    modes = [decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode for _, d in commands]
    assert modes[1:].count(CtrlMode.ACTIVE) == len(modes) - 1
    for name in ("python-2", "c-1", "c-2"):
        assert runs[name] == (commands, diags), f"{name} differs from python-1"


@pytest.mark.parametrize("case", [pytest.param(name, marks=() if name in IN_MAKE_TEST else [
    pytest.mark.slow, pytest.mark.skipif(not CONFORMANCE_FULL, reason="ECU_CONFORMANCE_FULL=1")])
    for name in CONFORMANCE_CASES])
def test_conformance_with_sample_release_c_ecu_equals_python_ecu(native, case: str, tmp_path: Path) -> None:
    """The fault cases of revision 2 with the sample release on in both ECUs: the same
    frames (modes, fault bits, the watchdog's cycles)."""
    table = dict(CONFORMANCE_CASES[case])
    jump = table.pop("jump", None)
    runs = {which: run(which, tmp_path, which, controller="lmpc", faults=table or None, jump=jump)
            for which in ("python", "c")}
    (py_commands, py_diags), (c_commands, c_diags) = runs["python"], runs["c"]
    modes = sorted({decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode.name for _, d in py_commands})
    print(f"{case}: {len(py_commands)} commands, modes {modes}, FAULTS {sorted({f[3] for _, f in py_diags})}")
    assert len(c_commands) == len(py_commands)
    first = next((i for i, (a, b) in enumerate(zip(py_commands, c_commands)) if a != b), None)
    assert first is None, f"first differing STEER_TORQUE_CMD at tick {py_commands[first][0]} ms"
    assert c_diags == py_diags
    gaps = [b - a for (a, _), (b, _) in zip(py_commands, py_commands[1:])]
    assert max(gaps) <= 35, f"a gap of {max(gaps)} ms between two commands"  # the watchdog's bound


def test_both_ecus_refuse_an_unknown_release(native) -> None:
    """The same verdicts: clock and sample are taken, anything else is one error line
    naming control_release and exit status 2 before the bus is opened."""
    path = ROOT / "hil/paths/dlc.csv"
    for command in ([sys.executable, "-m", "firmware_sim"], [str(ECU)]):
        done = subprocess.run([*command, "--controller", "lmpc", "--path", f"1={path}", "--lockstep",
                               "--interface", "virtual" if command[0] == sys.executable else "socketcand",
                               "--channel", "none", "--release", "fast"],
                              cwd=ROOT, capture_output=True, text=True, timeout=60)
        print(command[-1], done.returncode, done.stderr.strip())
        assert done.returncode == 2
        assert "control_release must be one of clock, sample, got 'fast'" in done.stderr


def test_both_ecus_in_real_time_with_sample_release_track_as_in_lockstep(native, tmp_path: Path) -> None:
    """Real time, every node on the wall clock (not repeatable frame for frame): with the
    sample release each ECU sends valid commands (ACTIVE, DEGRADED on a late sample of a
    busy host) in at least 90 % of dlc_smoke's 25 ms periods, and
    tracks as the other (e_Y RMSE within 5 mm). Both pinned to CPU 0."""
    results = {}
    for which in ("python", "c"):
        raw, tracking, status, output = run_on_hub(which, "dlc_smoke", "lmpc", tmp_path / f"{which}.log",
                                                   realtime=True, executable=ECU,
                                                   extra=(*SAMPLE_RELEASE, "--cpu", "0"))
        assert status == 0, output[-2000:]
        commands = [decode(i, d).frame for _, i, d in raw if i == FrameId.STEER_TORQUE_CMD]
        valid = sum(int(c.ctrl_mode) in (2, 3) and c.cmd_valid for c in commands)
        results[which] = (len(commands), valid, tracking.lateral.rmse)
    print(f"real time, sample release, dlc_smoke (commands, valid in ACTIVE/DEGRADED, e_Y RMSE m): {results}")
    cycles = round(4.0 / 0.025)
    for n, valid, _ in results.values():
        assert n >= cycles and valid >= 0.9 * cycles
    assert abs(results["c"][2] - results["python"][2]) <= 0.005


def run_with_25_ms_plant(which: str, tmp_path: Path, realtime: bool = False) -> tuple[list, list, float]:
    """dlc_smoke with the plant publishing every 25 ms (rev. 3, ``PlantNode(sample_period_ms=25)``)
    and the ECU told so (``--release sample --plant-period 25``): commands, diagnoses
    (as ``commands_and_diags``) and the e_Y RMSE, m."""
    from hil.bus import BusConfig, private_virtual_channel
    from hil.ecu_runners import EcuProcess
    from hil.plant_node import PlantNode
    from hil.rig import Rig, RigHooks
    from hil.run_types import RunOptions
    from hil.scenario import load_scenario
    from studies.bench_native import ecu_command

    scenario = load_scenario("dlc_smoke")
    log = tmp_path / f"{which}.log"
    options = RunOptions(controller="eso-dkmpc", bus=BusConfig("virtual", private_virtual_channel("rev3")),
                         lockstep=not realtime, handshake_timeout_s=60.0, ack_timeout_s=10.0, ecu_output=log)

    def start_ecu(rig: Rig) -> EcuProcess:
        command, environment = ecu_command(which, "eso-dkmpc", scenario.path_file, rig.hub_port,
                                           "--realtime" if realtime else "--lockstep", ECU,
                                           (*SAMPLE_RELEASE, "--plant-period", "25"))
        return EcuProcess(scenario, options, command, environment)

    def plant_at_25_ms(plant: PlantNode) -> PlantNode:
        plant.sample_period_ms = 25  # the rig's own plant node keeps the run's trace
        return plant

    def before_run() -> None:
        if realtime:
            import time
            time.sleep(1.5 if which == "python" else 0.3)  # the ECU's start-up

    rig = Rig(scenario, options, RigHooks(ecu=start_ecu, own_hub=True, wrap_plant=plant_at_25_ms,
                                          before_run=before_run))
    with rig:
        rig.run(scenario.duration_s)
    assert rig.ecu.process.returncode == 0, log.read_text()[-2000:]
    commands, diags = commands_and_diags(rig.monitor.raw)
    return commands, diags, rig.result().tracking.lateral.rmse


def test_a_25_ms_plant_is_served_on_every_sample_by_both_ecus_alike(native, tmp_path: Path) -> None:
    """Lockstep, the plant at 25 ms (aligned): the commands come in the ticks of revision 2
    (0, 25, 50, ...), every one in ACTIVE after the engagement, the same frames from both
    ECUs, and the lane change is tracked as with the 10 ms plant (e_Y RMSE within 5 mm of
    the 10 ms plant's with the same option)."""
    runs = {which: run_with_25_ms_plant(which, tmp_path) for which in ("python", "c")}
    commands, diags, rmse = runs["python"]
    ticks = [t for t, _ in commands]
    modes = [decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode for _, d in commands]
    raw_10, tracking_10, status, _ = run_on_hub("python", "dlc_smoke", "eso-dkmpc", tmp_path / "ten.log",
                                                executable=ECU, extra=SAMPLE_RELEASE)
    print(f"25 ms plant: {len(ticks)} commands, e_Y RMSE {rmse:.4f} m (10 ms plant: "
          f"{tracking_10.lateral.rmse:.4f} m), modes {sorted({m.name for m in modes})}")
    assert ticks == list(range(0, 25 * len(ticks), 25))
    assert modes[1:].count(CtrlMode.ACTIVE) == len(modes) - 1
    assert runs["c"][:2] == (commands, diags)
    assert abs(rmse - tracking_10.lateral.rmse) <= 0.005


def test_both_ecus_refuse_a_25_ms_plant_without_the_sample_release_and_other_periods(native) -> None:
    path = ROOT / "hil/paths/dlc.csv"
    cases = {("--plant-period", "25"): "plant_sample_period_ms 25 needs control_release 'sample', got 'clock'",
             ("--plant-period", "20", "--release", "sample"): "plant_sample_period_ms must be 10 or 25, got 20"}
    for arguments, message in cases.items():
        for command in ([sys.executable, "-m", "firmware_sim"], [str(ECU)]):
            done = subprocess.run([*command, "--controller", "lmpc", "--path", f"1={path}", "--lockstep",
                                   "--interface", "virtual" if command[0] == sys.executable else "socketcand",
                                   "--channel", "none", *arguments],
                                  cwd=ROOT, capture_output=True, text=True, timeout=60)
            print(command[-1], arguments, done.returncode, done.stderr.strip())
            assert done.returncode == 2 and message in done.stderr


def test_both_ecus_serve_a_25_ms_plant_in_real_time(native, tmp_path: Path) -> None:
    """Real time, the plant at 25 ms on its own clock (the grid follows its samples, rule 6
    of revision 3; the rig's first sample may come apart from the phase of the next ones):
    at least 90 % of dlc_smoke's periods with a valid command from each ECU."""
    for which in ("python", "c"):
        commands, diags, rmse = run_with_25_ms_plant(which, tmp_path, realtime=True)
        frames = [decode(FrameId.STEER_TORQUE_CMD, d).frame for _, d in commands]
        valid = sum(int(f.ctrl_mode) in (2, 3) and f.cmd_valid for f in frames)
        degraded = sum(int(f.ctrl_mode) == 3 for f in frames)
        print(f"{which}: {len(frames)} commands, {valid} valid, {degraded} DEGRADED, e_Y RMSE {rmse:.4f} m")
        assert valid >= 0.9 * round(4.0 / 0.025) and degraded <= 0.05 * len(frames)
