"""Replay rebuilds the recorded ECU: a run with ``--excite`` or ``--model`` records both in
its sidecar with a SHA-256 of every input file, ``eso-hil replay`` rebuilds the same ECU
from it (MATCH) and refuses, with one ``error:`` line naming the file, once a recorded file
has changed or gone. And cut-off BLF and ASC recordings: read as incomplete with a warning,
the frames before the cut replay to a MATCH that says the log was incomplete.

Each test records a short run of ``dlc_smoke`` (4 s of virtual time, about 1.5 s here)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from hil.logio import read_log, read_sidecar

pytest.importorskip("osqp")

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    """``python -m hil`` with the run / replay / decode subcommands registered."""
    import hil.__main__ as cli

    for name in ("run", "replay", "decode"):
        monkeypatch.setitem(cli.SUBCOMMANDS, name, f"hil.commands.{name}")
    return cli.main


def _record(hil_cli, log: Path, controller: str, *extra: str) -> None:
    assert hil_cli(["run", "--scenario", "dlc_smoke", "--controller", controller,
                    "--log", str(log), *extra]) == 0


def _replay(hil_cli, capsys, log: Path, *extra: str) -> tuple[int, str, str]:
    status = hil_cli(["replay", str(log), *extra])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _bicycle_file(path: Path) -> Path:
    """A fitted bicycle (models/bicycle_fit.py's form) with softer front tyres than the
    nominal one, so the LMPC steers differently with it."""
    from models.bicycle import nominal_model_params
    from models.bicycle_fit import BICYCLE_FIELDS

    nominal = nominal_model_params()
    fields = {name: float(getattr(nominal, name)) for name in BICYCLE_FIELDS}
    fields["cornering_stiffness_front"] *= 0.7
    path.write_text(json.dumps({"kind": "linear_bicycle", "format": 1, **fields}))
    return path


def test_a_run_with_an_excitation_replays_to_a_match(hil_cli, capsys, tmp_path: Path) -> None:
    log = tmp_path / "drive.log"
    _record(hil_cli, log, "lmpc", "--excite", "prbs-torque")
    metadata = read_sidecar(log)
    assert metadata is not None and metadata.excite == "prbs-torque" and metadata.ecu == "python"
    assert {f.role for f in metadata.input_files} == {"path 1", "vehicle", "tuning"}
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "excitation: prbs-torque (from the sidecar)" in out
    assert "result: MATCH" in out
    # without the excitation the replay diverges once the program starts (2 s after ACTIVE)
    log.with_name("drive.log.json").write_text(
        json.dumps({"controller": "lmpc", "paths": {"1": "hil/paths/dlc.csv"}}))
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 3 and "first divergence: t = 2.0" in out


def test_a_run_with_a_bicycle_model_replays_and_a_changed_model_is_refused(
        hil_cli, capsys, tmp_path: Path) -> None:
    model = _bicycle_file(tmp_path / "bicycle.json")
    log = tmp_path / "drive.blf"
    _record(hil_cli, log, "lmpc", "--model", str(model))
    metadata = read_sidecar(log)
    assert metadata is not None and metadata.model == str(model)
    assert [Path(f.path) for f in metadata.input_files if f.role == "model"] == [model]
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and f"model: {model} (from the sidecar)" in out and "result: MATCH" in out

    model.write_text(model.read_text() + "\n")
    status, out, err = _replay(hil_cli, capsys, log)
    assert status == 1 and out == ""
    assert err.count("\n") == 1 and err.startswith("error: ")
    assert f"the model file {model} changed since the recording" in err and "--model" in err
    # another file given on purpose is the user's choice: no refusal
    status, out, _ = _replay(hil_cli, capsys, log, "--model", str(model))
    assert status in (0, 3) and "model: " in out and "(--model)" in out

    model.unlink()
    status, _, err = _replay(hil_cli, capsys, log)
    assert status == 1 and f"the model file {model} is missing" in err


def test_a_run_with_a_koopman_artefact_replays_to_a_match(hil_cli, capsys, tmp_path: Path) -> None:
    for suffix in (".npz", ".json"):
        shutil.copy(ROOT / "models" / "artifacts" / f"dk_paper_nominal{suffix}",
                    tmp_path / f"koopman{suffix}")
    log = tmp_path / "drive.log"
    _record(hil_cli, log, "eso-dkmpc", "--model", str(tmp_path / "koopman"))
    metadata = read_sidecar(log)
    assert metadata is not None
    assert sorted(Path(f.path).name for f in metadata.input_files if f.role == "model") == [
        "koopman.json", "koopman.npz"]
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "result: MATCH" in out
    (tmp_path / "koopman.npz").write_bytes((tmp_path / "koopman.npz").read_bytes() + b"\0")
    status, _, err = _replay(hil_cli, capsys, log)
    assert status == 1 and "koopman.npz changed since the recording" in err


def test_a_changed_tuning_replays_with_a_note(hil_cli, capsys, tmp_path: Path) -> None:
    """The tuning is part of the build, like the code: a replay against a changed build
    runs (that is how a regression is found) and says why it may differ."""
    log = tmp_path / "drive.log"
    _record(hil_cli, log, "lmpc")
    sidecar = log.with_name("drive.log.json")
    data = json.loads(sidecar.read_text())
    for entry in data["input_files"]:
        if entry["role"] == "tuning":
            entry["sha256"] = "0" * 64
    sidecar.write_text(json.dumps(data))
    status, out, _ = _replay(hil_cli, capsys, log)
    assert status == 0 and "note: the tuning file" in out and "changed since the recording" in out


@pytest.mark.parametrize("suffix, keep", [(".blf", 5000), (".asc", 20000)])
def test_a_cut_vector_log_is_incomplete_and_replays_up_to_the_cut(
        hil_cli, capsys, tmp_path: Path, suffix: str, keep: int) -> None:
    whole = tmp_path / f"run{suffix}"
    _record(hil_cli, whole, "lmpc")
    assert read_log(whole).complete and not read_log(whole).warnings
    cut = tmp_path / f"trunc{suffix}"
    cut.write_bytes(whole.read_bytes()[:keep])
    shutil.copy(whole.with_name(whole.name + ".json"), cut.with_name(cut.name + ".json"))
    capsys.readouterr()  # the run's summary

    assert hil_cli(["decode", str(cut), "--json"]) == 0
    captured = capsys.readouterr()
    decoded = json.loads(captured.out)
    assert decoded["complete"] is False and decoded["warnings"]
    assert "warning: " in captured.err and ("truncated" in captured.err or "End TriggerBlock" in captured.err)
    contents = read_log(cut)
    assert 0 < len(contents.messages) < len(read_log(whole).messages)

    status, out, _ = _replay(hil_cli, capsys, cut)
    assert status == 0 and "first divergence: none" in out
    assert "result: MATCH (the log is incomplete" in out
