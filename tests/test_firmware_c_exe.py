"""The ECU executable build/firmware/ecu (first part: --version, start-up checks, --replay)
and the C path-file reader, against the Python ECU's behaviour."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from controller.errors import PathError
from controller.reference import ReferencePath
from controller.registry import create_controller
from firmware_sim.errors import ConfigError
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built, libecu.so loaded)

ROOT = Path(__file__).resolve().parent.parent
#: The executable under test (``make firmware-asan`` points ECU_EXE at the sanitized build).
ECU = ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")
SAMPLE_FIELDS = ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque", "target_speed")


def run_ecu(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([str(ECU), *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout, check=False)


def test_version_prints_the_generator_inputs(native) -> None:
    result = run_ecu("--version")
    assert result.returncode == 0
    assert native.version() in result.stdout
    assert "can_defs/vehicle.dbc" in result.stdout and "build shapes: n_x 4" in result.stdout


@pytest.mark.parametrize("name", ["eso-dkmpc", "lmpc"])
def test_replay_equals_python_controller(native, name: str, tmp_path: Path) -> None:
    """The executable fed dlc_smoke's recorded samples gives the Python controller's commands."""
    from studies.bench import record_samples

    samples, path, _ = record_samples(scenario_name="dlc_smoke", driver=name)
    rows = [",".join(repr(float(getattr(s, f))) for f in SAMPLE_FIELDS) for s in samples]
    (tmp_path / "samples.csv").write_text(",".join(SAMPLE_FIELDS) + "\n" + "\n".join(rows) + "\n")
    controller = create_controller(name)
    controller.set_path(ReferencePath.from_csv(ROOT / "hil" / "paths" / "dlc.csv"))
    expected = [controller.step(s) for s in samples]
    result = run_ecu("--controller", name, "--path", "1=hil/paths/dlc.csv", "--replay", str(tmp_path / "samples.csv"))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("steer_angle,drive_torque,status,iterations")
    assert len(lines) == len(samples) + 1
    for (command, debug), line in zip(expected, lines[1:]):
        steer, torque, status, iterations, fallback = line.split(",")[:5]
        assert abs(float(steer) - command.steer_angle) < 1e-12 and abs(float(torque) - command.drive_torque) < 1e-9
        assert (int(status), int(iterations), bool(int(fallback))) == (int(debug.status), debug.iterations,
                                                                       debug.fallback)


@pytest.mark.parametrize("args, message", [
    (["--controller", "nmpc", "--path", "1=hil/paths/dlc.csv"], "error: unknown controller nmpc"),
    (["--controller", "lmpc", "--path", "1=hil/paths/missing.csv"], "error: hil/paths/missing.csv: path file not found"),
    (["--controller", "lmpc", "--path", "x=hil/paths/dlc.csv"], "error: --path 'x=hil/paths/dlc.csv': expected ID"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--data", "nowhere.bin"],
     "error: nowhere.bin: cannot open the ECU data file"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv"], "error: give --interface / --channel / --lockstep"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--realtime", "--lockstep"], "error: exactly one of --lockstep or --realtime is required"),
    (["--interface", "socketcand", "--channel", "vcan0", "--port", "1", "--controller", "lmpc", "--path",
      "1=hil/paths/dlc.csv", "--lockstep"], "error: cannot open CAN bus (interface=socketcand, channel=vcan0)"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--lockstep", "--rt-priority", "1000"], "error: SCHED_FIFO priority must be in 1..99, got 1000"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--lockstep", "--cpu", "x"], "error: --cpu: expected a non-negative integer, got 'x'"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--lockstep", "--timing-out", "hil/paths/dlc.csv"],
     "error: --timing-out hil/paths/dlc.csv: file exists (give --replace to overwrite it)"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--lockstep", "--timing-out", "no/such/folder/t.npz"],
     "error: --timing-out no/such/folder/t.npz: folder no/such/folder does not exist"),
    (["--interface", "socketcan", "--channel", "nosuchcan0", "--controller", "lmpc", "--path",
      "1=hil/paths/dlc.csv", "--lockstep"], "error: cannot open CAN bus (interface=socketcan, channel=nosuchcan0)"),
])
def test_bad_start_up_is_one_error_line(native, args: list[str], message: str) -> None:
    """One error line; exit 1 for a bus that cannot be opened, 2 for the rest (as the
    Python ECU's CLI)."""
    result = run_ecu(*args)
    assert result.returncode == (1 if "cannot open CAN bus" in message else 2), result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith(message)


@pytest.mark.parametrize("file", ["dlc.csv", "slalom.csv", "identification.csv"])
def test_path_reader_equals_reference_path(native, file: str) -> None:
    """The C reader gives ReferencePath.from_csv's arrays (x, y, unwrapped yaw, s) exactly."""
    source = ROOT / "hil" / "paths" / file
    if not source.is_file():
        pytest.skip(f"{source} not in this checkout")
    core = native.NativeController("lmpc")
    core.load_path_file(source)
    expected = ReferencePath.from_csv(source)
    for got, want in zip(core.path_arrays(), (expected.x, expected.y, expected.yaw, expected.s)):
        np.testing.assert_array_equal(got, want)


BAD_FILES = {
    "header": "x,y,z\n0,0,0\n0.1,0,0\n",
    "columns": "x,y,yaw\n0,0,0\n0.1,0\n",
    "number": "x,y,yaw\n0,0,0\n0.1,abc,0\n",
    "one_point": "x,y,yaw\n0,0,0\n",
    "empty": "\n\n",
    "spacing": "x,y,yaw\n0,0,0\n0.6,0,0\n",
    "close": "x,y,yaw\n0,0,0\n0.001,0,0\n",
    "yaw": "x,y,yaw\n0,0,0\n0.1,0,0.9\n",
    "turn": "x,y,yaw\n0,0,0\n0.1,0,0\n0.1,0.1,0.3\n",
    "range": "x,y,yaw\n9000,0,0\n9000.1,0,0\n",
    "not_finite": "x,y,yaw\n0,0,0\n0.1,0,inf\n",
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_path_files_refused_with_pythons_message(native, case: str, tmp_path: Path) -> None:
    """Every check of the contract refuses the same files with PathError's message."""
    file = tmp_path / f"{case}.csv"
    file.write_text(BAD_FILES[case])
    with pytest.raises(PathError) as python_error:
        ReferencePath.from_csv(file)
    core = native.NativeController("lmpc")
    with pytest.raises(ConfigError) as c_error:
        core.load_path_file(file)
    assert str(c_error.value) == str(python_error.value)
