"""studies.identification_least_squares (issue 40, item 3 on the identification log): the
refusal of models tested on other pieces, the table and ratios from made-up figures, the
cache key, and the CLI's errors. No training and no log: a few seconds."""
from __future__ import annotations

from pathlib import Path

import pytest

from models.errors import KoopmanError
from studies.identification_least_squares import (
    CANDIDATE_LABEL, DEEP_LABEL, GOAL_RATIO, cache_key, check_same_test_pieces, main, markdown, split_options,
    summarise)


def _figures(vx: float, vy: float, yaw_rate: float) -> dict[str, dict[str, float]]:
    """Made-up figures of one model: the 2 s RMSE twice the 1 s one."""
    return {state: {"one_step_rmse": value / 10, "1 s": value, "2 s": 2 * value}
            for state, value in (("vx", vx), ("vy", vy), ("yaw_rate", yaw_rate))}


def _split(test: list[str]) -> dict[str, list[str]]:
    return {"train": ["log#000"], "validation": ["log#001"], "test": test}


def test_same_test_pieces_in_any_order_are_accepted() -> None:
    pieces = check_same_test_pieces({"deep seed 0": _split(["log#004", "log#019"]),
                                     "edmdc-linear": _split(["log#019", "log#004"])})
    assert pieces == ["log#004", "log#019"]


def test_other_test_pieces_are_refused_naming_the_model() -> None:
    with pytest.raises(KoopmanError, match=r"not tested on the same pieces.*deep seed 1"):
        check_same_test_pieces({"deep seed 0": _split(["log#004", "log#019"]),
                                "deep seed 1": _split(["log#004", "log#007"])})


def test_no_model_is_refused() -> None:
    with pytest.raises(KoopmanError, match="no model"):
        check_same_test_pieces({})


def test_summary_mean_min_max_and_ratio_to_the_best_lift() -> None:
    deep = {DEEP_LABEL: [_figures(0.04, 0.010, 0.004), _figures(0.06, 0.020, 0.002)]}
    lifts = {"edmdc-linear": _figures(0.05, 0.030, 0.010), "edmdc-bilinear": _figures(0.05, 0.015, 0.020)}
    summary = summarise(deep, lifts)
    cell = summary["rows"][0]["figures"]["vy"]["1 s"]
    assert cell == pytest.approx({"mean": 0.015, "min": 0.010, "max": 0.020})
    goals = {(g["state"], g["horizon"]): g for g in summary["goals"]}
    assert set(goals) == {(s, h) for s in ("vy", "yaw_rate") for h in ("1 s", "2 s")}
    assert {g["model"] for g in summary["goals"]} == {DEEP_LABEL}
    vy = goals[("vy", "1 s")]
    assert vy["best_least_squares"] == "edmdc-bilinear"
    assert vy["ratio"] == pytest.approx(0.015 / 0.015)
    assert vy["met"] is False
    yaw = goals[("yaw_rate", "2 s")]
    assert yaw["best_least_squares"] == "edmdc-linear"
    assert yaw["ratio"] == pytest.approx(0.003 / 0.010)
    assert yaw["met"] is True and yaw["goal"] == GOAL_RATIO


def test_each_deep_form_has_its_row_and_its_own_goals_before_the_lifts() -> None:
    deep = {DEEP_LABEL: [_figures(0.04, 0.010, 0.004), _figures(0.06, 0.020, 0.002)],
            CANDIDATE_LABEL: [_figures(0.05, 0.012, 0.006), _figures(0.05, 0.012, 0.010)]}
    lifts = {"edmdc-linear": _figures(0.05, 0.030, 0.010), "edmdc-bilinear": _figures(0.05, 0.015, 0.020)}
    summary = summarise(deep, lifts)
    assert [row["label"] for row in summary["rows"]] == [DEEP_LABEL, CANDIDATE_LABEL, "edmdc-linear", "edmdc-bilinear"]
    candidate = {(g["state"], g["horizon"]): g for g in summary["goals"] if g["model"] == CANDIDATE_LABEL}
    assert len(summary["goals"]) == 8 and len(candidate) == 4
    assert candidate[("yaw_rate", "1 s")]["ratio"] == pytest.approx(0.008 / 0.010)
    assert candidate[("vy", "1 s")]["ratio"] == pytest.approx(0.012 / 0.015)
    text = markdown(summary, Path("log"), [0, 1], ["log#004"])
    assert text.index(f"{DEEP_LABEL}:") < text.index(f"{CANDIDATE_LABEL}:")
    assert "- yaw_rate, 1 s: deep 0.0080 / edmdc-linear 0.0100 = 0.80: met." in text


def test_a_form_without_seeds_is_refused() -> None:
    with pytest.raises(KoopmanError, match="no deep model"):
        summarise({DEEP_LABEL: []}, {"edmdc-linear": _figures(0.05, 0.030, 0.010)})


def test_markdown_names_each_goal_with_its_ratio_and_verdict() -> None:
    summary = summarise({DEEP_LABEL: [_figures(0.04, 0.010, 0.004), _figures(0.06, 0.020, 0.002)]},
                        {"edmdc-linear": _figures(0.05, 0.030, 0.010),
                         "edmdc-bilinear": _figures(0.05, 0.015, 0.020)})
    text = markdown(summary, Path("build/identification/drive_changed.log"), [0, 1], ["log#004", "log#019"])
    assert f"| {DEEP_LABEL}, 2 seeds | " in text
    assert "0.0150 [0.0100, 0.0200]" in text
    assert "- vy, 1 s: deep 0.0150 / edmdc-bilinear 0.0150 = 1.00: NOT met." in text
    assert "- yaw_rate, 2 s: deep 0.0060 / edmdc-linear 0.0200 = 0.30: met." in text
    assert "seeds 0, 1 (2 seeds)" in text
    assert "log#004, log#019" in text


