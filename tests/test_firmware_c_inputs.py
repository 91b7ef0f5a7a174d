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
