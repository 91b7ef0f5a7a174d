"""A run without ``--model`` records the files its controller is built on: the default
Koopman or DMDc artefact, models/vehicle.toml, and for the C ECU its data file
build/firmware/ecu_data.bin, each with its path and SHA-256 in the log's sidecar, so that
``eso-hil replay`` refuses with one ``error:`` line once one of them has changed, as it does
for ``--model`` files. A sidecar written before (no such record) replays as it did.

The repository's own files are never edited here: the sidecar is pointed at copies, and
the copies are changed."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hil.logio import file_sha256, read_sidecar
from hil.rig import recorded_ecu_files

pytest.importorskip("osqp")

ROOT = Path(__file__).resolve().parent.parent
LOCKSTEP_LOG = ROOT / "tests" / "data" / "logs" / "lockstep_lmpc.log"

#: Lists the files (outside Python's own) that building each controller opens, through an
#: audit hook: what the registry really reads, not what this module believes it reads.
_TRACE = r"""
import json, sys
from pathlib import Path
opened, tracing = [], [False]
def hook(event, args):
    if tracing[0] and event == "open" and isinstance(args[0], (str, Path)):
        opened.append(str(Path(args[0]).resolve()))
sys.addaudithook(hook)
from controller.registry import create_controller
result = {}
for case in json.loads(sys.argv[1]):
    name, model = case
    opened.clear(); tracing[0] = True
    create_controller(name, model_path=model)
    tracing[0] = False
    python = tuple(str(Path(p).resolve()) for p in (sys.prefix, sys.base_prefix)) + ("/proc", "/dev")
    result[f"{name} {model}"] = sorted({p for p in opened if not p.endswith((".py", ".pyc", ".so"))
                                        and not p.startswith(python)})
