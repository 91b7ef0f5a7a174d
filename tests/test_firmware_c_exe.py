"""The ECU executable build/firmware/ecu (first part: --version, start-up checks, --replay)
and the C path-file reader, against the Python ECU's behaviour."""
from __future__ import annotations

import os
import subprocess
import sys
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
    (["--controller", "nmpc", "--path", "1=hil/paths/dlc.csv"],
     "error: --controller 'nmpc': the C ECU has eso-dkmpc, dkmpc, lmpc"),
    (["--controller", "lmpc", "--path", "1=hil/paths/missing.csv"], "error: hil/paths/missing.csv: path file not found"),
    (["--controller", "lmpc", "--path", "x=hil/paths/dlc.csv"], "error: --path 'x=hil/paths/dlc.csv': expected ID"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--data", "nowhere.bin"],
     "error: --data nowhere.bin: cannot read the ECU data file: No such file or directory"),
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
     "error: --timing-out hil/paths/dlc.csv: is one of the inputs of this run (hil/paths/dlc.csv)"),
    (["--interface", "socketcand", "--channel", "vcan0", "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv",
      "--lockstep", "--timing-out", "no/such/folder/t.npz"],
     "error: --timing-out no/such/folder/t.npz: folder no/such/folder does not exist"),
    (["--interface", "socketcan", "--channel", "nosuchcan0", "--controller", "lmpc", "--path",
      "1=hil/paths/dlc.csv", "--lockstep"], "error: cannot open CAN bus (interface=socketcan, channel=nosuchcan0)"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--dbc", "no/such.dbc", "--lockstep"],
     "error: --dbc no/such.dbc: cannot read: No such file or directory"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--model", "models/artifacts/dk_d5.npz", "--lockstep"],
     "error: --model models/artifacts/dk_d5.npz: the C ECU reads the data file of a model, not its artefact: "
     "write it with 'python firmware/tools/ecu_data.py --model models/artifacts/dk_d5.npz --out FILE.bin'"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--model", "a.bin", "--data", "b.bin"],
     "error: give --data or --model (a data file), not both"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--bitrate", "fast", "--lockstep"],
     "error: --bitrate: expected a bit rate in 1..8000000 bit/s, got 'fast'"),
    (["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--bitrate"], "error: --bitrate needs a value"),
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


def test_dbc_other_than_the_builds_is_refused_naming_both_hashes(native, tmp_path: Path) -> None:
    """--dbc: the build's DBC passes (--debug says so); any other file - one byte more -
    is one error line with its SHA-256 and the build's, exit 2, before anything runs."""
    import hashlib

    dbc = ROOT / "can_defs" / "vehicle.dbc"
    other = tmp_path / "other.dbc"
    other.write_bytes(dbc.read_bytes() + b"\n")
    result = run_ecu("--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--dbc", str(other), "--lockstep")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: --dbc {other}: SHA-256 {hashlib.sha256(other.read_bytes()).hexdigest()} differs from the DBC "
        f"this build's codecs were generated from (can_defs/vehicle.dbc, SHA-256 "
        f"{hashlib.sha256(dbc.read_bytes()).hexdigest()}); rebuild with make firmware for another CAN matrix"]
    # the hash itself on lengths around SHA-256's padding boundary (55, 56, 64 bytes)
    for size in (0, 55, 56, 63, 64, 65, 119, 120):
        other.write_bytes(bytes(range(size)))
        result = run_ecu("--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--dbc", str(other), "--lockstep")
        assert hashlib.sha256(bytes(range(size))).hexdigest() in result.stderr, size
    accepted = run_ecu("--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--dbc", str(dbc), "--debug",
                       "--replay", "/dev/null")
    assert f"debug: --dbc {dbc}: the build's DBC (SHA-256 equal)" in accepted.stderr
    assert accepted.stderr.strip().splitlines()[-1] == "error: --replay: empty samples file"


def test_model_takes_a_data_file_and_bitrate_is_a_note(native, tmp_path: Path) -> None:
    """--model FILE.bin is the data file (the replay equals --data's); --bitrate on
    socketcand is accepted with a note; --debug prints what was loaded."""
    from studies.bench import record_samples

    samples, _, _ = record_samples(scenario_name="dlc_smoke", driver="lmpc")
    rows = [",".join(repr(float(getattr(s, f))) for f in SAMPLE_FIELDS) for s in samples[:40]]
    (tmp_path / "samples.csv").write_text(",".join(SAMPLE_FIELDS) + "\n" + "\n".join(rows) + "\n")
    data = str(ROOT / "build" / "firmware" / "ecu_data.bin")
    common = ("--controller", "eso-dkmpc", "--path", "1=hil/paths/dlc.csv", "--replay", str(tmp_path / "samples.csv"))
    by_data, by_model = run_ecu(*common, "--data", data), run_ecu(*common, "--model", data, "--debug")
    assert by_data.returncode == by_model.returncode == 0, by_model.stderr
    assert by_model.stdout.splitlines()[1:] and [r.split(",")[:5] for r in by_model.stdout.splitlines()] == \
        [r.split(",")[:5] for r in by_data.stdout.splitlines()]
    assert f"debug: controller eso-dkmpc, data file {data}" in by_model.stderr
    result = run_ecu("--interface", "socketcand", "--channel", "vcan0", "--port", "1", "--controller", "lmpc",
                     "--path", "1=hil/paths/dlc.csv", "--lockstep", "--bitrate", "500000")
    assert result.returncode == 1  # no hub on port 1: the note came before the bus was opened
    assert result.stderr.splitlines()[0] == "note: --bitrate 500000 ignored: socketcand's daemon sets its bus's bit rate"


def test_footprint_report_reads_the_build(native, tmp_path: Path) -> None:
    """firmware/tools/footprint.py (make firmware-footprint): the executable's sections as
    binutils' size gives them, the report's largest frame is the largest of every .su line
    (our sources and the generated OSQP ones), and a missing build is one error line."""
    tool = ROOT / "firmware" / "tools" / "footprint.py"
    out = tmp_path / "footprint.md"
    folders = [ROOT / "build" / "firmware" / "obj-ecu", ROOT / "build" / "firmware" / "obj"]
    result = subprocess.run([sys.executable, str(tool), "--exe", str(ECU), *(f"--su={f}" for f in folders),
                             "--out", str(out)], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    text = out.read_text()
    frames = [(int(line.split("\t")[1]), line.split("\t")[0].rsplit(":", 1)[1])
              for folder in folders for su in folder.glob("*.su") for line in su.read_text().splitlines()]
    assert any(name.startswith("osqp_") for _, name in frames)  # the generated solver is counted
    largest, name = max(frames)
    assert f"stack (gcc `-fstack-usage`, {len(frames)} functions): largest own frames `{name}` {largest:,} B" in text
    text_b, data_b, bss_b = (int(v) for v in subprocess.run(["size", str(ECU)], capture_output=True, text=True,
                                                            check=True).stdout.splitlines()[1].split()[:3])
    assert f"text {text_b:,} B, data {data_b:,} B, bss {bss_b:,} B" in text and bss_b > 6_000_000
    missing = subprocess.run([sys.executable, str(tool), "--exe", str(tmp_path / "ecu"), "--out", str(out)],
                             capture_output=True, text=True, check=False)
    assert missing.returncode == 1
    assert missing.stderr.strip().splitlines() == [f"error: {tmp_path / 'ecu'}: no such executable (run make firmware)"]
