"""The live view of a run (`hil.live_view`, ``eso-hil run --plot``), headless (Agg).

A dlc_smoke run with the view fills its buffers and writes a four-panel image; the run's
frames, plant trace and tracking equal those of the run without the view to the last bit;
redraws keep to their wall-clock interval; ``--plot``'s errors are one line.
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # headless, whatever the machine running the tests has

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from can_defs.frames import FrameId  # noqa: E402
from hil.__main__ import main  # noqa: E402
from hil.live_view import (PANEL_TITLES, LiveSampler, LiveView, run_with_live_view,  # noqa: E402
                           LiveFigure, display_available)
from hil.metrics import control_instant_errors, reference_path  # noqa: E402
from hil.rig import Rig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402
from hil.session import default_options, run_hil  # noqa: E402

#: CTRL_DIAG's fields measured on the wall clock: they differ between any two runs.
WALL_CLOCK_COLUMNS = ("solve_time_us", "cycle_time_us")


@pytest.fixture(scope="module")
def smoke():
    """dlc_smoke (4 s) with LMPC, with and without the view (the view redrawing during the
    run as in a window, at its real wall-clock rate)."""
    scenario = load_scenario("dlc_smoke")
    plain = run_hil(scenario, default_options("lmpc"))
    rig = Rig(scenario, default_options("lmpc"))
    path = reference_path(scenario)
    figure = LiveFigure(path, "dlc_smoke - lmpc")
    view = LiveView(LiveSampler(rig.plant, rig.monitor, path), figure, interactive=True)
    with rig:
        rig.run(on_tick=view.on_tick)
    yield scenario, plain, rig.result(), view
    view.close()


def test_headless_backend_has_no_display():
    assert not display_available()


def test_the_view_fills_its_buffers_and_writes_four_panels(smoke, tmp_path):
    scenario, _, viewed, view = smoke
    buffers = view.buffers
    assert view.sampler.samples == len(buffers.time) == 160  # 4 s, one per control cycle
    assert len(buffers.cycle_time) == len(buffers.steer_cmd) == viewed.summary()["control_cycles"]
    assert len(buffers.task_us) >= 160 and max(buffers.ctrl_mode) == 2  # ACTIVE
    assert view.redraws >= 1
    # e_Y in the view is the metrics' e_Y at the control instants, to the last bit
    times, errors = control_instant_errors(viewed.plant_trace, reference_path(scenario))
    # (the view samples t = 25 ms .. 4 s; the plant trace ends at its last tick, 3.995 s)
    shown = view.buffers.array("lateral_error")[:-1]
    assert np.array_equal(view.buffers.array("time")[:-1], times[1:])
    print(f"max |e_Y view - e_Y metrics| = {np.max(np.abs(shown - errors.lateral_error[1:]))}")
    assert np.array_equal(shown, errors.lateral_error[1:])

    out = view.save(tmp_path / "view.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert matplotlib.image.imread(out).shape[:2] == (800, 1200)
    panels = view.figure.panels
    assert tuple(axis.get_title() for axis in panels) == PANEL_TITLES
    for axis in panels:
        assert all(len(line.get_xdata()) > 0 for line in axis.get_lines()
                   if not line.get_label().startswith("_"))


def test_the_view_changes_nothing_in_the_run(smoke):
    _, plain, viewed, _ = smoke

    def commands(result):  # STEER_TORQUE_CMD, raw; CTRL_DIAG holds wall-clock task times
        return [frame for frame in result.extra["ecu_frames_raw"] if frame[1] == FrameId.STEER_TORQUE_CMD]

    assert len(commands(plain)) == 160 and commands(viewed) == commands(plain)
    for name, column in plain.plant_trace.items():
        difference = np.nanmax(np.abs(viewed.plant_trace[name] - column)) if column.size else 0.0
        print(f"plant {name}: max |with view - without| = {difference}")
        assert np.array_equal(viewed.plant_trace[name], column, equal_nan=True)
    for name, column in plain.ecu_trace.items():
        if name in WALL_CLOCK_COLUMNS:
            continue
        assert np.array_equal(viewed.ecu_trace[name], column), name
    assert viewed.tracking == plain.tracking
    assert viewed.summary()["tracking"] == plain.summary()["tracking"]


class _Sampler:
    buffers = None

    def __call__(self, tick_ms: int) -> bool:
        return True


class _Figure:
    def __init__(self, clock: list[float], cost_s: float) -> None:
        self.clock, self.cost_s, self.draws = clock, cost_s, 0
        self.starts: list[float] = []

    def update(self, buffers: object) -> None:
        pass

    def draw(self, interactive: bool) -> None:
        self.starts.append(self.clock[0])
        self.clock[0] += self.cost_s
        self.draws += 1

    def is_open(self) -> bool:
        return True


@pytest.mark.parametrize("cost_s, interval_s, expected_draws", [(0.01, 0.1, 12), (0.05, 0.25, 5)])
def test_redraws_keep_to_the_interval_and_share_of_wall_clock(cost_s, interval_s, expected_draws):
    """1000 ticks of 1 ms of wall clock each, plus the redraws' cost: a redraw every 100 ms
    when cheap, every 5 x its cost (draw_share 0.2) when not."""
    clock = [0.0]
    figure = _Figure(clock, cost_s)
    view = LiveView(_Sampler(), figure, interactive=True,  # type: ignore[arg-type]
                    min_interval_s=0.1, draw_share=0.2, clock=lambda: clock[0])
    for tick in range(1000):
        view.on_tick(tick * 5)
        clock[0] += 0.001
    assert figure.draws == expected_draws
    assert np.min(np.diff(figure.starts)) == pytest.approx(interval_s)
    assert view.draw_time_s <= 0.2 * clock[0] + cost_s
    assert view.draw_time_s == pytest.approx(expected_draws * cost_s)


def test_without_display_the_view_only_samples(smoke):
    scenario, plain, _, _ = smoke
    result, view = run_with_live_view(scenario, default_options("lmpc"), interactive=False)
    try:
        assert view.redraws == 0 and view.sampler.samples == 160
        assert np.array_equal(result.plant_trace["steer_cmd"], plain.plant_trace["steer_cmd"])
    finally:
        view.close()


def _run(tmp_path, *extra: str) -> list[str]:
    return ["run", "--scenario", "dlc_smoke", "--controller", "lmpc", *extra]


def test_cli_plot_file_is_written_and_stdout_stays_json(tmp_path, capsys):
    import json

    out = tmp_path / "live.png"
    assert main(_run(tmp_path, "--plot", str(out))) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["active_cycles"] == 159
    assert f"wrote {out}" in captured.err
    assert matplotlib.image.imread(out).shape[:2] == (800, 1200)
    # an existing image needs --replace
    assert main(_run(tmp_path, "--plot", str(out))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: --plot {out}: file exists")


def test_cli_plot_without_file_and_display_notes_and_runs(tmp_path, capsys):
    assert main(_run(tmp_path, "--plot")) == 0
    captured = capsys.readouterr()
    assert "note: --plot: no display here" in captured.err
    assert '"tracking"' in captured.out


@pytest.mark.parametrize("name, message", [
    ("view.txt", "'.txt' is not an image format (one of "),
    ("view", "has no suffix (one of "),
    ("missing/view.png", "folder"),
])
def test_cli_plot_errors_are_one_line_before_the_run(tmp_path, capsys, name, message):
    target = tmp_path / name
    assert main(_run(tmp_path, "--plot", str(target))) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and captured.err.startswith(f"error: --plot {target}")
    assert message in captured.err
    assert not target.exists()


def test_cli_plot_onto_an_input_is_refused(tmp_path, capsys):
    scenario = load_scenario("dlc_smoke")
    before = scenario.path_file.read_bytes()
    assert main(_run(tmp_path, "--plot", str(scenario.path_file))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is one of the inputs" in err
    assert scenario.path_file.read_bytes() == before