def test_cache_key_depends_on_log_vehicle_and_options() -> None:
    base = cache_key("a" * 64, "b" * 64, ["--seed", "0"])
    assert base == cache_key("a" * 64, "b" * 64, ["--seed", "0"])
    assert len({base, cache_key("c" * 64, "b" * 64, ["--seed", "0"]),
                cache_key("a" * 64, "c" * 64, ["--seed", "0"]), cache_key("a" * 64, "b" * 64, ["--seed", "1"])}) == 4


def test_split_options_pin_the_test_and_validation_pieces() -> None:
    assert split_options(None) == []
    assert split_options(_split(["log#004", "log#019"])) == ["--val-runs", "log#001", "--test-runs",
                                                              "log#004,log#019"]


def test_cli_missing_log_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text("")
    code = main(["--log", str(tmp_path / "missing.log"), "--vehicle", str(vehicle), "--out", str(tmp_path / "out"),
                 "--work", str(tmp_path / "work")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: --log ") and "missing.log" in err and "make identify" in err
    assert not (tmp_path / "work").exists() and not (tmp_path / "out").exists()


def test_cli_missing_vehicle_file_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "drive.log"
    log.write_text("")
    code = main(["--log", str(log), "--vehicle", str(tmp_path / "none.toml"), "--out", str(tmp_path / "out")])
    assert code == 2
    assert "error: --vehicle " in capsys.readouterr().err


def test_cli_bad_seeds_are_refused(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--log", "x.log", "--vehicle", "v.toml", "--out", str(tmp_path), "--seeds", "0,a"])
    assert exit_info.value.code == 2


@pytest.mark.parametrize("options, row_name", [("CANDIDATE_OPTIONS", "DICTIONARY_LIGHT_ANCHOR_ROW"),
                                               ("NO_SQUARE_OPTIONS", "DICTIONARY_NO_SQUARE_ROW")])
def test_candidate_options_are_the_table1_rows_settings_through_the_trainers_parser(options: str,
                                                                                    row_name: str) -> None:
    import studies.identification_least_squares as study
    import studies.table1 as table1
    from models.koopman_cli import build_parser

    args = build_parser().parse_args(["--logs", "drive.log", "--out", "out", *getattr(study, options)])
    row = getattr(table1, row_name).overrides
    parsed = {"mirror_symmetric": args.mirror_symmetric, "n_features": args.features,
              "even_features": args.even_features, "servo_lag": args.servo_lag,
              "steer_bilinear": args.steer_bilinear, "dictionary": tuple(args.dictionary),
              "gain_anchor": args.gain_anchor}
    assert parsed == {name: row[name] for name in parsed} and set(row) == set(parsed)


def test_a_setting_without_a_trainer_option_is_refused() -> None:
    from studies.identification_least_squares import trainer_options

    assert trainer_options({"gain_anchor": 2.5, "servo_lag": False}) == ("--gain-anchor", "2.5")
    with pytest.raises(KoopmanError, match="lateral_per_step"):
        trainer_options({"n_features": 8, "lateral_per_step": True})


def test_markdown_gives_the_stretches_within_the_training_range_their_own_table_and_goals() -> None:
    lifts = {"edmdc-linear": _figures(0.05, 0.030, 0.010), "edmdc-bilinear": _figures(0.05, 0.015, 0.020)}
    summary = summarise({DEEP_LABEL: [_figures(0.2, 0.010, 0.004)]}, lifts)
    within = {"summary": summarise({DEEP_LABEL: [_figures(0.02, 0.020, 0.004)]}, lifts),
              "outside": [{"run": "log#006", "state": "vx", "samples": 882, "of": 1224, "low": 2.43, "high": 12.34}],
              "training_min": {"vx": 3.38}, "training_max": {"vx": 30.13}, "within_samples": 2785, "test_samples": 3672}
    text = markdown(summary, Path("log"), [0], ["log#004", "log#006"], within)
    before, after = text.split("## Within the training pieces' states")
    assert "- log#006: 882 of 1224 samples with vx outside 3.38 .. 30.13 (the piece's 2.43 .. 12.34)" in after
    assert "(2785 of 3672 samples)" in after
    assert "- vy, 1 s: deep 0.0100 / edmdc-bilinear 0.0150 = 0.67: met." in before
    assert "- vy, 1 s: deep 0.0200 / edmdc-bilinear 0.0150 = 1.33: NOT met." in after
    assert "0.0200" in after and "| 0.2000 |" not in after


def test_the_three_deep_forms_are_identifys_then_the_two_table1_candidates() -> None:
    from studies.identification_least_squares import CANDIDATE_OPTIONS, DEEP_FORMS, NO_SQUARE_OPTIONS

    assert [(prefix, options) for _, prefix, options in DEEP_FORMS] == [
        ("deep", ()), ("dictionary", CANDIDATE_OPTIONS), ("no-square", NO_SQUARE_OPTIONS)]
    dictionary = NO_SQUARE_OPTIONS[NO_SQUARE_OPTIONS.index("--dictionary") + 1]
    assert dictionary == "vy/vx,r/vx,vx*r"
