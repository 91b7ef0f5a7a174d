"""Data set generator: deterministic for a seed, manifest, READY, loadable, CLI errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from models.data import generate_dataset, main
from models.dataset import RUN_COLUMNS, load_dataset


def _small(out, seed):
    # 3 runs of 6 s: enough to exercise every code path in a few seconds.
    return generate_dataset(out, hours=3 * 6.0 / 3600.0, seed=seed, run_duration=6.0, progress=False)


def test_generation_is_deterministic_for_a_seed(tmp_path):
    first = _small(tmp_path / "a", seed=3)
    second = _small(tmp_path / "b", seed=3)
    other = _small(tmp_path / "c", seed=4)
    print(f"content hash seed 3: {first['content_sha256'][:16]} / {second['content_sha256'][:16]}, "
          f"seed 4: {other['content_sha256'][:16]}")
    assert first["content_sha256"] == second["content_sha256"]
    assert first["content_sha256"] != other["content_sha256"]
    for name in ("run_0000.csv", "run_0001.csv"):
        if (tmp_path / "a" / name).exists():
            assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_output_has_manifest_ready_and_loads(tmp_path):
    manifest = _small(tmp_path, seed=0)
    on_disk = json.loads((tmp_path / "manifest.json").read_text())
    assert on_disk["seed"] == 0 and on_disk["params"]["mass"] == 1648.0
    assert on_disk["content_sha256"] == manifest["content_sha256"]
    assert (tmp_path / "READY").read_text().strip() == manifest["content_sha256"]
    runs = load_dataset(tmp_path)
    assert len(runs) == manifest["n_runs"] >= 1
    for run in runs:
        data = run.array(RUN_COLUMNS)
        assert np.all(np.isfinite(data))
        assert np.allclose(np.diff(run.time), 0.025)
        assert np.all(np.abs(run.columns["steer"]) <= 0.3 + 1e-12)
        assert np.all(run.columns["vx"] > 2.0)
    vx = np.concatenate([r.columns["vx"] for r in runs])
    print(f"{len(runs)} runs, vx {vx.min():.1f}..{vx.max():.1f} m/s")


def test_cli_rejects_bad_hours(tmp_path, capsys):
    assert main(["generate", "--out", str(tmp_path), "--hours", "-1", "--no-progress"]) != 0
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and "hours" in err
