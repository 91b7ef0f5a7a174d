"""The command line of the DMDc artefact's builder (``python -m models.dmdc_artifact``):
``--out`` has no default at the committed artefact, and an existing artefact is
overwritten only with ``--replace``, checked before the data are read."""
from __future__ import annotations

from pathlib import Path

import pytest

from models import dmdc_artifact


def test_out_is_required(tmp_path: Path, capsys) -> None:
    """No ``--out``: argparse's usage error (exit 2), nothing fitted or written."""
    with pytest.raises(SystemExit) as stop:
        dmdc_artifact.main(["--data", str(tmp_path / "no_data")])
    assert stop.value.code == 2
    assert "the following arguments are required: --out" in capsys.readouterr().err


@pytest.mark.parametrize("existing", [".npz", ".json"])
def test_an_existing_artifact_needs_replace(tmp_path: Path, capsys, existing: str) -> None:
    """Either file of an existing artefact without ``--replace``: one ``error:`` line naming
    ``--out`` and the file, exit 2, the file untouched. ``--data`` names no folder, so the
    check must come before the data are looked at."""
    out = tmp_path / "dmdc"
    out.with_suffix(existing).write_bytes(b"artefact")
    status = dmdc_artifact.main(["--out", str(out), "--data", str(tmp_path / "no_data")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert err == [f"error: --out {out}{existing}: file exists (give --replace to overwrite it)"]
    assert out.with_suffix(existing).read_bytes() == b"artefact"


def test_replace_lets_the_builder_run(tmp_path: Path, capsys) -> None:
    """With ``--replace`` the output check passes and the builder goes on (here to its own
    error on the missing data folder), the file still untouched since nothing was fitted."""
    out = tmp_path / "dmdc"
    out.with_suffix(".npz").write_bytes(b"artefact")
    status = dmdc_artifact.main(["--out", str(out), "--replace", "--data", str(tmp_path / "no_data")])
    assert status == 2
    assert capsys.readouterr().err.strip().startswith(f"error: data directory not found: {tmp_path / 'no_data'}")
    assert out.with_suffix(".npz").read_bytes() == b"artefact"
