"""What a campaign writes: ``cells.csv`` (one row per cell), ``summary.md`` (pivot tables)
and heat maps of e_Y RMSE (``heatmap_*.png``).

The tables' columns are a controller on one ECU (:func:`column_label`): "ESO-DKMPC" on the
Python ECU, "ESO-DKMPC (C)" on the C ECU executable, side by side; a grid with C cells
also gets a table of each C cell against its Python twin (:func:`c_against_python`)."""
from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from studies.campaign.grid import AXES, DEFAULT_ECU, DEFAULT_TUNING, HIL_RUNNER, NO_CASE, Grid

#: Columns of cells.csv, in order (the axes as the issue names them, then the results). The
#: runner and the tuning override are axes too: without them two rows of a grid that differ
#: only there (a tuning axis' settings of one controller) could not be told apart.
CSV_FIELDS = ("controller", "ecu", "scenario", "mu", "speed", "mass", "lag", "fault", "disturbance",
              "model", "seed", "runner", "tuning",
              "e_y_rmse", "e_y_max", "heading_rmse", "completed", "end_reason",
              "step_p50_us", "step_p99_us", "overruns", "wall_s", "error", "key")
#: cells.csv column -> Cell field.
_AXIS_COLUMN = {"mass": "mass_offset_kg", "lag": "lag_factor"}
#: Axes the pivot tables and heat maps split by (controller is always the columns).
PIVOT_AXES = ("scenario", "mu", "speed", "mass_offset_kg", "lag_factor", "fault", "disturbance",
              "model", "seed", "runner", "tuning")
_TITLES = {"mass_offset_kg": "mass offset (kg)", "lag_factor": "steering lag (x time constant)",
           "mu": "mu", "speed": "speed (km/h)", "scenario": "scenario", "fault": "fault",
           "disturbance": "disturbance", "model": "model", "seed": "seed", "runner": "runner",
           "tuning": "tuning override"}


def _text(value: Any, digits: int = 6) -> str:
    if isinstance(value, float):
        if not math.isfinite(value):
            return ""
        return f"{value:.{digits}f}" if digits else f"{value:g}"
    return "" if value is None else str(value)


def csv_row(row: dict[str, Any]) -> dict[str, str]:
    """A result row as the text of :data:`CSV_FIELDS` (a ``fault_case`` cell's case in the
    ``fault`` column: it has no other fault)."""
    out = {}
    for name in CSV_FIELDS:
        value = row.get(_AXIS_COLUMN.get(name, name), "")
        if name == "fault" and row.get("case", NO_CASE) != NO_CASE:
            value = row["case"]
        if name in ("e_y_rmse", "e_y_max", "heading_rmse"):
            out[name] = _text(_float(value))
        elif name in ("step_p50_us", "step_p99_us", "wall_s"):
            out[name] = _text(_float(value), 1 if name == "wall_s" else 0)
        elif name in ("mu", "speed", "mass", "lag") and isinstance(value, float):
            out[name] = f"{value:g}"
        else:
            out[name] = _text(value).replace("\n", " ")
    return out


def _float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


class CsvAppender:
    """``cells.csv`` written row by row as cells finish (rewritten in grid order at the end)."""

    def __init__(self, path: Path, rows: Sequence[dict[str, Any]] = ()) -> None:
        self.path = path
        write_cells_csv(path, rows)

    def __call__(self, row: dict[str, Any]) -> None:
        with self.path.open("a", newline="", encoding="utf-8") as handle:
            csv.DictWriter(handle, CSV_FIELDS).writerow(csv_row(row))


#: Every row of the run with all its fields, for a grid whose cells are not cached (the
#: ``fault_case`` runner's: ``studies.fault_report`` renders from it).
ROWS_JSON = "rows.json"


