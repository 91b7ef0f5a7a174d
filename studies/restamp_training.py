"""The training smoke of ``make restamp``: a change to the trainer keeps behaviour when a
small training gives the same model, bit for bit, before and after it.

The closed-loop smoke of ``studies.restamp`` runs the ECUs; it never trains. Every study on
the campaign engine imports the trainer (its prediction rows train models), so a change to
the trainer alone, an option that is off by default for one, makes dozens of closed-loop
results stale although none of their figures can move. This smoke covers that code: in the
base revision's tree and in this checkout, each with its own code,

1. generate a small wide data set (``python -m models.data generate``, :data:`DATA_ARGS`:
   26 runs of 30 s, about 30 s), so that the data generator is checked too;
2. train on it with the default artefact's form (``KOOPMAN_FORM`` of ``mk/koopman.mk``,
   the anchored mirror form) for :data:`SHORT_TRAINING` (2 epochs of 10 steps, about 10 s),
   and fit the least-squares lift ``--form edmdc-bilinear``
   (``python -m models.koopman_train``: its command line, settings, split and writer);
3. compare the written artefacts: every array of the ``.npz`` byte for byte, and the
   ``.json`` with the wall-clock seconds and the data folder's path left out
   (:data:`VOLATILE_KEYS`).

One difference, or a run that fails in either tree, and nothing is restamped. Training from
CAN logs (``--logs``, the identification and vehicle-variant studies) runs the same trainer
behind a loader that the smoke does not exercise (:data:`NOT_TRAINED`): a change there
needs those studies rerun, as the restamp's rule for code outside its smoke says.
"""
from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import numpy as np

from studies import provenance

#: The trainer's entry points: the command line and the data generator.
TRAINING_ENTRY_MODULES = ("models.koopman_train", "models.data")
#: Trainer code the smoke does not run: training from CAN logs and named-column CSVs with a
#: mapping (``--logs``, ``--mapping``), and ``--compare-with``.
NOT_TRAINED = frozenset({"models/can_log_data.py", "models/log_identification.py", "models/named_csv_data.py",
                         "models/koopman_compare.py"})
#: A small wide data set (26 runs of 30 s after the generator's checks).
DATA_ARGS = ("--profile", "wide", "--hours", "0.25", "--run-duration", "30", "--seed", "0")
#: A short training: the code paths of a full one, a few seconds.
SHORT_TRAINING = ("--epochs", "2", "--steps-per-epoch", "10", "--seed", "0", "--threads", "1")
#: The trainings of the smoke besides the default form: (name, arguments). A closed-form
#: fit takes none of the network's options.
OTHER_FORMS = (("edmdc-bilinear", ("--form", "edmdc-bilinear")),)
#: Metadata that the host decides, not the trainer: wall-clock seconds and the data's path.
VOLATILE_KEYS = ("training_seconds", "data_dir")
RUN_TIMEOUT_S = 900


class TrainingSmokeError(Exception):
    """A training smoke run failed or its form cannot be read."""


def training_sources(root: Path = provenance.ROOT) -> frozenset[str]:
    """The source files (paths from ``root``) that the training smoke executes: the project
    modules of :data:`TRAINING_ENTRY_MODULES`, transitively, without studies/ and
    :data:`NOT_TRAINED`."""
    modules = provenance.module_sources(TRAINING_ENTRY_MODULES, root)
    names = (path.relative_to(root).as_posix() for path in modules)
    return frozenset(name for name in names if not name.startswith("studies/") and name not in NOT_TRAINED)


def default_form(root: Path = provenance.ROOT) -> list[str]:
    """The default artefact's trainer options: ``KOOPMAN_FORM`` of ``mk/koopman.mk``."""
    makefile = root / "mk" / "koopman.mk"
    found = re.search(r"^KOOPMAN_FORM\s*\?=\s*(.+)$", makefile.read_text(), re.MULTILINE)
    if found is None:
        raise TrainingSmokeError(f"{makefile}: no KOOPMAN_FORM line")
    return shlex.split(found.group(1))


def training_smoke(tree: Path, out: Path, form: list[str], report: Callable[[str], None] = print,
                   data: Path | None = None) -> list[Path]:
    """Generate the data set and run the trainings with the code of ``tree``, writing under
    ``out``; returns the artefacts (without extension) in a fixed order. ``data``: train on
    this data set instead of generating one (the data generator then goes unchecked). Raises
    TrainingSmokeError when a command fails."""
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    python = str((tree / ".venv" / "bin" / "python").absolute())
    commands = []
    if data is None:
        data = out / "data"
        shutil.rmtree(data, ignore_errors=True)  # the generator refuses an existing data set
        commands.append(("data", [python, "-m", "models.data", "generate", "--out", str(data), *DATA_ARGS,
                                  "--no-progress"]))
    artefacts = []
    for name, extra in (("default", (*SHORT_TRAINING, *form)), *OTHER_FORMS):
        artefact = out / name
        artefacts.append(artefact)
        commands.append((name, [python, "-m", "models.koopman_train", "--data", str(data), "--out", str(artefact),
                                "--replace", "--no-progress", *extra]))
    for name, command in commands:
        report(f"  {tree.name}: training smoke, {name}")
        done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
        if done.returncode != 0:
            raise TrainingSmokeError(f"training smoke failed in {tree} ({' '.join(command[1:])}):\n"
                                     f"{done.stdout[-1000:]}{done.stderr[-2000:]}")
    return artefacts


def artefact_difference(base: Path, now: Path) -> str | None:
    """None when the artefacts ``base`` and ``now`` (paths without extension) hold the same
    arrays, byte for byte, and the same metadata but for :data:`VOLATILE_KEYS`; else the
    first difference."""
    with np.load(base.with_suffix(".npz")) as a, np.load(now.with_suffix(".npz")) as b:
        if sorted(a.files) != sorted(b.files):
            return f"{now.name}.npz: arrays {sorted(a.files)} at the base, {sorted(b.files)} now"
        for key in sorted(a.files):
            x, y = a[key], b[key]
            if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
                return f"{now.name}.npz: array {key} differs"
    meta = [json.loads(path.with_suffix(".json").read_text()) for path in (base, now)]
    for entry in meta:
        for key in VOLATILE_KEYS:
            entry.pop(key, None)
    if meta[0] != meta[1]:
        keys = sorted(k for k in set(meta[0]) | set(meta[1]) if meta[0].get(k) != meta[1].get(k))
        return f"{now.name}.json: {', '.join(keys)} differ"
    return None
