"""Every figure of the log tools and the timing study says what it shows (issue 19): a
title, axes with units, a legend entry for every line (the timing plots' dashed 25 ms
line included)."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from controller.reference import ReferencePath  # noqa: E402
from hil.decode_log import decode_log, overview_figure  # noqa: E402
from hil.logio import read_log  # noqa: E402

LOGS = Path(__file__).parent / "data" / "logs"
DLC = Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"
UNIT = re.compile(r"\[[^\]]+\]")


def _check_panels(figure, panels) -> list[str]:
    """Problems of the drawn panels: no title, an axis label without a [unit], a line
    without a legend entry."""
    problems = []
    for axis in panels:
        name = axis.get_title() or "(untitled)"
        if not axis.get_title():
            problems.append("a panel has no title")
        for label in (axis.get_xlabel(), axis.get_ylabel()):
            if not UNIT.search(label):
                problems.append(f"{name}: axis label {label!r} has no [unit]")
        legend = axis.get_legend()
        legend_labels = {t.get_text() for t in legend.get_texts()} if legend else set()
        for line in axis.get_lines() + [p for p in axis.patches if p.get_label()[:1] != "_"]:
            if line.get_label().startswith("_"):
                continue
            if line.get_label() not in legend_labels:
                problems.append(f"{name}: line {line.get_label()!r} not in a legend")
    if not figure._suptitle or not figure._suptitle.get_text():
        problems.append("the figure has no title")
    return problems


def test_the_log_overview_is_titled_with_units_and_legends() -> None:
    decoded = decode_log(read_log(LOGS / "lockstep_lmpc.log"))
    figure = overview_figure(decoded, ReferencePath.from_csv(DLC), "CAN log lockstep_lmpc.log")
    try:
        problems = _check_panels(figure, figure.axes)
        print([a.get_title() for a in figure.axes])
        assert problems == []
        assert len(figure.axes) == 5
    finally:
        plt.close(figure)


def test_the_timing_histograms_explain_the_dashed_line() -> None:
    from studies.timing.report import FIGURES, PERIOD_MS, RunFigures, histogram_figure

    rng = np.random.default_rng(0)
    runs = []
    for controller, scale_ms in (("lmpc", 2.0), ("nmpc", 20.0)):
        values = {f.name: 0 for f in dataclasses.fields(RunFigures)}
        values.update(condition="idle", controller=controller, modes={}, stats={},
                      scheduling={},
                      samples_ms={name: rng.gamma(4.0, scale_ms / 4.0, 300) for name, _ in FIGURES})
        runs.append(RunFigures(**values))
    figure = histogram_figure(runs, "idle")
    try:
        drawn, legend_panel = figure.axes[:len(FIGURES)], figure.axes[-1]
        problems = []
        for axis in drawn:
            problems += [p for p in _check_panels(figure, [axis]) if "not in a legend" not in p]
        legend = {t.get_text() for t in legend_panel.get_legend().get_texts()}
        print(legend)
        assert problems == []
        assert {"lmpc", "nmpc", f"control period {PERIOD_MS:g} ms (deadline)"} == legend
        dashed = [line for axis in drawn for line in axis.get_lines() if line.get_linestyle() == "--"]
        assert dashed and all(line.get_label() in legend for line in dashed)
    finally:
        plt.close(figure)


def test_a_foreign_dbc_figure_names_every_signal_with_its_unit(tmp_path) -> None:
    import can

    from hil.decode_log import decode_with_dbc, load_display_dbc, signals_figure

    dbc = tmp_path / "x.dbc"
    dbc.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\nBO_ 256 M: 8 A\n'
                   ' SG_ S : 0|16@1+ (0.1,0) [0|6553.5] "bar" A\n')
    log = tmp_path / "x.log"
    with can.Logger(log) as writer:
        for i in range(5):
            writer.on_message_received(can.Message(timestamp=i * 0.1, arbitration_id=0x100,
                                                   is_extended_id=False,
                                                   data=(i * 10).to_bytes(2, "little") + bytes(6)))
    figure = signals_figure(decode_with_dbc(read_log(log), load_display_dbc(dbc)), "x.log")
    try:
        assert _check_panels(figure, figure.axes) == []
        assert figure.axes[0].get_legend().get_texts()[0].get_text() == "S [bar]"
    finally:
        plt.close(figure)