def write_rows_json(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """``rows.json``: the rows in grid order, every field (NaN as JSON's NaN)."""
    import json

    path.write_text(json.dumps(list(rows), indent=1, allow_nan=True) + "\n", encoding="utf-8")
    return path


def read_rows_json(path: Path) -> list[dict[str, Any]]:
    """The rows :func:`write_rows_json` wrote."""
    import json

    return json.loads(path.read_text(encoding="utf-8"))


def write_cells_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            writer.writerow(csv_row(row))
    return path


def column_label(controller: str, ecu: str = DEFAULT_ECU) -> str:
    """A controller's column in the tables: its display name, "NAME (C)" on the C ECU (as
    the "NAME (C)" rows of make bench and make timing)."""
    from studies.report import display_name

    return f"{display_name(controller)} (C)" if ecu == "c" else display_name(controller)


def _column(row: dict[str, Any]) -> str:
    return column_label(row["controller"], row.get("ecu", DEFAULT_ECU))


def grid_columns(grid: Grid) -> list[str]:
    """The tables' columns in grid order: each controller, its C ECU column beside it."""
    return list(dict.fromkeys(column_label(c.controller, c.ecu) for c in grid.cells))


def _sort_key(value: Any) -> tuple:
    return (0, value, "") if isinstance(value, (int, float)) else (1, 0.0, str(value))


def pivot(rows: Sequence[dict[str, Any]], axis: str, columns: Sequence[str],
          statistic: Callable[[list[dict[str, Any]]], str]) -> list[str]:
    """A Markdown table: one row per value of ``axis``, one column per controller and ECU
    (:func:`column_label`)."""
    groups: dict[tuple[Any, str], list[dict[str, Any]]] = defaultdict(list)
    for row in rows:
        groups[(row[axis], _column(row))].append(row)
    values = sorted({row[axis] for row in rows}, key=_sort_key)
    lines = [f"| {_TITLES[axis]} | " + " | ".join(columns) + " |",
             "|---|" + "---|" * len(columns)]
    for value in values:
        cells = [statistic(groups.get((value, c), [])) for c in columns]
        lines.append(f"| {_text(value, 0)} | " + " | ".join(cells) + " |")
    return lines


def _mean_rmse(rows: list[dict[str, Any]]) -> str:
    done = [_float(r.get("e_y_rmse")) for r in rows if r.get("completed")]
    if not rows:
        return "-"
    mean = sum(done) / len(done) if done else math.nan
    text = f"{mean * 100:.1f}" if done else "-"
    return text if len(done) == len(rows) else f"{text} ({len(done)}/{len(rows)})"


def _median(rows: Sequence[dict[str, Any]], field: str) -> float | None:
    """The (upper) median of ``field`` over the rows where it is a finite number."""
    values = sorted(v for v in (_float(r.get(field)) for r in rows) if math.isfinite(v))
    return values[len(values) // 2] if values else None


def _completed(rows: list[dict[str, Any]]) -> str:
    return f"{sum(1 for r in rows if r.get('completed'))}/{len(rows)}" if rows else "-"


def summary_markdown(grid: Grid, rows: Sequence[dict[str, Any]], *, command: str, wall_s: float,
                     executor: str, computed: int, cached: int, machine: str,
                     interrupted: bool = False) -> str:
    """``summary.md``: the run's facts, per-controller totals and one pivot per axis."""
    columns = grid_columns(grid)
    lines = [f"# Campaign `{grid.name}`", "", f"`{command}`", ""]
    if grid.description:
        lines += [grid.description, ""]
    lines += [
        f"- Grid: `{_shown(grid.source)}`, "
        f"{len(grid.cells)} cells ({grid.excluded} excluded, {grid.not_applicable} not applicable: "
        "the model axis on a controller without a Koopman model"
        + "".join(f"; {n} C cells left out: {why}" for why, n in grid.c_left_out.items())
        + (f"; {grid.case_left_out} left out: a controller the fault case does not run"
           if grid.case_left_out else "") + ").",
        f"- This run: {computed} cells computed, {cached} from the cache, {len(rows)} of "
        f"{len(grid.cells)} finished{' (interrupted)' if interrupted else ''}; wall time "
        f"{wall_s:.0f} s on {executor}.",
        f"- Machine: {machine}.",
        *runner_lines(grid),
        "",
        "## Per controller", "",
        "| controller | completed | e_Y RMSE mean (cm) | e_Y max worst (cm) | heading RMSE mean (mrad) "
        "| step p50 / p99 median (us) | errors |",
        "|---|---|---|---|---|---|---|",
    ]
    for column in columns:
        mine = [r for r in rows if _column(r) == column]
        done = [r for r in mine if r.get("completed")]
        e_y = [_float(r["e_y_rmse"]) for r in done]
        e_max = [_float(r["e_y_max"]) for r in mine if math.isfinite(_float(r.get("e_y_max")))]
        head = [v for v in (_float(r.get("heading_rmse")) for r in done) if math.isfinite(v)]
        p50, p99 = _median(mine, "step_p50_us"), _median(mine, "step_p99_us")
        fields = [column, f"{len(done)}/{len(mine)}",
                  f"{sum(e_y) / len(e_y) * 100:.1f}" if e_y else "-",
                  f"{max(e_max) * 100:.1f}" if e_max else "-",
                  f"{sum(head) / len(head) * 1000:.1f}" if head else "-",
                  f"{p50:.0f} / {p99:.0f}" if p50 is not None else "-",
                  str(sum(1 for r in mine if r.get("error")))]
        lines.append("| " + " | ".join(fields) + " |")
    lines += c_against_python(rows)
    for axis in PIVOT_AXES:
        if len({getattr(c, axis) for c in grid.cells}) < 2:
            continue
        lines += ["", f"## e_Y RMSE (cm) by {_TITLES[axis]}", "",
                  "Mean over the other axes, completed cells only; (k/n) when only k of the n "
                  "cells completed.", ""]
        lines += pivot(rows, axis, columns, _mean_rmse)
        lines += ["", f"Completed cells by {_TITLES[axis]}:", ""]
        lines += pivot(rows, axis, columns, _completed)
    failures = [r for r in rows if not r.get("completed")]
    if failures:
        lines += ["", "## Cells not completed", "", "| controller | cell | end | error |", "|---|---|---|---|"]
        for r in failures[:60]:
            cell = ", ".join(f"{a}={_text(r[a], 0)}" for a in AXES[1:] if a in r and a != "ecu"
                             and not (a == "runner" and r[a] == HIL_RUNNER)
                             and not (a == "case" and r[a] == NO_CASE)
                             and not (a == "tuning" and r[a] == DEFAULT_TUNING))
            error = str(r.get("error", "")).replace("|", "/").replace("\n", " ")[:160]
            lines.append(f"| {_column(r)} | {cell} | {r.get('end_reason', '')} | {error} |")
        if len(failures) > 60:
            lines.append(f"| ... | {len(failures) - 60} more in cells.csv | | |")
    return "\n".join(lines) + "\n"


def runner_lines(grid: Grid) -> list[str]:
    """What one cell is, for each runner of the grid (summary.md's header)."""
    from studies.campaign.grid import CLOSED_LOOP_RUNNER, FAULT_CASE_RUNNER

    runners = {cell.runner for cell in grid.cells}
    lines = []
    if HIL_RUNNER in runners:
        lines.append("- Each cell: one lockstep run on the virtual bus (`hil.session.run_hil`, as "
                     "`python -m hil run --faults`): the Python ECU in-process; \"NAME (C)\" the C ECU "
                     "executable `build/firmware/ecu` as a process on the run's own loopback socketcand hub "
                     "(`--ecu c`). Completed: ran to the end with the ECU ACTIVE and |e_Y| <= 2 m throughout.")
    if FAULT_CASE_RUNNER in runners:
        lines.append(f"- Each {FAULT_CASE_RUNNER} cell: one case of the fault catalogue with one controller, "
                     "run and judged by `hil.fault_cases.runs.run_case` (as `make faults`). Completed: the "
                     "verdict passed; end reason: its outcome; e_Y max: max |e_Y|. The report is "
                     "`studies.fault_report`'s (results/faults.*).")
    if CLOSED_LOOP_RUNNER in runners:
        lines.append(f"- Each {CLOSED_LOOP_RUNNER} cell: one run of the controller and the plant without "
                     "CAN (`studies.closed_loop.run_closed_loop`, the runner of `make tables`). Completed: "
                     "ran to the end with |e_Y| <= 2 m throughout; step times are the controller's.")
    return lines


def c_against_python(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: each C cell against the Python cell of the same conditions (every
    axis but ``ecu`` equal), per controller; no lines without such pairs.

    Columns: pairs; pairs with the same outcome (completed or not, and the end reason);
    pairs both completed; over those, the largest and the mean of C's e_Y RMSE minus
    Python's (mm); the median of the cells' step p99 (us) on each ECU.
    """
    others = [a for a in AXES if a not in ("ecu", "runner")]  # a C cell is always over CAN
    python = {tuple(r[a] for a in others): r for r in rows if r.get("ecu", DEFAULT_ECU) == DEFAULT_ECU}
    pairs: dict[str, list[tuple[dict[str, Any], dict[str, Any]]]] = defaultdict(list)
    for row in rows:
        twin = python.get(tuple(row[a] for a in others))
        if row.get("ecu") == "c" and twin is not None:
            pairs[row["controller"]].append((twin, row))
    if not pairs:
        return []
    lines = ["", "## C ECU against the Python ECU", "",
             "Each C cell beside the Python cell of the same conditions. Same outcome: both "
             "completed, or both ended for the same reason. e_Y RMSE difference: C minus Python, "
             "over the pairs that both completed. Step p99: the median over the cells of each "
             "ECU's control task p99 (CTRL_DIAG, wall clock of a shared worker).", "",
             "| controller | pairs | same outcome | both completed | max abs e_Y RMSE difference (mm) "
             "| mean e_Y RMSE difference (mm) | step p99 median Python / C (us) |",
             "|---|---|---|---|---|---|---|"]
    for controller, matched in pairs.items():
        same = sum(1 for p, c in matched if (p.get("completed"), p.get("end_reason"))
                   == (c.get("completed"), c.get("end_reason")))
        both = [(p, c) for p, c in matched if p.get("completed") and c.get("completed")]
        deltas = [(_float(c["e_y_rmse"]) - _float(p["e_y_rmse"])) * 1000 for p, c in both]
        p99 = [_median(side, "step_p99_us") for side in ([p for p, _ in matched], [c for _, c in matched])]
        step = " / ".join("-" if v is None else f"{v:.0f}" for v in p99)
        lines.append(f"| {column_label(controller)} | {len(matched)} | {same} | {len(both)} | "
                     + (f"{max(abs(d) for d in deltas):.2f} | {sum(deltas) / len(deltas):+.2f}"
                        if deltas else "- | -") + f" | {step} |")
    return lines


def _shown(path: Path) -> str:
    from studies.campaign.grid import ROOT

    try:
        return path.relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def heatmap_axes(grid: Grid) -> tuple[str, str]:
    """The two axes of the heat maps: the two with the most values (mu and speed first)."""
    varying = [a for a in ("mu", "speed", "mass_offset_kg", "lag_factor", "scenario", "fault",
                           "disturbance", "model", "seed")
               if len({getattr(c, a) for c in grid.cells}) > 1]
    if len(varying) >= 2:
        ranked = sorted(varying, key=lambda a: -len({getattr(c, a) for c in grid.cells}))
        first, second = sorted(ranked[:2], key=varying.index)
        return first, second
    if varying:
        return varying[0], "controller"
    return "scenario", "controller"


def write_heatmaps(grid: Grid, rows: Sequence[dict[str, Any]], out_dir: Path) -> list[Path]:
    """``heatmap_e_y_rmse.png``: mean e_Y RMSE (cm) over the two :func:`heatmap_axes`, one
    panel per controller and ECU: the Python ECU's panels in the first row, the C ECU's
    below them, each under its controller (a controller the C ECU does not have leaves its
    place empty); or one panel with the controller columns (:func:`column_label`) as an
    axis. Cells that did not complete are grey with a cross."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    row_axis, col_axis = heatmap_axes(grid)
    controllers = list(dict.fromkeys(c.controller for c in grid.cells))
    ecus = list(dict.fromkeys(c.ecu for c in grid.cells))
    present = {(c.controller, c.ecu) for c in grid.cells}
    # panel layout (ECU row, controller column) -> (controller, ecu), or None: one panel
    layout = ({(0, 0): None} if col_axis == "controller" else
              {(i, j): (controller, ecu) for i, ecu in enumerate(ecus)
               for j, controller in enumerate(controllers) if (controller, ecu) in present})
    row_values = sorted({r[row_axis] for r in rows}, key=_sort_key)
    col_values = (grid_columns(grid) if col_axis == "controller"
                  else sorted({r[col_axis] for r in rows}, key=_sort_key))
    if not rows or not row_values or not col_values:
        return []
    grids = {}
    for place, panel in layout.items():
        values = np.full((len(row_values), len(col_values)), np.nan)
        for i, rv in enumerate(row_values):
            for j, cv in enumerate(col_values):
                group = [r for r in rows if r[row_axis] == rv and
                         (_column(r) == cv if col_axis == "controller" else r[col_axis] == cv)
                         and (panel is None or (r["controller"], r.get("ecu", DEFAULT_ECU)) == panel)]
                done = [_float(r["e_y_rmse"]) * 100 for r in group if r.get("completed")]
                if group and len(done) == len(group):
                    values[i, j] = float(np.mean(done))
        grids[place] = values
    finite = [v for g in grids.values() for v in g[np.isfinite(g)]]
    vmax = max(finite) if finite else 1.0
    n_rows = 1 + max(i for i, _ in layout)
    n_cols = 1 + max(j for _, j in layout)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.2 + 2.6 * n_cols, 0.4 + 3.4 * n_rows),
                             squeeze=False)
    fig.subplots_adjust(hspace=0.45, wspace=0.3)
    for (i, j), ax in np.ndenumerate(axes):
        if (i, j) not in layout:
            ax.axis("off")
            ax.text(0.5, 0.5, f"no {column_label(controllers[j], ecus[i])} cells", ha="center",
                    va="center", fontsize=8, transform=ax.transAxes)
            continue
        values, panel = grids[(i, j)], layout[(i, j)]
        image = ax.imshow(values, cmap="viridis", vmin=0.0, vmax=vmax, origin="lower", aspect="auto")
        for a in range(len(row_values)):
            for b in range(len(col_values)):
                text = "x" if not np.isfinite(values[a, b]) else f"{values[a, b]:.1f}"
                ax.text(b, a, text, ha="center", va="center", fontsize=7,
                        color="white" if not np.isfinite(values[a, b]) or values[a, b] < vmax / 2 else "black")
        ax.set_xticks(range(len(col_values)), [_text(v, 0) for v in col_values], fontsize=7,
                      rotation=30 if col_axis in ("controller", "scenario", "fault", "disturbance") else 0)
        ax.set_yticks(range(len(row_values)), [_text(v, 0) for v in row_values], fontsize=7)
        ax.set_xlabel(_TITLES.get(col_axis, col_axis), fontsize=8)
        if j == 0:  # the panels of a row share the rows' axis
            ax.set_ylabel(_TITLES.get(row_axis, row_axis), fontsize=8)
        ax.set_facecolor("0.85")
        ax.set_title("all controllers" if panel is None else column_label(*panel), fontsize=9)
    fig.colorbar(image, ax=axes.ravel().tolist(), label="e_Y RMSE (cm), mean over the other axes")
    fig.suptitle(f"Campaign {grid.name}: e_Y RMSE (x: not every cell completed)", fontsize=9)
    path = out_dir / "heatmap_e_y_rmse.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return [path]