print(json.dumps(result))
"""


def _bicycle_file(path: Path) -> Path:
    from models.bicycle import nominal_model_params
    from models.bicycle_fit import BICYCLE_FIELDS

    nominal = nominal_model_params()
    fields = {name: float(getattr(nominal, name)) for name in BICYCLE_FIELDS}
    path.write_text(json.dumps({"kind": "linear_bicycle", "format": 1, **fields}))
    return path


def test_the_recorded_files_are_those_each_controller_is_built_on(tmp_path: Path) -> None:
    from controller.registry import ALL_CONTROLLER_NAMES
    from controller.tuning import DEFAULT_TUNING_PATH, load_tuning

    bicycle = _bicycle_file(tmp_path / "bicycle.json")
    cases = [(name, None) for name in ALL_CONTROLLER_NAMES]
    cases += [("lmpc", str(bicycle)), ("eso-dkmpc", str(ROOT / "models/artifacts/dk_paper_nominal"))]
    done = subprocess.run([sys.executable, "-c", _TRACE, json.dumps(cases)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    opened = json.loads(done.stdout)
    for name, model in cases:
        recorded = {str(Path(file).resolve()) for _, file in recorded_ecu_files(name, model)}
        print(name, model, sorted(recorded))
        assert recorded | {str(DEFAULT_TUNING_PATH.resolve())} == set(opened[f"{name} {model}"])
    roles = {name: [role for role, _ in recorded_ecu_files(name, None)] for name in ALL_CONTROLLER_NAMES}
    tuning = load_tuning()
    for name in ("eso-dkmpc", "dkmpc", "dmdc-eso"):  # the vehicle file with the grip envelope on
        envelope = tuning.for_controller(name).grip_slip_excess > 0.0
        assert roles[name] == ["default model"] * 2 + ["vehicle"] * envelope
    assert roles["lmpc"] == roles["nmpc"] == roles["stanley"] == ["vehicle"]
    c_ecu = recorded_ecu_files("eso-dkmpc", None, ecu="c")
    assert ("C ECU data", ROOT / "build" / "firmware" / "ecu_data.bin") in c_ecu \
        or not (ROOT / "build" / "firmware" / "ecu_data.bin").is_file()
    assert all(role != "C ECU data" for role, _ in recorded_ecu_files("lmpc", bicycle, ecu="c"))


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    """``python -m hil`` with the run and replay subcommands registered."""
    import hil.__main__ as cli

    for name in ("run", "replay"):
        monkeypatch.setitem(cli.SUBCOMMANDS, name, f"hil.commands.{name}")
    return cli.main


def _replay(hil_cli, capsys, log: Path, *extra: str) -> tuple[int, str, str]:
    status = hil_cli(["replay", str(log), *extra])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _point_at_copies(log: Path, roles: set[str], folder: Path) -> list[Path]:
    """Rewrite the sidecar's records of ``roles`` to copies of their files in ``folder``
    (the hashes stay: the copies are equal); returns the copies."""
    sidecar = log.with_name(log.name + ".json")
    data = json.loads(sidecar.read_text())
    copies = []
    for entry in data["input_files"]:
        if entry["role"] in roles:
            copy = folder / Path(entry["file"]).name
            shutil.copy(ROOT / entry["file"], copy)
            entry["file"] = str(copy)
            copies.append(copy)
    sidecar.write_text(json.dumps(data))
    return copies


def test_a_changed_default_koopman_artefact_is_refused(hil_cli, capsys, tmp_path: Path) -> None:
    log = tmp_path / "drive.log"
    assert hil_cli(["run", "--scenario", "dlc_smoke", "--controller", "eso-dkmpc",
                    "--log", str(log)]) == 0
    metadata = read_sidecar(log)
    assert metadata is not None and metadata.model is None
    recorded = {Path(f.path).name: f.sha256 for f in metadata.input_files if f.role == "default model"}
    artefact = ROOT / "models" / "artifacts"
    assert recorded == {name: file_sha256(artefact / name) for name in ("dk_d5.npz", "dk_d5.json")}
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "result: MATCH" in out

    copies = _point_at_copies(log, {"default model"}, tmp_path)
    assert _replay(hil_cli, capsys, log)[0] == 0
    npz = next(copy for copy in copies if copy.suffix == ".npz")
    npz.write_bytes(npz.read_bytes() + b"\0")
    status, out, err = _replay(hil_cli, capsys, log)
    print(err)
    assert status == 1 and out == "" and err.count("\n") == 1 and err.startswith("error: ")
    assert f"the default model file {npz} changed since the recording" in err and "--model" in err
    # a model given on purpose replaces the default one: nothing to check
    status, out, _ = _replay(hil_cli, capsys, log, "--model", str(artefact / "dk_d5"))
    assert status == 0 and "result: MATCH" in out
    npz.unlink()
    status, _, err = _replay(hil_cli, capsys, log)
    assert status == 1 and f"the default model file {npz} is missing" in err

    # the same log as a sidecar written before these records: replays as it did
    sidecar = log.with_name(log.name + ".json")
    data = json.loads(sidecar.read_text())
    data["input_files"] = [e for e in data["input_files"] if e["role"] != "default model"]
    sidecar.write_text(json.dumps(data))
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "result: MATCH" in out


@pytest.mark.parametrize("role, file", [("vehicle", "models/vehicle.toml"),
                                        ("C ECU data", "build/firmware/ecu_data.bin")])
def test_a_changed_vehicle_or_c_ecu_data_file_is_refused(hil_cli, capsys, tmp_path: Path,
                                                         role: str, file: str) -> None:
    """A C-ECU LMPC log's sidecar records models/vehicle.toml (the replayed Python ECU's
    bicycle) and the C ECU's data file (what the recorded ECU ran on); neither has an
    option that replaces it, so the line says only to restore it."""
    source = ROOT / file
    if not source.is_file():
        pytest.skip(f"{file} is not built (make firmware)")
    log = tmp_path / "c_drive.log"
    shutil.copy(LOCKSTEP_LOG, log)
    copy = tmp_path / source.name
    shutil.copy(source, copy)
    sidecar = log.with_name(log.name + ".json")
    sidecar.write_text(json.dumps({
        "version": 3, "controller": "lmpc", "mode": "lockstep", "paths": {"1": "hil/paths/dlc.csv"},
        "ecu": "c", "model": None, "excite": None,
        "input_files": [{"role": role, "file": str(copy), "sha256": file_sha256(copy)}]}))
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "result: MATCH" in out

    copy.write_bytes(copy.read_bytes() + b"\n")
    status, out, err = _replay(hil_cli, capsys, log)
    print(err)
    assert status == 1 and out == "" and err.count("\n") == 1
    assert f"the {role} file {copy} changed since the recording" in err
    assert err.rstrip().endswith("restore the file")
    # a replay of another controller builds it on its own files: not this one's business
    status, out, _ = _replay(hil_cli, capsys, log, "--controller", "eso-dkmpc")
    assert status in (0, 3) and "controller: eso-dkmpc (--controller)" in out
