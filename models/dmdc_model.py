"""The DMDc artefact at run time: load ``models/artifacts/dmdc.{npz,json}`` and check it.

The ``dmdc-eso`` ablation's controller loads its model here; ``models.dmdc_artifact``
builds it (``make dmdc``) from the training data, and only that builder imports the
training code. The artefact is an ordinary ``models.koopman`` artefact of a linear model
with z = x (n_z = n_x = 3): states [vx, vy, yaw_rate], inputs [torque, steer].
"""
from __future__ import annotations

from pathlib import Path

from models.koopman import ARTIFACT_DIR, KoopmanError, KoopmanModel

#: The committed artefact (``<name>.npz`` + ``<name>.json``).
DMDC_ARTIFACT = ARTIFACT_DIR / "dmdc.npz"
#: ``kind`` in the artefact's JSON; ``load_dmdc_model`` refuses other artefacts.
DMDC_KIND = "DMDc"
#: The controller's sample time (s); the artefact must have been fitted at it.
TS = 0.025


def load_dmdc_model(path: str | Path = DMDC_ARTIFACT) -> KoopmanModel:
    """The DMDc artefact as a linear ``KoopmanModel`` with z = x (n_z = n_x = 3).

    Raises ``KoopmanError`` naming the file for a missing or unreadable artefact (with the
    command that builds it) and for one that is not a plain DMDc model.
    """
    npz_path = Path(path).with_suffix(".npz")
    try:
        model = KoopmanModel.load(npz_path)
    except KoopmanError as e:
        if not (npz_path.is_file() and npz_path.with_suffix(".json").is_file()):
            raise KoopmanError(f"{e}; build it with `make dmdc` (python -m models.dmdc_artifact)") from e
        raise
    kind = model.metadata.get("kind")
    if kind != DMDC_KIND:
        raise KoopmanError(f"{npz_path}: kind {kind!r} is not {DMDC_KIND!r}: not a DMDc artefact")
    if model.form != "linear" or model.n_z != model.n_x:
        raise KoopmanError(f"{npz_path}: a DMDc model is linear with z = x, got form {model.form!r}, "
                           f"n_z {model.n_z} for n_x {model.n_x}")
    if model.state_names != ("vx", "vy", "yaw_rate") or model.input_names != ("torque", "steer"):
        raise KoopmanError(f"{npz_path}: states {model.state_names} / inputs {model.input_names} are not "
                           "[vx, vy, yaw_rate] / [torque, steer], which the controller needs")
    if abs(model.ts - TS) > 1e-12:
        raise KoopmanError(f"{npz_path}: ts {model.ts} s is not the controller's {TS} s")
    return model
