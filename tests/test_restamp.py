"""python -m studies.restamp (studies/restamp.py): which stale results a behaviour-keeping
change may restamp, and what counts as the same behaviour in a frame log."""
from __future__ import annotations

import shutil
from pathlib import Path

import cantools
import pytest

from studies import provenance, restamp

ROOT = Path(__file__).resolve().parent.parent
DATABASE = cantools.database.load_file(str(ROOT / "can_defs" / "vehicle.dbc"))
#: STEER_TORQUE_CMD (0x200) and CTRL_DIAG (0x201) of one control step.
COMMAND = "(1700000000.100000) vcan0 200#0102030405060708 T"


def _diag(solve_us: int, cycle_us: int, qp_iter: int = 7) -> bytes:
    message = DATABASE.get_message_by_name("CTRL_DIAG")
    return message.encode({"CRC": solve_us % 256, "CNT": 3, "QP_STATUS": 1, "SOLVE_TIME_US": solve_us,
                           "CYCLE_TIME_US": cycle_us, "QP_ITER": qp_iter, "OVERRUNS": 0, "FAULTS": 0})


def _log(path: Path, start: float, diag: bytes, command: str = COMMAND) -> Path:
    lines = [f"({start:.6f}) vcan0 100#6200CC0300000000 R",
             command.replace("(1700000000.100000)", f"({start + 0.1:.6f})"),
             f"({start + 0.1:.6f}) vcan0 201#{diag.hex().upper()} T"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_wall_clock_and_start_time_are_not_behaviour(tmp_path: Path) -> None:
    base = _log(tmp_path / "base.log", 1700000000.0, _diag(120, 900))
    now = _log(tmp_path / "now.log", 1800000000.0, _diag(95, 640))
    assert restamp.first_difference(base, now, DATABASE) is None


def test_a_changed_command_or_iteration_count_is_named(tmp_path: Path) -> None:
    base = _log(tmp_path / "base.log", 1700000000.0, _diag(120, 900))
    other_command = _log(tmp_path / "cmd.log", 1700000000.0, _diag(120, 900),
                         COMMAND.replace("0102030405060708", "0102030405060709"))
    other_iterations = _log(tmp_path / "iter.log", 1700000000.0, _diag(120, 900, qp_iter=8))
    assert "frame 2" in restamp.first_difference(base, other_command, DATABASE)
    assert "frame 3" in restamp.first_difference(base, other_iterations, DATABASE)
    shorter = tmp_path / "short.log"
    shorter.write_text("".join(base.read_text().splitlines(keepends=True)[:2]))
    assert "3 frames at the base, 2 now" in restamp.first_difference(base, shorter, DATABASE)


def test_an_unreadable_line_is_an_error(tmp_path: Path) -> None:
    broken = tmp_path / "broken.log"
    broken.write_text("not a frame\n")
    with pytest.raises(restamp.RestampError, match="not candump frames were skipped: line 1"):
        restamp.behaviour_frames(broken, DATABASE)
    # beside good frames too: a log read in part proves nothing
    partly = _log(tmp_path / "partly.log", 1700000000.0, _diag(120, 900))
    lines = partly.read_text().splitlines(keepends=True)
    partly.write_text(lines[0] + "not a frame\n" + "".join(lines[1:]))
    with pytest.raises(restamp.RestampError, match="not candump frames were skipped: line 2"):
        restamp.behaviour_frames(partly, DATABASE)


#: The fake project's code that its smoke runs.
SMOKED = frozenset({"controller/__init__.py", "controller/law.py"})


def test_the_smoke_covers_the_ecus_and_the_plant_not_training_or_studies() -> None:
    covered = restamp.smoke_sources(ROOT)
    assert {"controller/observed_mpc.py", "hil/recorder.py", "models/vehicle.py", "firmware_sim/ecu.py",
            "firmware/src/ecu_core.c"} <= covered
    assert "models/koopman_train.py" not in covered  # training: the closed-loop smoke trains nothing
    # the smoke injects no fault and runs no replay: their code is not covered
    assert not {"hil/faults.py", "hil/fault_injector.py", "hil/fault_cases/catalogue.py", "hil/replay.py",
                "hil/commands/faults.py"} & covered
    assert not any(name.startswith("studies/") for name in covered)


def _project(root: Path) -> None:
    """A tiny project: a product package, a study module and a data file, four results
    files stamped by three commands."""
    (root / "controller").mkdir(parents=True)
    (root / "controller" / "__init__.py").write_text("")
    (root / "controller" / "law.py").write_text("GAIN = 2\n")
    (root / "studies").mkdir()
    (root / "studies" / "__init__.py").write_text("")
    (root / "studies" / "study.py").write_text("import controller.law\n")
    (root / "tuning.toml").write_text("q = 1\n")
    (root / "results").mkdir()
    for name in ("table.md", "other.md", "timing.md", "data.md"):
        (root / "results" / name).write_text(name)
    provenance.stamp([root / "results" / "table.md", root / "results" / "other.md"], "make tables",
                     modules=["studies.study"], root=root)
    provenance.stamp(root / "results" / "timing.md", "make timing", modules=["studies.study"], root=root)
    provenance.stamp(root / "results" / "data.md", "make data", inputs=["tuning.toml"],
                     modules=["studies.study"], root=root)


def _commented(tmp_path: Path) -> tuple[Path, Path]:
    """A project at base and its copy now whose product code differs by a comment."""
    base, now = tmp_path / "base", tmp_path / "now"
    _project(base)
    shutil.copytree(base, now)
    (now / "controller" / "law.py").write_text("GAIN = 2  # same law, new comment\n")
    return base, now


def test_only_product_code_changes_of_non_machine_studies_are_candidates(tmp_path: Path) -> None:
    base, now = _commented(tmp_path)
    chosen, refused = restamp.candidates(base, now, SMOKED)
    assert [c.path for c in chosen] == ["results/data.md", "results/other.md", "results/table.md"]
    assert chosen[0].changed == ("controller/law.py",)
    assert "measures the machine" in refused["results/timing.md"]

    (now / "tuning.toml").write_text("q = 2\n")  # a data input: its study must run again
    (now / "studies" / "study.py").write_text("import controller.law  # edited\n")
    chosen, refused = restamp.candidates(base, now, SMOKED)
    assert chosen == []
    assert "changed beyond the code the smoke runs: studies/study.py, tuning.toml" in refused["results/data.md"]
    assert "changed beyond the code the smoke runs: studies/study.py" in refused["results/table.md"]


def test_excluded_files_are_left_stale(tmp_path: Path) -> None:
    base, now = _commented(tmp_path)
    chosen, _ = restamp.candidates(base, now, SMOKED)
    kept, left = restamp.excluded_candidates(chosen, ["results/ta*", "results/none.md"])
    assert [c.path for c in kept] == ["results/data.md", "results/other.md"]
    assert [c.path for c in left] == ["results/table.md"]
    assert restamp.excluded_candidates(chosen, []) == (chosen, [])


def test_a_stamp_stale_already_at_the_base_is_refused(tmp_path: Path) -> None:
    base, now = tmp_path / "base", tmp_path / "now"
    _project(now)
    shutil.copytree(now, base)
    (base / "controller" / "law.py").write_text("GAIN = 3\n")  # the base differed from the stamp
    (now / "controller" / "law.py").write_text("GAIN = 4\n")
    _, refused = restamp.candidates(base, now, SMOKED)
    assert refused["results/table.md"] == "its stamp was not current at the base revision"


def test_restamp_moves_the_stamp_and_drops_whole_known_stale_rows(tmp_path: Path) -> None:
    base, now = tmp_path / "base", tmp_path / "now"
    _project(base)
    shutil.copytree(base, now)
    (now / "controller" / "law.py").write_text("GAIN = 2\n\n")
    (now / "results" / "KNOWN_STALE.md").write_text(
        "| Files | Regenerates them | Why |\n|---|---|---|\n"
        "| `results/table.md`, `results/other.md` | `make tables` | long |\n"
        "| `results/timing.md` | `make timing` | machine |\n")
    chosen, _ = restamp.candidates(base, now, SMOKED)
    restamp.restamp([c for c in chosen if c.path != "results/data.md"], "abc123", "python -m studies.restamp --base abc123",
                    now)
    stale = {entry.path for entry in provenance.check(now)}
    assert stale == {"results/data.md", "results/timing.md"}
    entry = provenance.load_manifest(now)["results/table.md"]
    assert entry["restamped"] == {"base": "abc123", "check": "python -m studies.restamp --base abc123",
                                  "changed": ["controller/law.py"]}
    assert restamp.drop_known_stale_rows({"results/table.md", "results/other.md"}, now) == ["make tables"]
    assert "make timing" in (now / "results" / "KNOWN_STALE.md").read_text()
    assert "make tables" not in (now / "results" / "KNOWN_STALE.md").read_text()
