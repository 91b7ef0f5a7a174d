"""Data set generator: deterministic for a seed, manifest, READY, loadable, CLI errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from models.data import generate_dataset, main, plan_run
from models.dataset import RUN_COLUMNS, load_dataset
from models.vehicle_params import load_vehicle_params


def _small(out, seed):
    # 2 runs of 5 s: enough to exercise every code path in a few seconds.
    return generate_dataset(out, hours=2 * 5.0 / 3600.0, seed=seed, run_duration=5.0, progress=False)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen_seed3")
    return out, _small(out, seed=3)


def test_generation_is_deterministic_for_a_seed(generated, tmp_path):
    first_dir, first = generated
    second = _small(tmp_path, seed=3)
    print(f"content hash seed 3, twice: {first['content_sha256'][:16]} / {second['content_sha256'][:16]}")
    assert first["content_sha256"] == second["content_sha256"]
    for path in sorted(first_dir.glob("run_*.csv")):
        assert path.read_bytes() == (tmp_path / path.name).read_bytes()
    # Another seed draws other manoeuvres (the plans are what the seed drives).
    params = load_vehicle_params()
    plan_a = plan_run(np.random.default_rng(3), 5.0, 0.025, params)
    plan_b = plan_run(np.random.default_rng(4), 5.0, 0.025, params)
    assert plan_a.initial_speed != plan_b.initial_speed


def test_output_has_manifest_ready_and_loads(generated):
    out, manifest = generated
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk["seed"] == 3 and on_disk["params"]["mass"] == 1648.0
    assert on_disk["content_sha256"] == manifest["content_sha256"]
    assert (out / "READY").read_text().strip() == manifest["content_sha256"]
    runs = load_dataset(out)
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
