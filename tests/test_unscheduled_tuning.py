"""The tuning file without the speed schedule (make tables-unscheduled)."""
from __future__ import annotations

from pathlib import Path

from controller.tuning import DEFAULT_TUNING_PATH, SCHEDULED_WEIGHTS, load_tuning
from studies.unscheduled_tuning import main, unscheduled_text


def test_every_mpc_table_gets_one_weighting_at_every_speed(tmp_path: Path) -> None:
    out = tmp_path / "flat.toml"
    out.write_text(unscheduled_text(DEFAULT_TUNING_PATH.read_text(encoding="utf-8")), encoding="utf-8")
    shipped, flat = load_tuning(), load_tuning(out)
    changed = 0
    for name in ("eso-dkmpc", "dkmpc", "lmpc", "nmpc", "lmpc-eso", "dmdc-eso"):
        before, after = shipped.for_controller(name), flat.for_controller(name)
        for weight in SCHEDULED_WEIGHTS:
            assert getattr(after, f"low_speed_{weight}") == getattr(after, weight) == getattr(before, weight)
            changed += getattr(before, f"low_speed_{weight}") != getattr(before, weight)
        assert after.weights_at(5.0) == after.weights_at(30.0)
        unscheduled = {f"low_speed_{w}" for w in SCHEDULED_WEIGHTS}
        assert {k: v for k, v in vars(after).items() if k not in unscheduled} == \
            {k: v for k, v in vars(before).items() if k not in unscheduled}  # nothing else moved
    assert changed > 0  # the shipped file has a schedule to remove
    assert flat.for_controller("stanley") == shipped.for_controller("stanley")


def test_the_input_is_never_overwritten_and_an_output_needs_replace(tmp_path: Path, capsys) -> None:
    assert main(["--tuning", str(DEFAULT_TUNING_PATH), "--out", str(DEFAULT_TUNING_PATH)]) == 1
    assert "is the input tuning file" in capsys.readouterr().err
    out = tmp_path / "flat.toml"
    assert main(["--out", str(out)]) == 0
    assert main(["--out", str(out)]) == 1
    assert "--replace" in capsys.readouterr().err
    assert main(["--out", str(out), "--replace"]) == 0
