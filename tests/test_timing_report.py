"""`make timing`'s report of contract revision 3 (issue 37), without a real-time run: the
run plan (both releases, repeats interleaved), the run-to-run spread, the goal lines with
their verdicts, the release in every table and the rendered report."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from studies.timing.goals import (GOAL_C_TASK_P99_MS, GOAL_LATENCY_P99_MS, GOAL_TASK_P99_MS,
                                  goal_lines, spread, spread_table)
from studies.timing.plan import (RUN_OVERHEAD_S, estimated_seconds, parse_releases,
                                 plan_runs)
from studies.timing.report import FIGURES, RunFigures, percentile_table, summary_table, watchdog_releases


def _run(condition: str = "idle", controller: str = "eso-dkmpc", release: str = "sample",
         repeat: int = 1, task: float = 1.0, latency: float = 1.5, age: float = 0.1,
         overruns: int = 0, seconds: float = 45.0, modes: dict[str, int] | None = None) -> RunFigures:
    """A run's figures with the p99 (ms) of task time, RX-to-TX latency and input age given;
    the law running on all 1760 cycles unless ``modes`` says otherwise; the other figures 0."""
    p99 = {"task_time": task, "rx_to_tx_latency": latency, "input_age": age}
    values = {f.name: 0 for f in dataclasses.fields(RunFigures)}
    values.update(condition=condition, controller=controller, release=release, repeat=repeat,
                  seconds=seconds, overruns=overruns, cycles=1760,
                  modes=modes or {"ACTIVE": 1760},
                  command_gap_max_ms=30.0, steal_share=0.0, scheduling={},
                  stats={name: (p99.get(name, 0.0) / 2, p99.get(name, 0.0), p99.get(name, 0.0),
                                p99.get(name, 0.0), 1760) for name, _ in FIGURES},
                  samples_ms={name: np.full(10, max(p99.get(name, 0.0), 0.02))
                              for name, _ in FIGURES})
    return RunFigures(**values)


# ------------------------------------------------------------------ plan
def test_the_default_plan_repeats_eso_dkmpc_under_both_releases_and_the_others_once_on_the_clock():
    plan = plan_runs(["eso-dkmpc", "dkmpc", "lmpc", "nmpc"], ["eso-dkmpc", "dkmpc", "lmpc"],
                     ["clock", "sample"], 3, 45.0, 30.0)
    rows = [(s.label, s.release, s.repeat, s.seconds) for s in plan]
    print(rows)
    assert len(plan) == 17
    # interleaved: repeat 1 of every repeated row before repeat 2
    assert rows[:4] == [("eso-dkmpc", "clock", 1, 45.0), ("eso-dkmpc", "sample", 1, 45.0),
                        ("eso-dkmpc (C)", "clock", 1, 45.0), ("eso-dkmpc (C)", "sample", 1, 45.0)]
    assert [r[2] for r in rows[:12]] == [1] * 4 + [2] * 4 + [3] * 4
    assert rows[12:] == [("dkmpc", "clock", 1, 45.0), ("lmpc", "clock", 1, 45.0),
                         ("nmpc", "clock", 1, 30.0), ("dkmpc (C)", "clock", 1, 45.0),
                         ("lmpc (C)", "clock", 1, 45.0)]
    assert len({s.work_name("idle") for s in plan}) == 17   # one folder per run
    assert plan[7].work_name("stress") == "stress__eso-dkmpc_c__sample__r2"
    # 2 conditions x (16 x 45 s + 30 s) plus the start-up of each of the 34 runs
    assert estimated_seconds(plan, 2) == pytest.approx(2 * (16 * 45 + 30) + 34 * RUN_OVERHEAD_S)
    assert estimated_seconds(plan, 2) <= 30 * 60


def test_a_single_release_applies_to_every_row_and_nmpc_is_capped_by_seconds():
    plan = plan_runs(["eso-dkmpc", "nmpc"], [], ["sample"], 2, 20.0, 30.0)
    assert [(s.label, s.release, s.repeat, s.seconds) for s in plan] == [
        ("eso-dkmpc", "sample", 1, 20.0), ("eso-dkmpc", "sample", 2, 20.0),
        ("nmpc", "sample", 1, 20.0)]


@pytest.mark.parametrize("text, message", [
    ("clock,fast", r"unknown \['fast'\]"), ("", "empty list"), ("sample,sample", "twice")])
def test_bad_release_lists_are_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_releases(text)


def test_bad_repeats_and_run_lengths_are_named():
    with pytest.raises(ValueError, match="--repeats must be >= 1, got 0"):
        plan_runs(["eso-dkmpc"], [], ["clock"], 0, 45.0, 30.0)
    with pytest.raises(ValueError, match="run lengths must be > 0 s"):
        plan_runs(["eso-dkmpc"], [], ["clock"], 1, 0.0, 30.0)


def test_the_bench_cli_refuses_bad_options_before_any_run(capsys):
    from studies.timing.bench import main

    assert main(["--repeats", "0", "--out", "/nonexistent/x.md"]) == 1
    assert main(["--release", "clock,fast", "--out", "/nonexistent/x.md"]) == 1
    err = capsys.readouterr().err
    print(err)
    assert "error: --repeats must be >= 1, got 0" in err and "error: --release: unknown" in err


# ------------------------------------------------------------------ spread
def test_spread_is_min_median_max_and_leaves_runs_without_a_figure_out():
    figure = spread([2.0, 1.0, 4.0])
    assert (figure.low, figure.median, figure.high, figure.runs) == (1.0, 2.0, 4.0, 3)
    assert figure.describe() == "1.000 / 2.000 / 4.000"
    assert spread([1.5]).describe() == "1.500"          # one run: one figure
    partial = spread([1.0, math.nan, 3.0])
    assert (partial.median, partial.runs) == (2.0, 3)
    assert math.isnan(spread([math.nan]).median) and spread([math.nan]).describe() == "-"
    with pytest.raises(ValueError, match="at least one run"):
        spread([])


def test_spread_table_gives_each_repeated_row_its_p99_spread_and_leaves_single_runs_out():
    runs = [_run(repeat=k, latency=lat, task=task, age=age, overruns=o)
            for k, (lat, task, age, o) in enumerate([(1.2, 1.0, 0.05, 0), (1.8, 1.4, 0.2, 1),
                                                      (1.5, 1.1, 0.1, 0)], start=1)]
    runs += [_run(release="clock", latency=7.0), _run(controller="lmpc", release="clock")]
    lines = spread_table(runs)
    print("\n".join(lines))
    assert len(lines) == 2 + 1                           # the single runs are left out
    assert lines[2] == ("| idle | eso-dkmpc | sample | 3 | 1.200 / 1.500 / 1.800 "
                        "| 1.000 / 1.100 / 1.400 | 0.050 / 0.100 / 0.200 | 0, 1, 0 |")
    assert len(spread_table(runs, min_runs=1)) == 2 + 3


# ------------------------------------------------------------------ goal lines
def test_a_run_whose_law_did_not_run_meets_no_goal():
    """A controller that fell into SAFE_STOP at the start has no overruns and a short task:
    its row must not pass for a met goal (the NMPC rows of make timing once did)."""
    stopped = {"ACTIVE": 4, "SAFE_STOP": 1756}
    lines = goal_lines([_run(controller="nmpc", release="clock", modes=stopped),
                        _run(controller="lmpc", release="clock", modes={"ACTIVE": 1700, "DEGRADED": 60}),
                        _run(release="clock", modes=stopped)])
    print("\n".join(lines))
    nmpc = next(line for line in lines if line.startswith("- idle, clock release: nmpc overruns"))
    assert "NOT met (the law ran on 4 of 1760 cycles of run 1 (SAFE_STOP 1756))" in nmpc
    lmpc = next(line for line in lines if line.startswith("- idle, clock release: lmpc overruns"))
    assert ": met;" in lmpc                    # DEGRADED cycles ran the law too
    task = next(line for line in lines if "ESO-DKMPC (Python ECU) task time" in line)
    assert "NOT met (the law ran on 4 of 1760 cycles" in task


def test_goal_lines_judge_every_run_and_give_the_spread():
    runs = [_run(repeat=1, latency=1.0), _run(repeat=2, latency=3.5), _run(repeat=3, latency=2.0)]
    lines = goal_lines(runs)
    print("\n".join(lines))
    latency = next(line for line in lines if "RX-to-TX" in line)
    assert latency == (f"- idle, sample release: ESO-DKMPC (Python ECU) RX-to-TX latency p99 <= "
                       f"{GOAL_LATENCY_P99_MS:g} ms: NOT met (2 of 3 runs within), "
                       "p99 min / median / max 1.000 / 2.000 / 3.500 ms")
    task = next(line for line in lines if "task time" in line)
    assert task.endswith(f"<= {GOAL_TASK_P99_MS:g} ms: met (3 of 3 runs within), "
                         "p99 min / median / max 1.000 / 1.000 / 1.000 ms")


def test_goal_lines_cover_both_ecus_both_releases_and_both_loads():
    runs = [_run(condition, controller, release, task=task, latency=latency, overruns=overruns)
            for condition in ("idle", "stress") for release in ("clock", "sample")
            for controller, task, latency, overruns in (
                ("eso-dkmpc", 1.5, 8.0 if release == "clock" else 1.5, 0),
                ("eso-dkmpc (C)", 0.3 if condition == "stress" else 0.2,
                 7.0 if release == "clock" else 0.2, 0))]
    runs.append(_run("idle", "nmpc", "clock", overruns=4, seconds=30.0))
    lines = goal_lines(runs)
    print("\n".join(lines))
    for condition in ("idle", "stress"):
        for release in ("clock", "sample"):
            where = f"- {condition}, {release} release: "
            for ecu in ("Python", "C"):
                latency = next(line for line in lines
                               if line.startswith(f"{where}ESO-DKMPC ({ecu} ECU) RX-to-TX"))
                assert (": met" in latency) == (release == "sample"), latency
            c_task = next(line for line in lines
                          if line.startswith(f"{where}ESO-DKMPC (C ECU) task time"))
            assert f"<= {GOAL_C_TASK_P99_MS:g} ms" in c_task
            assert (": met" in c_task) == (condition == "idle"), c_task
            python_task = [line for line in lines
                           if line.startswith(f"{where}ESO-DKMPC (Python ECU) task time")]
            assert len(python_task) == (1 if condition == "idle" else 0)  # the goal is idle's
            for row in ("eso-dkmpc", "eso-dkmpc (C)"):
                assert f"{where}{row} overruns at 25 ms (goal 0): 0 in 1 run of 45 s: met; " \
                       "commands lost: 0" in lines
    assert "- idle, clock release: nmpc overruns at 25 ms (goal 0): 4 in 1 run of 30 s: " \
           "NOT met; commands lost: 0" in lines
    assert all(" met" in line for line in lines)          # every line has its verdict


def test_goal_lines_give_the_issue_9_ratio_where_lmpc_ran_under_the_same_release():
    runs = [_run(release="clock", task=1.5), _run(release="sample", task=1.5),
            _run(controller="lmpc", release="clock", task=1.0)]
    ratios = [line for line in goal_lines(runs) if "/ LMPC" in line]
    assert ratios == ["- idle, clock release: ESO-DKMPC / LMPC task time p99 (medians over the "
                      "runs) = 1.50 (<= 2): met"]


# ------------------------------------------------------------------ release labels
def test_every_table_names_the_release_and_the_run():
    runs = [_run(release="clock", repeat=1), _run(release="sample", repeat=2)]
    summary, percentiles = summary_table(runs), percentile_table(runs)
    assert summary[0].startswith("| load | controller | release | run | s |")
    assert summary[2].startswith("| idle | eso-dkmpc | clock | 1 | 45 |")
    assert summary[3].startswith("| idle | eso-dkmpc | sample | 2 | 45 |")
    assert percentiles[0].startswith("| load | controller | release | run | figure |")
    assert percentiles[-1].startswith("| idle | eso-dkmpc | sample | 2 | RX-to-TX latency |")


def test_histogram_lines_pool_repeats_and_name_the_release_only_when_there_are_two():
    import matplotlib.pyplot as plt

    from studies.timing.report import histogram_figure

    def legend(runs):
        figure = histogram_figure(runs, "idle")
        try:
            return [t.get_text() for t in figure.axes[-1].get_legend().get_texts()]
        finally:
            plt.close(figure)

    both = [_run(release="clock", repeat=k) for k in (1, 2)] + [_run(release="sample")]
    assert legend(both) == ["eso-dkmpc, clock release", "eso-dkmpc, sample release"]
    assert legend([_run(release="sample"), _run(controller="lmpc", release="sample")]) == \
        ["eso-dkmpc", "lmpc"]


# ------------------------------------------------------------------ the report
def test_the_report_states_run_lengths_releases_goals_and_spread(tmp_path):
    from studies.timing.bench import ReportContext, _report, grouped

    plan = plan_runs(["eso-dkmpc", "nmpc"], ["eso-dkmpc"], ["clock", "sample"], 2, 45.0, 30.0)
    # in run order (repeats interleaved); the report groups them
    runs = [_run(controller=s.label, release=s.release, repeat=s.repeat, seconds=s.seconds)
            for s in plan]
    context = ReportContext(argv=["--repeats", "2", "--out", "x y.md"], plan=plan,
                            started="2026-12-05 12:00 UTC", wall_s=600.0,
                            loads={"idle": "load average (1 min) 0.10 before, 0.20 after"},
                            stress_pinning=[], pngs=[tmp_path / "timing_idle.png"],
                            idle_states="held at 0 us", speed_reference_ms=3.25)
    text = "\n".join(_report(grouped(runs), context))
    print(text[:3000])
    assert "`python -m studies.timing.bench --repeats 2 --out 'x y.md'` (`make timing`)" in text
    assert ("- Run lengths: eso-dkmpc rows 45 s per run, 2 runs per ECU and release "
            "(clock, sample); nmpc: 30 s, one run (clock release). 9 runs in all, "
            "10.0 min of wall time (start-up included).") in text
    assert "- Speed reference: 3.25 ms before the first run" in text
    for heading in ("## Goals (issue 37)", "## Run-to-run spread", "## Summary\n",
                    "## Percentiles (ms)", "![timing_idle](timing_idle.png)"):
        assert heading in text
    summary = text.split("## Summary\n")[1].split("## Percentiles")[0]
    rows = [line.split(" | ")[1:4] for line in summary.splitlines() if line.startswith("| idle")]
    assert rows[:4] == [["eso-dkmpc", "clock", "1"], ["eso-dkmpc", "clock", "2"],
                        ["eso-dkmpc", "sample", "1"], ["eso-dkmpc", "sample", "2"]]
    assert "- idle, sample release: ESO-DKMPC (C ECU) RX-to-TX latency p99 <= 3 ms: met" in text


# ------------------------------------------------------------------ watchdog releases
def test_watchdog_releases_are_the_cycles_released_at_or_after_the_window_end():
    """A sample releases inside [N - 2.5, N + 7.5) ms; the watchdog at N + 7.5 ms or later."""
    jitter_ms = np.array([0.0, 5.0, -2.4, 7.499, 7.5, 7.6, 32.5, np.nan])
    assert watchdog_releases(jitter_ms / 1e3) == 3


def test_the_summary_counts_watchdog_releases_for_the_sample_release_only():
    runs = [dataclasses.replace(_run(release="clock"), watchdog_releases=None),
            dataclasses.replace(_run(release="sample"), watchdog_releases=6)]
    summary = summary_table(runs)
    assert summary[0].endswith("| max abs e_Y (m) | watchdog releases |")
    assert summary[2].endswith("| - |") and summary[3].endswith("| 6 |")
