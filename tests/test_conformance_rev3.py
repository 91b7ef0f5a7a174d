"""Contract revision 3 on the bus, both ECUs: the control task released by the plant's
samples (``--release sample``), in lockstep against the plant of revision 2 (10 ms).

The Python ECU (``python -m firmware_sim``) and the C executable each run as a process on
a hub of their own (``studies.bench_native.run_on_hub``), as in ``test_firmware_c_bus``:
two runs of one ECU send the same frames, the two ECUs send the same frames (STEER_TORQUE_CMD
byte for byte, CTRL_DIAG but its wall-clock fields), and the conformance cases of revision 2
(``CONFORMANCE_CASES``) give the same frames in both with the option on. The first cases run
in make test, every case with ECU_CONFORMANCE_FULL=1; a real-time run of each closes.
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
