"""Input files of both ECUs held to the same verdict (issue 38): an output of a command is
never one of its inputs, in the C executable, the Python ECU and ``hil run``."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)

ROOT = Path(__file__).resolve().parent.parent
ECU = ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")
PATH = ROOT / "hil" / "paths" / "dlc.csv"


def start(which: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """One ECU process (``c`` or ``python``) on a bus that exists nowhere (nothing is sent:
    every case here must stop before the bus is opened)."""
    if which == "c":
        command = [str(ECU), "--interface", "socketcand", "--channel", "vcan0", "--port", "1", *args]
    else:
        command = [sys.executable, "-m", "firmware_sim", "--interface", "virtual", "--channel", "inputs", *args]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=timeout, check=False)


def last_line(result: subprocess.CompletedProcess) -> str:
    return (result.stderr.strip().splitlines() or [""])[-1]


def input_cases(tmp_path: Path) -> dict[str, tuple[list[str], Path, list[str]]]:
    """Per input option: (arguments, the input file, the ECUs that take the option)."""
    path = tmp_path / "path.csv"
    shutil.copy(PATH, path)
    dbc = tmp_path / "vehicle.dbc"
    shutil.copy(ROOT / "can_defs" / "vehicle.dbc", dbc)
    data = tmp_path / "data.bin"
    shutil.copy(ROOT / "build" / "firmware" / "ecu_data.bin", data)
    program = tmp_path / "doublet.csv"
    program.write_text("time_s,steer_rad\n0.0,0.0\n0.5,0.02\n1.0,0.0\n")
    model = tmp_path / "dk"
    for suffix in (".npz", ".json"):
        shutil.copy((ROOT / "models" / "artifacts" / "dk_d5").with_suffix(suffix), model.with_suffix(suffix))
    common = ["--controller", "lmpc", "--lockstep"]
    return {
        "path": ([*common, "--path", f"1={path}"], path, ["c", "python"]),
        "dbc": ([*common, "--path", f"1={PATH}", "--dbc", str(dbc)], dbc, ["c", "python"]),
        "excite": ([*common, "--path", f"1={PATH}", "--excite", str(program)], program, ["c", "python"]),
        "data": ([*common, "--path", f"1={PATH}", "--data", str(data)], data, ["c"]),
        "model (C: a data file)": ([*common, "--path", f"1={PATH}", "--model", str(data)], data, ["c"]),
        "model (artefact)": (["--controller", "eso-dkmpc", "--lockstep", "--path", f"1={PATH}", "--model",
                              str(model)], model.with_suffix(".npz"), ["python"]),
    }


@pytest.mark.parametrize("option", ["path", "dbc", "excite", "data", "model (C: a data file)", "model (artefact)"])
def test_timing_out_never_overwrites_an_input(native, option: str, tmp_path: Path) -> None:
    """``--timing-out INPUT --replace``: one error line, exit 2, the input unchanged, from
    every ECU that takes the option (before, the C ECU wrote its timing record over the
    path, data or program file, and the Python ECU over the model)."""
    args, source, ecus = input_cases(tmp_path)[option]
    before = source.read_bytes()
    for which in ecus:
        result = start(which, *args, "--timing-out", str(source), "--replace")
        assert result.returncode == 2, (which, result.stderr[-2000:])
        assert last_line(result) == f"error: --timing-out {source}: is one of the inputs of this run ({source})"
        assert source.read_bytes() == before


def test_a_link_to_an_input_is_the_input(native, tmp_path: Path) -> None:
    args, source, _ = input_cases(tmp_path)["path"]
    link = tmp_path / "link.npz"
    link.symlink_to(source)
    for which in ("c", "python"):
        result = start(which, *args, "--timing-out", str(link), "--replace")
        assert (result.returncode, last_line(result)) == (
            2, f"error: --timing-out {link}: is one of the inputs of this run ({source})"), which


@pytest.mark.parametrize("option", ["excite", "model"])
def test_hil_run_never_writes_its_log_over_the_ecus_inputs(option: str, tmp_path: Path) -> None:
    """``hil run --excite P.csv --log P.csv --replace`` and ``--model M --log M.npz``:
    refused before the run, the input unchanged."""
    from hil.commands.run import check_run_paths
    from hil.errors import OutputPathError
    from hil.scenario import load_scenario

    cases = input_cases(tmp_path)
    source = cases["excite" if option == "excite" else "model (artefact)"][1]
    before = source.read_bytes()
    extra = {"excite": str(source)} if option == "excite" else {"model": source.with_suffix("")}
    with pytest.raises(OutputPathError, match=r"is one of the inputs of this run"):
        check_run_paths(load_scenario("dlc_smoke"), source, None, True, **extra)
    assert source.read_bytes() == before


#: Probe files of the line rules (models/input_files.py, firmware/src/ecu_lines.c): both
#: ECUs refuse each with the same message (before, the C ECU split long lines and cut them
#: at a NUL, and took files the Python ECU refused).
PADDING = " " * 4200
LINE_PROBES = {
    "long_line": (b"x,y,yaw\n0,0,0\n0.1,0," + PADDING.encode() + b"0,1,2\n", "line 3: longer than 4096 bytes"),
    "long_header": (b"x,y,yaw" + PADDING.encode() + b"\n0,0,0\n", "line 1: longer than 4096 bytes"),
    "nul": (b"x,y,yaw\n0,0,0\n0.1,0\x00junk,0\n0.2,0,0\n", "line 3: holds a NUL byte"),
    "nul_header": (b"x,y\x00,yaw\n0,0,0\n0.1,0,0\n", "line 1: holds a NUL byte"),
    "not_utf8": (b"x,y,yaw\n0,0,0\n0.1,0,0 \xff\n", "line 3: not UTF-8"),
    # a CSV number is ASCII without underscores (models/input_files.py csv_number): before,
    # the Python ECU read 1_0 as 10 and an Arabic-Indic digit as its value
    "underscore": (b"x,y,yaw\n0,0,0\n0.25,1_0,0\n", "line 3 column y: not a number: '1_0'"),
    "non_ascii_digit": ("x,y,yaw\n0,0,0\n0.25,\u0661,0\n".encode(), "line 3 column y: not a number: '\u0661'"),
}


def path_probe(case: str, tmp_path: Path) -> tuple[Path, str]:
    """A probe path file and the end of the message both ECUs give for it."""
    if case == "dev_zero":
        return Path("/dev/zero"), "/dev/zero: line 1: holds a NUL byte"
    file = tmp_path / f"{case}.csv"
    if case == "huge":   # 16 MiB + in lines of 4000 bytes: refused at the line that crosses it
        row = ("0.0,0.0,0.0" + " " * 3988 + "\n").encode()
        file.write_bytes(b"x,y,yaw\n" + row * 4300)
        return file, f"{file}: larger than 16777216 bytes (the limit of this file)"
    content, message = LINE_PROBES[case]
    file.write_bytes(content)
    return file, f"{file}: {message}"


@pytest.mark.parametrize("case", [*LINE_PROBES, "dev_zero", "huge"])
def test_path_files_over_the_line_and_size_limits_get_one_verdict(native, case: str, tmp_path: Path) -> None:
    from controller.errors import PathError
    from controller.reference import ReferencePath
    from firmware_sim.errors import ConfigError

    file, message = path_probe(case, tmp_path)
    with pytest.raises(PathError) as python_error:
        ReferencePath.from_csv(file)
    core = native.NativeController("lmpc")
    with pytest.raises(ConfigError) as c_error:
        core.load_path_file(file)
    assert str(python_error.value) == message
    assert str(c_error.value) == message


def test_the_c_ecu_does_not_hang_on_a_path_from_dev_zero(native) -> None:
    """``--path 1=/dev/zero``: refused at its first line (before, start-up never ended)."""
    result = start("c", "--controller", "lmpc", "--lockstep", "--path", "1=/dev/zero", timeout=20)
    assert "/dev/zero: line 1: holds a NUL byte" in result.stderr


@pytest.mark.parametrize("case", ["long_line.csv", "nul.toml", "zero.csv", "huge.csv"])
def test_excitation_programs_over_the_line_and_size_limits_get_one_verdict(native, case: str,
                                                                           tmp_path: Path) -> None:
    file = tmp_path / case
    if case == "long_line.csv":
        file.write_text("time_s,steer_rad\n0.0,0.0\n1.0," + PADDING + "0.01\n")
        message = f"error: --excite {file}: line 3: longer than 4096 bytes"
    elif case == "nul.toml":
        file.write_bytes(b'kind = "prbs"\nhold_s = 0.5\x00\n')
        message = f"error: --excite {file}: line 2: holds a NUL byte"
    elif case == "zero.csv":
        file.symlink_to("/dev/zero")
        message = f"error: --excite {file}: line 1: holds a NUL byte"
    else:
        file.write_text("time_s,steer_rad\n" + "".join(f"{k}.0,0.0" + " " * 3990 + "\n" for k in range(1100)))
        message = f"error: --excite {file}: larger than 4194304 bytes (the limit of this file)"
    args = ["--controller", "lmpc", "--lockstep", "--path", f"1={PATH}", "--excite", str(file)]
    for which in ("c", "python"):
        result = start(which, *args, timeout=30)
        assert (result.returncode, last_line(result)) == (2, message), which


def test_the_c_command_line_refuses_what_it_cannot_use_before_the_bus(native, tmp_path: Path) -> None:
    """An unknown controller, a folder as a path file and a data file that cannot be read
    exit 2 before the bus is opened (port 1 would be exit 1), as the Python ECU; before,
    each latched FAULT on the bus (issue 38, item 13)."""
    folder = tmp_path / "paths"
    folder.mkdir()
    common = ["--lockstep", "--path", f"1={PATH}"]
    cases = [
        (["--controller", "foo", *common], "error: --controller 'foo': the C ECU has eso-dkmpc, dkmpc, lmpc"),
        (["--controller", "lmpc", "--lockstep", "--path", f"1={folder}"],
         f"error: --path '1={folder}': cannot read {folder}: it is a folder"),
        (["--controller", "lmpc", *common, "--data", str(tmp_path / "missing.bin")],
         f"error: --data {tmp_path / 'missing.bin'}: cannot read the ECU data file: No such file or directory"),
        (["--controller", "lmpc", *common, "--data", str(folder)],
         f"error: --data {folder}: cannot read the ECU data file: it is a folder"),
    ]
    for args, message in cases:
        result = start("c", *args)
        assert (result.returncode, last_line(result)) == (2, message), result.stderr
    python = start("python", "--controller", "lmpc", "--lockstep", "--path", f"1={folder}")
    assert (python.returncode, last_line(python)) == (2, f"error: --path '1={folder}': cannot read {folder}: "
                                                         "it is a folder")
    upper = start("c", "--controller", "LMPC", *common)   # any case, as the Python ECU
    assert upper.returncode == 1 and "cannot" in last_line(upper)   # loaded; only the bus is missing


def test_help_and_the_default_data_file_beside_the_executable(native, tmp_path: Path) -> None:
    help_run = subprocess.run([str(ECU), "--help"], capture_output=True, text=True, timeout=30, check=False)
    assert help_run.returncode == 0 and help_run.stdout.startswith("usage: ecu --version")
    samples = tmp_path / "samples.csv"
    samples.write_text("vx,vy,yaw_rate,x,y,yaw,steer_angle,drive_torque,target_speed\n"
                       "10,0,0,0,0,0,0,0,10\n10,0,0,0.25,0,0,0,0,10\n")
    # started from another folder: the data file is found beside the executable
    replay = subprocess.run([str(ECU), "--controller", "lmpc", "--path", f"1={PATH}", "--replay", str(samples)],
                            cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False)
    assert replay.returncode == 0, replay.stderr
    assert len(replay.stdout.strip().splitlines()) == 3


def test_a_dbc_from_dev_zero_is_one_line_from_both_ecus(native) -> None:
    """``--dbc /dev/zero``: the C ECU hashed it for ever, the Python ECU read it whole (a
    MemoryError); both read at most the DBC's bound and give one line, exit 2."""
    message = "error: cannot load DBC /dev/zero: larger than 4194304 bytes (the limit of this file)"
    for which in ("c", "python"):
        result = start(which, "--controller", "lmpc", "--lockstep", "--path", f"1={PATH}", "--dbc", "/dev/zero",
                       timeout=60)
        assert (result.returncode, last_line(result)) == (2, message), which
