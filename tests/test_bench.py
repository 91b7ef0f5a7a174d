"""`make bench` (studies/bench.py) on a few recorded samples: the table has a row for every
controller of the registry (read at run time), the C core's rows (issue 18: "NAME (C)", when
libecu.so is built) and the ECU overhead, every figure finite and positive. Speeds are not
asserted: they depend on the machine and its load."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from controller import registry
from firmware_sim.native import DEFAULT_LIBRARY, NATIVE_CONTROLLERS
from studies import bench, step_timing

STEPS = 6


def _rows(markdown: str, table: int = 0) -> dict[str, list[str]]:
    """First cell -> the other cells, for every body row of the file's ``table``-th table."""
    rows: dict[str, list[str]] = {}
    seen, inside = -1, False
    for line in markdown.splitlines():
        if line.startswith("|") != inside:
            inside = not inside
            seen += inside
        if inside and seen == table and line.startswith("| ") and not line.startswith("| controller"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_bench_times_every_registered_controller_on_the_same_samples(tmp_path: Path) -> None:
    out, out_json = tmp_path / "bench.md", tmp_path / "bench.json"
    assert bench.main(["--steps", str(STEPS), "--out", str(out), "--json", str(out_json)]) == 0
    text = out.read_text()
    print(text)
    rows = _rows(text)
    c_rows = {f"{name} (C)" for name in NATIVE_CONTROLLERS if name in registry.CONTROLLERS}
    built = DEFAULT_LIBRARY.is_file()
    # NMPC a second time as the real-time ECU runs it (its NLP compiled)
    assert set(rows) == (set(registry.CONTROLLERS) | {bench.ECU_OVERHEAD_ROW, bench.NMPC_COMPILED_ROW}
                         | (c_rows if built else set()))
    assert ("is not built (make firmware)" in text) != built
    assert "Load average (1 / 5 / 15 min)" in text and "OPENBLAS_NUM_THREADS=1" in text
    assert "- Speed reference: " in text
    assert f"{STEPS} samples of `{step_timing.RECORDING_SCENARIO}`" in text

    document = json.loads(out_json.read_text())
    assert 0 < document["speed_reference_ms"] < 1000
    assert list(document["controllers"]) == [*registry.CONTROLLERS, bench.NMPC_COMPILED_ROW]
    assert document["not_built"] == {}
    for name, timing in document["controllers"].items():
        for kind in ("wall", "cpu"):
            figures = timing[kind]
            assert figures["n"] == STEPS - 1, (name, kind)  # the set-up step left out
            assert all(math.isfinite(figures[key]) and figures[key] > 0
                       for key in ("p50_ms", "p99_ms", "max_ms")), (name, kind, figures)
            assert figures["p50_ms"] <= figures["p99_ms"] <= figures["max_ms"]
        if name in registry.GEOMETRIC_NAMES:  # no solver: nothing to share
            assert timing["solver_share"] == 0.0 and timing["solver"]["p50_ms"] == 0.0, name
        else:
            assert 0 < timing["solver_share"] <= 1.0, name
            assert timing["solver"]["p50_ms"] > 0, name
    assert set(document["c_core"]["rows"]) == (c_rows if built else set())
    for name, timing in document["c_core"]["rows"].items():  # ecu_step's own time, the set-up step left out
        assert timing["wall"]["n"] == STEPS - 1 and 0 < timing["wall"]["p50_ms"] <= timing["wall"]["max_ms"], name
        assert 0 < timing["solver_share"] <= 1.0 and timing["cpu"]["p50_ms"] > 0, name
        assert float(rows[name][6]) > 0, name  # its ratio to LMPC's (Python) step
    lmpc = rows[bench.BASELINE]
    assert lmpc[6:8] == ["1.00", "1.00"]  # p50 / p99 ratios of the baseline to itself
    for name in registry.CONTROLLERS:
        assert float(rows[name][6]) > 0 and float(rows[name][7]) > 0, name
    overhead = document["ecu_overhead"]
    assert overhead["final_mode"] == "ACTIVE"
    assert overhead["control_task"]["n"] == STEPS - 1 and overhead["control_task"]["p50_ms"] > 0
    if bench.GOAL_CONTROLLER in rows:
        assert f"{bench.GOAL_CONTROLLER} step within {bench.GOAL_RATIO:g}x" in text
    assert bench.goal_line({}) is None
    # the headline controller at the control cadence, Python and (built) C, STEPS - 1 steps a pass
    cadence = _rows(text, table=1)
    headline = {bench.GOAL_CONTROLLER} | ({f"{bench.GOAL_CONTROLLER} (C)"} if built else set())
    assert set(cadence) == headline
    assert [row["name"] for row in document["cadence"]["rows"]] == sorted(headline, key=len)
    for row in document["cadence"]["rows"]:
        assert row["steps"] == STEPS - 1
        assert 0 < row["back_to_back_p50_ms"] <= row["back_to_back_p99_ms"], row
        assert 0 < row["at_cadence_p50_ms"] <= row["at_cadence_p99_ms"], row
        assert row["p50_ratio"] == pytest.approx(row["at_cadence_p50_ms"] / row["back_to_back_p50_ms"])


def test_bench_reads_the_registry_at_run_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A controller added to the registry joins the table; one that cannot be built is named
    with its error, the others are still timed, and the exit status is 1."""
    table = {name: registry.CONTROLLERS[name] for name in ("lmpc", "dkmpc")}
    monkeypatch.setattr(registry, "CONTROLLERS", {**table, "broken": ("controller.no_such_module", "X")})
    out = tmp_path / "bench.md"
    assert bench.main(["--steps", "3", "--no-ecu", "--no-c", "--out", str(out)]) == 1
    text = out.read_text()
    assert set(_rows(text)) == {"lmpc", "dkmpc"}
    assert "broken: not built (ModuleNotFoundError" in text


def test_bench_says_when_the_c_core_is_not_built(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without libecu.so the table has no C rows and says why (make firmware); with --no-c
    it has none and says nothing."""
    import firmware_sim.native

    monkeypatch.setattr(firmware_sim.native, "DEFAULT_LIBRARY", tmp_path / "libecu.so")
    monkeypatch.delenv("ECU_LIB", raising=False)
    out = tmp_path / "bench.md"
    assert bench.main(["--steps", "3", "--no-ecu", "--controllers", "lmpc", "--out", str(out)]) == 0
    text = out.read_text()
    assert set(_rows(text)) == {"lmpc"} and "C core: not timed, libecu.so is not built (make firmware)." in text
    assert bench.main(["--steps", "3", "--no-ecu", "--no-c", "--controllers", "lmpc", "--out", str(out)]) == 0
    assert "C core" not in out.read_text()
    # the cadence's C row says the same, and --no-c leaves it out without a word
    assert bench.main(["--steps", "3", "--no-ecu", "--controllers", "eso-dkmpc", "--out", str(out)]) == 0
    text = out.read_text()
    assert set(_rows(text, table=1)) == {"eso-dkmpc"}
    assert "C core: not timed at the cadence, libecu.so is not built (make firmware)." in text
    assert bench.main(["--steps", "3", "--no-ecu", "--no-c", "--controllers", "eso-dkmpc", "--out", str(out)]) == 0
    assert "C core" not in out.read_text() and set(_rows(out.read_text(), table=1)) == {"eso-dkmpc"}


def test_bench_refuses_unknown_controllers_and_too_few_steps(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["--controllers", "lmpc,nope", "--out", str(tmp_path / "x.md")]) == 2
    assert "nope" in capsys.readouterr().err
    assert bench.main(["--steps", "1", "--out", str(tmp_path / "x.md")]) == 1
    assert capsys.readouterr().err.startswith("error:")
    assert not (tmp_path / "x.md").exists()


def test_profile_prints_and_writes_no_file(tmp_path, capsys):
    out = tmp_path / "bench.md"
    assert bench.main(["--steps", "3", "--no-ecu", "--no-c", "--controllers", "lmpc",
                       "--profile", "lmpc", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "cProfile of lmpc `step()` x 2" in printed and "| lmpc |" in printed
    assert not out.exists() and "wrote" not in printed
