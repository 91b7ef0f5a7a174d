"""Table I's rows without training, in minutes, beside the deep default row.

The rows of ``studies.table1.CLOSED_FORM_ROWS`` (DMDc, EDMDc, the trainer's least-squares
lifts ``--form edmdc-linear`` / ``edmdc-bilinear``, the linear bicycle, the single track),
measured as ``make table1`` measures them (same seeds, same split by run, same test runs
and figures: the same cells of the grid ``table1``, run in this process and cached in
``build/table1/cache/``) but without its hours of deep training. Then, for the 1 s and 2 s open-loop
RMSE of vy and yaw rate, the best least-squares row (DMDc, EDMDc, edmdc-*) beside Table I's
default deep row (``studies.table1.DEFAULT_ROW``) read from ``results/table1.json``, with
the ratio deep / least squares (issue 40 asks for at most 0.9), and whether that file is
listed stale in ``results/KNOWN_STALE.md`` and why.

Writes ``table1_least_squares.md`` and ``.json`` into ``--out`` (default ``results``).
CLI: ``python -m studies.table1_least_squares [--data data/wide] [--seeds 0,1,2,3,4]
[--out results] [--table1 results/table1.json] [--models-dir build/table1]`` (``make table1-lsq``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.errors import ModelError
from models.koopman import KoopmanError
from studies.provenance import KNOWN_STALE_NAME, known_stale_row
from studies.table1 import DEFAULT_ROW, FITTED_ROWS, SEEDS, _indices, markdown_table, measure_rows, table_json

#: The states and horizons compared with the deep row (issue 40, item 3).
COMPARED_STATES = ("vy", "yaw_rate")
COMPARED_HORIZONS = ("1 s", "2 s")
STEM = "table1_least_squares"


def stale_reason(table1_json: Path) -> str | None:
    """Why ``results/KNOWN_STALE.md`` (beside ``table1_json``) lists ``table1_json`` as stale
    (its third cell), or None where it does not."""
    listing = table1_json.parent / KNOWN_STALE_NAME
    if not listing.is_file():
        return None
    name = f"{table1_json.parent.name}/{table1_json.name}"
    for line in listing.read_text().splitlines():
        row = known_stale_row(line)
        if row is not None and name in row.files:
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            return cells[2] if len(cells) > 2 else ""
    return None


def _mean_sd(row: dict, state: str, horizon: str) -> tuple[float, float]:
    values = np.array([figures[state][horizon] for figures in row["seeds"]])
    return float(values.mean()), float(values.std(ddof=1)) if values.size > 1 else 0.0


def shared_rows_difference(rows: Sequence[dict], table1_rows: Sequence[dict]) -> dict[str, Any]:
    """The rows measured here and in Table I alike (DMDc, EDMDc, bicycle, single track): their
    labels and the largest relative difference of any figure of any seed, a check that both
    were measured on the same data, split and test runs."""
    theirs = {row["label"]: row for row in table1_rows}
    labels, largest = [], 0.0
    for row in rows:
        other = theirs.get(row["label"])
        if other is None or other["seed_ids"] != row["seed_ids"]:
            continue
        labels.append(row["label"])
        for mine, their in zip(row["seeds"], other["seeds"]):
            for state, figures in mine.items():
                for name, value in figures.items():
                    reference = their[state][name]
                    largest = max(largest, abs(value - reference) / max(abs(reference), 1e-12))
    return {"labels": labels, "max_relative_difference": largest}


def versus_deep(rows: Sequence[dict], seeds: Sequence[int], data_hash: str, table1_json: Path) -> dict[str, Any]:
    """The best least-squares row of ``rows`` (lowest mean over the seeds) beside Table I's
    default deep row, per state of COMPARED_STATES and horizon of COMPARED_HORIZONS.

    Returns {table1, deep_row, same_seeds, same_data, table1_data_hash, known_stale, cells:
    [{state, horizon, best_least_squares, least_squares_mean, least_squares_sd, deep_mean,
    deep_sd, deep_over_least_squares}]}; without cells (and with ``missing``) where
    ``table1_json`` or its default row is missing.
    """
    out: dict[str, Any] = {"table1": str(table1_json), "deep_row": DEFAULT_ROW.label,
                           "known_stale": stale_reason(table1_json)}
    if not table1_json.is_file():
        return {**out, "missing": f"{table1_json} not found"}
    table1 = json.loads(table1_json.read_text())
    deep = next((row for row in table1["rows"] if row["label"] == DEFAULT_ROW.label), None)
    if deep is None:
        return {**out, "missing": f"{table1_json} has no row {DEFAULT_ROW.label!r}"}
    out.update(same_seeds=list(table1["seeds"]) == list(seeds), same_data=table1["data_hash"] == data_hash,
               table1_data_hash=table1["data_hash"], shared_rows=shared_rows_difference(rows, table1["rows"]),
               cells=[])
    fitted = [row for row in rows if row["label"] in FITTED_ROWS]
    for state in COMPARED_STATES:
        for horizon in COMPARED_HORIZONS:
            best = min(fitted, key=lambda row: _mean_sd(row, state, horizon)[0])
            (lsq_mean, lsq_sd), (deep_mean, deep_sd) = _mean_sd(best, state, horizon), _mean_sd(deep, state, horizon)
            out["cells"].append({"state": state, "horizon": horizon, "best_least_squares": best["label"],
                                 "least_squares_mean": lsq_mean, "least_squares_sd": lsq_sd,
                                 "deep_mean": deep_mean, "deep_sd": deep_sd,
                                 "deep_over_least_squares": deep_mean / lsq_mean})
    return out


def comparison_markdown(comparison: dict[str, Any], seeds: Sequence[int], data_hash: str) -> str:
    """The report's section on the deep rows: where they are, the seeds, the comparison."""
    table1_md = Path(comparison["table1"]).with_suffix(".md")
    lines = ["## Beside the deep rows", "",
             f"Seeds {', '.join(map(str, seeds))} (each draws the split by run as the trainer does). The deep "
             f"rows are in `{table1_md}` (`make table1`: the same seeds, the same split and test runs, the same "
             "figures, so the rows compare cell for cell).", ""]
    if "missing" in comparison:
        return "\n".join([*lines, f"No comparison: {comparison['missing']}.", ""])
    if not comparison["same_seeds"]:
        lines += [f"`{comparison['table1']}` was measured with other seeds: its cells do not compare.", ""]
    if not comparison["same_data"]:
        lines += [f"`{comparison['table1']}` was measured on data {comparison['table1_data_hash']}, these rows on "
                  f"{data_hash} (the split by run depends only on the run names and the seed).", ""]
    shared = comparison["shared_rows"]
    if shared["labels"]:
        lines += [f"The rows in both tables ({', '.join(shared['labels'])}) differ by at most "
                  f"{shared['max_relative_difference']:.1e} (relative, any figure of any seed).", ""]
    if comparison["known_stale"] is not None:
        lines += [f"`{comparison['table1']}` is listed stale in `results/{KNOWN_STALE_NAME}`: "
                  f"\"{comparison['known_stale']}\"", ""]
    lines += [f"Open-loop RMSE, mean ± standard deviation over the seeds: the best least-squares row "
              f"({', '.join(FITTED_ROWS)}) and Table I's default deep row, \"{comparison['deep_row']}\".", "",
              "| state | horizon | best least-squares row | its RMSE | deep default's RMSE | deep / least squares |",
              "|---|---|---|---|---|---|"]
    for cell in comparison["cells"]:
        lines.append(f"| {cell['state']} | {cell['horizon']} | {cell['best_least_squares']} | "
                     f"{cell['least_squares_mean']:.4f} ± {cell['least_squares_sd']:.4f} | "
                     f"{cell['deep_mean']:.4f} ± {cell['deep_sd']:.4f} | {cell['deep_over_least_squares']:.2f} |")
    return "\n".join([*lines, ""])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.table1_least_squares",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/wide"))
    parser.add_argument("--seeds", type=_indices, default=SEEDS)
    parser.add_argument("--out", type=Path, default=Path("results"), help="folder for table1_least_squares.md/.json")
    parser.add_argument("--table1", type=Path, default=Path("results/table1.json"),
                        help="Table I's JSON with the deep rows (make table1)")
    parser.add_argument("--models-dir", type=Path, default=Path("build/table1"),
                        help="the cells' cache (cache/), shared with make table1")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    args = parser.parse_args(argv)
    try:
        if not args.data.is_dir():
            raise KoopmanError(f"data directory not found: {args.data} (make table1-lsq generates data/wide)")
        if not args.seeds:
            raise KoopmanError("--seeds must name at least one seed")
        measured = measure_rows(args.data, [], args.seeds, args.models_dir, {"serial": True})
        comparison = versus_deep(measured.rows, args.seeds, measured.data_hash, args.table1)
        generated_by = "`make table1-lsq` (`python -m studies.table1_least_squares`)"
        title = "Table I, the rows without training: prediction errors on held-out test runs, over seeds"
        report = (markdown_table(measured.rows, args.data, generated_by, title) + "\n"
                  + comparison_markdown(comparison, args.seeds, measured.data_hash))
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{STEM}.md").write_text(report)
        (args.out / f"{STEM}.json").write_text(json.dumps(
            {**table_json(measured, args.data, args.seeds), "versus_deep": comparison}, indent=1) + "\n")
    except (ModelError, OSError, ValueError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(comparison_markdown(comparison, args.seeds, measured.data_hash))
    print(f"wrote {args.out / f'{STEM}.md'}, {args.out / f'{STEM}.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
