"""The DMDc model of the ``dmdc-eso`` ablation as a committed artefact (build time vs run time).

``dmdc-eso`` is ESO-DKMPC with no lift: the observer (eq. 13) and the MPC (eq. 15) of
``controller.eso_dkmpc`` on a linear model x+ = A x + B u + c fitted by least squares
(``models.koopman_baselines.DMDc``), z = x. To compare like with like it is fitted on the
TRAINING runs of the default artefact's data and split (``data_dir`` and ``split`` of
``models/artifacts/dk_d5.json``), so the ECU never needs the data at run time:

    python -m models.dmdc_artifact --out models/artifacts/dmdc --replace
                                              # make dmdc; about 10 s plus the data set
                                              # (data/wide, make train generates it)

writes ``models/artifacts/dmdc.{npz,json}`` in the format of ``models.koopman.save_artifact``
(a linear model with no encoder and no dictionary: normalised A_n (3, 3), B_n (3, 2), the
affine term affine_n (3,) and the min-max bounds of the training runs), so
``KoopmanModel.load`` validates and folds it back to physical units exactly as it does the
deep model. The ECU loads it with ``models.dmdc_model.load_dmdc_model``, which adds the
checks that it IS such a model; that loader lives in its own module so that the run time
(and the provenance of every result the ECU produces) does not depend on the training
code this builder reads its data with.

``--out`` has no default (none points at the committed artefact) and an existing artefact
is overwritten only with ``--replace``, as ``models.koopman_train``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.dmdc_model import DMDC_ARTIFACT, DMDC_KIND, TS, load_dmdc_model
from models.errors import OutputPathError
from models.koopman import DEFAULT_ARTIFACT, KoopmanError, KoopmanModel, MinMaxScaling, NormalisedKoopman, save_artifact
from models.koopman_metrics import OPEN_LOOP_STEPS
from models.output_paths import check_output_file


def to_normalised(A: np.ndarray, B: np.ndarray, offset: np.ndarray, state_scaling: MinMaxScaling,
                  input_scaling: MinMaxScaling) -> NormalisedKoopman:
    """Physical x+ = A x + B u + offset -> the normalised quantities ``save_artifact`` stores.

    A (n_x, n_x), B (n_x, n_u), offset (n_x,). Inverts ``NormalisedKoopman.to_physical`` for
    a model with no encoder and no dictionary (S = diag(high - low), s = low, u_n = d_u u +
    c_u): A_n = S^-1 A S, B_n = S^-1 B diag(1 / d_u), affine_n = S^-1 (offset - s + A s -
    S B_n c_u), so that loading gives back A, B, offset to rounding.
    """
    span = state_scaling.high - state_scaling.low  # diagonal of S
    low = state_scaling.low
    A_n = (A * span[None, :]) / span[:, None]
    B_n = (B / input_scaling.scale[None, :]) / span[:, None]
    affine_n = (offset - low + A @ low - span * (B_n @ input_scaling.shift)) / span
    return NormalisedKoopman(encoder=(), A_n=A_n, B_n=B_n, state_scaling=state_scaling,
                             input_scaling=input_scaling, affine_n=affine_n)


def reference_split(reference_json: Path) -> tuple[Path, str, dict[str, list[str]]]:
    """(data_dir, data_hash, split {"train": [...], "validation": [...], "test": [...]}) of
    the artefact whose JSON is ``reference_json`` (the default: dk_d5.json)."""
    try:
        meta = json.loads(reference_json.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise KoopmanError(f"{reference_json}: cannot read the reference artefact's JSON: {e}") from e
    for key in ("data_dir", "data_hash", "split"):
        if key not in meta:
            raise KoopmanError(f"{reference_json}: missing field {key!r} (needed to fit DMDc on the same split)")
    split = meta["split"]
    if not isinstance(split, dict) or not all(isinstance(split.get(k), list) for k in ("train", "test")):
        raise KoopmanError(f"{reference_json}: 'split' must hold lists 'train' and 'test', got {type(split).__name__}")
    return Path(meta["data_dir"]), str(meta["data_hash"]), split


def build_dmdc_artifact(out: str | Path = DMDC_ARTIFACT, *, reference: str | Path = DEFAULT_ARTIFACT,
                        data_dir: str | Path | None = None) -> tuple[KoopmanModel, dict[str, Any]]:
    """Fit DMDc on the reference artefact's training runs and save it to ``out``.

    ``data_dir`` defaults to the reference's; its content hash must be the reference's
    (else the split's run names would pick other data). Returns the loaded model (what the
    controller will use) and the metadata written.
    """
    # Build time only: the data reader lives beside torch training code.
    from models.koopman_baselines import DMDc
    from models.koopman_metrics import prediction_errors
    from models.koopman_train import dataset_hash, fit_scaling, load_trajectories

    reference_json = Path(reference).with_suffix(".json")
    reference_dir, reference_hash, split = reference_split(reference_json)
    directory = Path(data_dir) if data_dir is not None else reference_dir
    if not directory.is_dir():
        raise KoopmanError(f"data directory not found: {directory} (generate it with make train, or "
                           f"python -m models.data generate --out {directory} --profile wide --hours 2 --seed 0)")
    data_hash = dataset_hash(directory)
    if data_hash != reference_hash:
        raise KoopmanError(f"{directory} holds other data ({data_hash}) than {reference_json.name} was "
                           f"trained on ({reference_hash}); regenerate it or retrain the reference")
    runs = {run.name: run for run in load_trajectories(directory)}
    missing = sorted(set(split["train"]) - set(runs))
    if missing:
        raise KoopmanError(f"{directory}: training runs of {reference_json.name} not found: {missing[:5]}")
    train = [runs[name] for name in split["train"]]
    test = [runs[name] for name in split["test"] if name in runs]
    fitted = DMDc().fit(train)
    state_scaling, input_scaling = fit_scaling(train)
    learned = to_normalised(fitted.A_, fitted.B_, fitted.offset_, state_scaling, input_scaling)
    metadata: dict[str, Any] = {
        "kind": DMDC_KIND,
        "ts": TS,
        "state_names": list(fitted.state_names_),
        "input_names": list(fitted.input_names_),
        "data_dir": str(directory),
        "data_hash": data_hash,
        "reference_artifact": reference_json.name,
        "split": {"train": list(split["train"]), "test": [run.name for run in test]},
        "n_train_runs": len(train),
        "spectral_radius_A": fitted.spectral_radius(),
        "test_errors": prediction_errors(fitted, test, open_loop_steps=OPEN_LOOP_STEPS) if test else {},
        "test_open_loop_steps": OPEN_LOOP_STEPS,
        "built_by": "python -m models.dmdc_artifact (make dmdc)",
    }
    npz_path, _ = save_artifact(out, learned, metadata)
    model = load_dmdc_model(npz_path)
    # The artefact must reproduce the fit: a wrong inversion would silently change the model.
    for name, fitted_value, loaded in (("A", fitted.A_, model.A), ("B", fitted.B_, model.B),
                                       ("offset", fitted.offset_, model.offset)):
        if not np.allclose(fitted_value, loaded, rtol=1e-9, atol=1e-12):
            raise KoopmanError(f"{npz_path}: saved {name} does not reproduce the fit "
                               f"(max diff {np.max(np.abs(fitted_value - loaded)):.3g})")
    return model, model.metadata


def check_out(out: Path, *, replace: bool, reference: Path, data_dir: Path | None) -> None:
    """Both files ``out`` names (.npz, .json) are writable before any fitting: neither is
    an input (the reference artefact, the data folder) and an existing one only with
    ``replace``.

    Raises:
        KoopmanError: naming ``--out``, the path and the problem.
    """
    inputs = [Path(reference).with_suffix(".npz"), Path(reference).with_suffix(".json"),
              *([Path(data_dir)] if data_dir is not None else [])]
    try:
        for suffix in (".npz", ".json"):
            check_output_file(Path(out).with_suffix(suffix), "--out", replace=replace, inputs=inputs)
    except OutputPathError as error:
        raise KoopmanError(str(error)) from None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.dmdc_artifact", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True,
                        help=f"artefact path without suffix (make dmdc: {DMDC_ARTIFACT.with_suffix('')})")
    parser.add_argument("--replace", action="store_true", help="overwrite an existing --out artefact")
    parser.add_argument("--reference", type=Path, default=DEFAULT_ARTIFACT,
                        help="artefact whose data_dir and training split to use (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=None, help="data folder (default: the reference's data_dir)")
    parser.add_argument("--debug", action="store_true", help="tracebacks on errors")
    args = parser.parse_args(argv)
    try:
        check_out(args.out, replace=args.replace, reference=args.reference, data_dir=args.data)
        model, meta = build_dmdc_artifact(args.out, reference=args.reference, data_dir=args.data)
    except KoopmanError as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2  # bad input (data, reference), as models.data and models.koopman_train
    print(f"wrote {Path(args.out).with_suffix('.npz')} and .json: DMDc on {meta['n_train_runs']} training runs "
          f"of {meta['data_dir']}, spectral radius of A {model.spectral_radius():.4f}")
    for name, figures in meta["test_errors"].items():
        print(f"  test {name:>10}: one-step rmse {figures['one_step_rmse']:.4f}, "
              f"{meta['test_open_loop_steps']}-step open-loop rmse {figures['open_loop_rmse']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
