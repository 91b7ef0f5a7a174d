"""Tables II / III over the seeds of the learned model: ``make seed-spread``.

The Koopman controllers (ESO-DKMPC, DKMPC) depend on a trained model, and training depends
on its seed (weights and split). This study runs them on the two evaluation lane changes
(``dlc_high_mu``, ``dlc_low_mu``) once per seed of the default model form (the committed
artefact is seed 0; seeds 1-4 are Table I's models of the default row, ``make table1``),
with the shipped tuning, and the physics-model controllers (LMPC, NMPC) once (they have no
seed). The learned controllers also run on each seed of three other rows of Table I (issue
40), what each form would do in closed loop before it could become the default: the default
with the lateral velocity's anchor as well (``VY_ANCHOR_ROW``, ``--gain-anchor-vy 10``) and
the wider mirror form on the physics dictionary with the gain anchor at weight 10
(``DICTIONARY_ANCHOR_ROW``) and at weight 1 (``DICTIONARY_LIGHT_ANCHOR_ROW``), and the last
without the dictionary's vx^2/100 (``DICTIONARY_NO_SQUARE_ROW``).
It writes ``results/seed_spread.md`` / ``.json``: e_Y RMSE per seed, and mean ± sd.

No tuning happens here: the settings are those of ``controller/tuning.toml``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from controller.registry import create_controller
from controller.tuning import load_tuning
from hil.errors import StudyError
from hil.scenario import load_scenario
from models.koopman import DEFAULT_ARTIFACT, KoopmanModel
from studies.closed_loop import run_closed_loop
from studies.table1 import (DEFAULT_ROW, DICTIONARY_ANCHOR_ROW, DICTIONARY_LIGHT_ANCHOR_ROW, DICTIONARY_NO_SQUARE_ROW,
                            VY_ANCHOR_ROW, Row,
                            cached_model_path)

SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
LEARNED = ("eso-dkmpc", "dkmpc")
PHYSICS = ("lmpc", "nmpc")
#: The labels' suffixes here of Table I's other rows the learned controllers run on.
VY_ANCHOR = " + vy anchor"
DICTIONARY = " + dictionary, d=12"
DICTIONARY_LIGHT_ANCHOR = " + dictionary, d=12, anchor w=1"
NO_SQUARE = " + dictionary without vx^2, d=12, anchor w=1"
#: (suffix, Table I's row, the JSON key of its artefacts), the default first.
FORMS = (("", DEFAULT_ROW, "artifacts"), (VY_ANCHOR, VY_ANCHOR_ROW, "vy_anchor_artifacts"),
         (DICTIONARY, DICTIONARY_ANCHOR_ROW, "dictionary_artifacts"),
         (DICTIONARY_LIGHT_ANCHOR, DICTIONARY_LIGHT_ANCHOR_ROW, "dictionary_light_anchor_artifacts"),
         (NO_SQUARE, DICTIONARY_NO_SQUARE_ROW, "no_square_artifacts"))


def artifact_paths(models_dir: Path, seeds: Sequence[int], row: Row = DEFAULT_ROW) -> dict[int, Path]:
    """Seed -> where the artefact of Table I's ``row`` is (the default row's seed 0: the
    committed default artefact), whether it is there or not."""
    return {seed: DEFAULT_ARTIFACT if seed == 0 and row is DEFAULT_ROW else cached_model_path(row, seed, models_dir)
            for seed in seeds}


def missing_models(models_dir: Path, seeds: Sequence[int], row: Row = DEFAULT_ROW) -> list[str]:
    """One line per seed whose artefact of ``row`` is not there, naming the command that
    trains it."""
    return [f"{path} missing: run `make table1` (it trains the seeds of {row.label!r})"
            for path in artifact_paths(models_dir, seeds, row).values() if not path.is_file()]


def seed_artifacts(models_dir: Path, seeds: Sequence[int], row: Row = DEFAULT_ROW) -> dict[int, Path]:
    """Seed -> artefact of Table I's ``row``.

    Raises:
        StudyError: a seed's artefact is missing (:func:`missing_models`'s first line).
    """
    missing = missing_models(models_dir, seeds, row)
    if missing:
        raise StudyError(missing[0])
    return artifact_paths(models_dir, seeds, row)


def learned_controller(name: str, model: KoopmanModel):
    """ESO-DKMPC or DKMPC on ``model`` with the shipped tuning."""
    from controller.dkmpc import Dkmpc
    from controller.eso_dkmpc import EsoDkmpc

    tuning = load_tuning()
    cls = EsoDkmpc if name == "eso-dkmpc" else Dkmpc
    return cls(model, tuning.for_controller(name), tuning.longitudinal)


def run_one(scenario_name: str, controller) -> dict:
    """e_Y RMSE / max and completion of one run."""
    result = run_closed_loop(load_scenario(scenario_name), controller)
    lateral = result.tracking.lateral
    return {"completed": bool(result.completed), "e_y_rmse": float(lateral.rmse), "e_y_max": float(lateral.max_abs)}


def markdown(doc: dict) -> str:
    """The per-seed table and the mean ± sd line per controller and scenario."""
    lines = ["# Tables II / III over the seeds of the learned model", "",
             "Written by `make seed-spread` (studies/seed_spread.py). e_Y RMSE (m) on the closed loop "
             "without CAN (as `make tables`); the learned controllers once per seed of the default model "
             "(seed 0 = the committed artefact), of Table I's row with the lateral velocity's anchor as well "
             f"(`{VY_ANCHOR.strip()}`) and of its rows of the d = 12 mirror form on the physics dictionary with the "
             f"gain anchor at weight 10 (`{DICTIONARY.strip()}`) and at weight 1 (`{DICTIONARY_LIGHT_ANCHOR.strip()}`), "
             f"the last without the dictionary's vx^2/100 (`{NO_SQUARE.strip()}`; "
             "every seed of these trained by `make table1`), the physics-model ones once. "
             "`*`: did not complete.", "",
             "| controller | scenario | " + " | ".join(f"seed {s}" for s in doc["seeds"]) + " | mean ± sd |",
             "|---|---|" + "---|" * (len(doc["seeds"]) + 1)]
    for name in (*(n + suffix for suffix, _, _ in FORMS for n in LEARNED), *PHYSICS):
        if name not in doc["runs"]:
            continue
        for scenario in SCENARIOS:
            runs = doc["runs"][name][scenario]
            cells = [f"{r['e_y_rmse']:.3f}{'' if r['completed'] else '*'}" for r in runs]
            values = np.array([r["e_y_rmse"] for r in runs])
            spread = f"{values.mean():.3f} ± {values.std(ddof=1):.3f}" if values.size > 1 else f"{values[0]:.3f}"
            if len(cells) == 1:
                cells = cells * len(doc["seeds"])
            lines.append(f"| {name} | {scenario} | " + " | ".join(cells) + f" | {spread} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.seed_spread", description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=lambda t: tuple(int(v) for v in t.split(",")), default=(0, 1, 2, 3, 4))
    parser.add_argument("--models-dir", type=Path, default=Path("build/table1"))
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--check-models", action="store_true",
                        help="only say whether --models-dir holds every seed's model (exit 0) or not (1)")
    args = parser.parse_args(argv)
    if args.check_models:
        missing = [line for _, row, _ in FORMS for line in missing_models(args.models_dir, args.seeds, row)]
        for line in missing:
            print(f"error: {line}", file=sys.stderr)
        if missing:
            return 1
        print(f"{args.models_dir}: every seed's model of the {len(FORMS)} forms is there")
        return 0
    try:
        forms = [(suffix, key, seed_artifacts(args.models_dir, args.seeds, row)) for suffix, row, key in FORMS]
    except StudyError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    runs: dict[str, dict[str, list[dict]]] = {}
    for suffix, _, paths in forms:
        for name in LEARNED:
            label = name + suffix
            runs[label] = {s: [] for s in SCENARIOS}
            for seed, path in paths.items():
                model = KoopmanModel.load(path)
                for scenario in SCENARIOS:
                    runs[label][scenario].append(run_one(scenario, learned_controller(name, model)))
                    print(f"{label} seed {seed} {scenario}: e_Y RMSE {runs[label][scenario][-1]['e_y_rmse']:.3f} m",
                          flush=True)
    for name in PHYSICS:
        runs[name] = {s: [run_one(s, create_controller(name))] for s in SCENARIOS}
    doc = {"seeds": list(args.seeds), **{key: {str(k): str(v) for k, v in paths.items()} for _, key, paths in forms},
           "runs": runs}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "seed_spread.md").write_text(markdown(doc))
    (args.out / "seed_spread.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out / 'seed_spread.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
