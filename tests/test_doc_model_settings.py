"""The manuals' statements of the trainer's defaults and of the committed artefact's form
against models/koopman_settings.py TrainingSettings and models/artifacts/dk_d5.json."""
from __future__ import annotations

import json
import re
from pathlib import Path

from models.koopman_settings import TrainingSettings

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
COMMITTED = ROOT / "models" / "artifacts" / "dk_d5.json"


def _flat(doc: str) -> str:
    """A manual's text with its line breaks as spaces (a sentence may span lines)."""
    return " ".join((DOCS / doc).read_text().split())


def test_koopman_md_names_the_default_encoder_and_features() -> None:
    """docs/koopman.md's opening: the default encoder's hidden layers and d, and the
    committed artefact's d (its JSON's settings)."""
    defaults = TrainingSettings()
    committed = json.loads(COMMITTED.read_text())["settings"]
    text = _flat("koopman.md")
    widths = set(defaults.hidden)
    assert len(widths) == 1, "the manual names one width for every hidden layer"
    assert f"{len(defaults.hidden)} hidden layers of {widths.pop()} tanh units" in text
    assert f"`--hidden {','.join(map(str, defaults.hidden))}`, the default" in text
    assert f"d = {defaults.n_features} by default, {committed['n_features']} in the committed artefact" in text


def test_identification_md_says_which_form_logs_train() -> None:
    """``--logs`` with the default options trains TrainingSettings' form: the manual says so,
    and names the options of the committed artefact's form where the two differ."""
    defaults = TrainingSettings()
    committed = json.loads(COMMITTED.read_text())["settings"]
    text = _flat("identification.md")
    assert "an artefact of the committed artefact's form" not in text
    assert (f"an artefact of the trainer's default form (`models/koopman_settings.py` `TrainingSettings`: "
            f"{defaults.form}, d = {defaults.n_features} features") in text
    options = re.search(r"python -m models\.koopman_train --logs LOG --out DIR ([^`]*)`", text)
    assert options is not None
    given = options.group(1).split()
    assert given[given.index("--features") + 1] == str(committed["n_features"])
    for flag, key in (("--mirror-symmetric", "mirror_symmetric"), ("--servo-lag", "servo_lag"),
                      ("--steer-bilinear", "steer_bilinear")):
        assert (flag in given) == bool(committed[key]) and committed[key] != getattr(defaults, key)
    assert float(given[given.index("--gain-anchor") + 1]) == committed["gain_anchor"]
    assert int(given[given.index("--even-features") + 1]) == committed["even_features"]
