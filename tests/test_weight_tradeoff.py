"""The weight trade-off analysis: Pareto fronts, iso-robustness picks, the report."""
from __future__ import annotations

from studies.tuning_sweep import FAILURE_PENALTY_M
from studies.weight_tradeoff import Point, best_high_mu_within, markdown, pareto_front


def _point(high: float, low: float, q: float, *, tuned: bool = False, completed=(True, True)) -> Point:
    setting = (("q_position", q), ("q_yaw", 20.0), ("r_steer", 0.3), ("p_steer_rate", 300.0))
    return Point("lmpc", setting, high, low, completed, tuned)


POINTS = [_point(0.01, 0.50, 30.0), _point(0.02, 0.10, 10.0, tuned=True), _point(0.03, 0.12, 3.0),
          _point(0.05, 0.04, 1.0), _point(0.005, FAILURE_PENALTY_M, 100.0, completed=(True, False))]


def test_the_front_keeps_exactly_the_undominated_settings() -> None:
    front = pareto_front(POINTS)
    assert [p.setting[0][1] for p in front] == [100.0, 30.0, 10.0, 1.0]  # q 3 is beaten by q 10


def test_iso_robustness_picks_the_best_high_mu_within_the_low_mu_level() -> None:
    assert best_high_mu_within(POINTS, 0.1).setting[0][1] == 10.0
    assert best_high_mu_within(POINTS, 0.05).setting[0][1] == 1.0
    assert best_high_mu_within(POINTS, 0.01) is None
    # An incomplete run never qualifies, whatever its figures.
    assert best_high_mu_within(POINTS, 2 * FAILURE_PENALTY_M).setting[0][1] == 30.0


def test_the_report_marks_the_tuned_setting_and_failures() -> None:
    text = markdown({"lmpc": POINTS}, command="make tradeoff", wall_s=60.0, workers=2)
    assert "| LMPC | q_position 10, q_yaw 20, r_steer 0.3 | 0.0200 / 0.1000 | yes |" in text
    assert "not a tuning" in text
    assert "0.0050 (did not complete)" in text


def test_a_scheduled_tuned_setting_is_reported_with_its_low_speed_weights() -> None:
    """The tuned point of a scheduled tuning names the low-speed weights that differ."""
    scheduled = (("q_position", 3.0), ("q_yaw", 80.0), ("r_steer", 3.0), ("p_steer_rate", 300.0),
                 ("low_speed_q_position", 10.0), ("low_speed_q_yaw", 80.0), ("low_speed_r_steer", 0.3))
    points = POINTS[:1] + [Point("lmpc", scheduled, 0.015, 0.09, (True, True), True)]
    text = markdown({"lmpc": points}, command="make tradeoff", wall_s=60.0, workers=2)
    assert ("| LMPC | q_position 3, q_yaw 80, r_steer 3, low_speed_q_position 10, low_speed_r_steer 0.3 "
            "| 0.0150 / 0.0900 | yes |") in text
