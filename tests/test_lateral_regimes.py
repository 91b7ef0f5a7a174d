"""The lateral-regimes study: its local fits, its regimes and its table."""
from __future__ import annotations

import numpy as np
import pytest

from models.errors import DatasetError
from models.koopman_baselines import DMDc
from models.koopman_metrics import Trajectory
from models import local_lateral_fit as llf
from studies import lateral_regimes as lr

#: A stable lateral system [vy, r, delta]+ = A x + B [torque, steer] + c (25 ms steps).
A = np.array([[0.90, -0.20, 0.30], [0.02, 0.85, 0.40], [0.0, 0.0, 0.70]])
B = np.array([[1e-5, 0.01], [2e-5, 0.02], [0.0, 0.30]])
C = np.array([0.001, -0.002, 0.0])


def _run(name: str, speed: float, n: int, seed: int) -> Trajectory:
    """A run at constant ``speed`` driven by random torque and steer through (A, B, C)."""
    rng = np.random.default_rng(seed)
    inputs = np.column_stack([rng.normal(0.0, 300.0, n), rng.normal(0.0, 0.05, n)])
    lateral = np.zeros((n, 3))
    for k in range(n - 1):
        lateral[k + 1] = A @ lateral[k] + B @ inputs[k] + C
    states = np.column_stack([np.full(n, speed), lateral])
    return Trajectory(name, states, inputs, lr.STATES, lr.INPUTS)


def test_a_local_fit_recovers_a_linear_system_from_the_samples_of_its_speed_band() -> None:
    runs = [_run("a", 10.0, 400, 0), _run("b", 20.0, 400, 1), _run("c", 10.3, 300, 2)]
    masks = [np.ones(len(r), dtype=bool) for r in runs]
    fit, n = lr.local_fit(runs, masks, 10.0)
    assert n == 399 + 299  # run b is outside the band; the last sample of a run has no successor
    assert fit.A_ == pytest.approx(A, abs=1e-9)
    assert fit.B_ == pytest.approx(B, abs=1e-9)
    assert fit.offset_ == pytest.approx(C, abs=1e-9)
    few = [np.arange(len(r)) < 50 for r in runs]
    empty, n_few = lr.local_fit(runs, few, 10.0)
    assert empty is None and n_few == 50 + 50  # fewer than MIN_SAMPLES: no fit
    gaps = [np.arange(len(r)) % 10 < 5 for r in runs]  # stretches of 5 samples, each with its successor
    assert sum(len(s) - 1 for s in lr.band_segments(runs, gaps, 10.0)) == 200 + 150


def test_the_antisymmetric_response_keeps_only_the_steer_part() -> None:
    lateral = DMDc()
    lateral.A_, lateral.B_, lateral.offset_, lateral.n_x_ = A, B, C, 3
    model = lr.LocalLateralModel(lateral)
    n = 40
    commands = np.column_stack([np.full(n, 250.0), np.full(n, 0.02)])
    states = np.zeros((n + 1, 4))
    states[:, 0] = 15.0
    response = lr.antisymmetric_response(model, states, commands)
    lateral = np.zeros(3)
    for _ in range(n):  # the steer alone, no torque, no constant
        lateral = A @ lateral + B[:, 1] * 0.02
    assert response[0] == 0.0  # vx held: the same after both steps
    assert response[1:] == pytest.approx(lateral, rel=1e-12)


def test_signals_and_regimes_select_by_longitudinal_and_lateral_grip_use() -> None:
    t = np.arange(200) * llf.TS
    vx = 10.0 - 2.0 * t  # braking at 2 m/s^2
    r = np.where(t < 2.5, 0.05, 0.6)  # |vx r| about 0.5 m/s^2, then about 3-5 m/s^2
    run = Trajectory("brake", np.column_stack([vx, np.zeros_like(t), r, np.zeros_like(t)]),
                     np.zeros((200, 2)), lr.STATES, lr.INPUTS)
    s = lr.signals(run, mu=1.0)
    assert s.ax == pytest.approx(np.full(200, -2.0))
    assert s.lateral_grip == pytest.approx(np.abs(vx * r) / llf.GRAVITY)
    assert s.combined_grip == pytest.approx(np.hypot(2.0, vx * r) / llf.GRAVITY)
    braking = lr.REGIMES["braking, ax < -0.5 m/s², lateral grip use < 0.3"](s)
    assert braking.tolist() == (np.abs(vx * r) / llf.GRAVITY < 0.3).tolist()
    assert not lr.REGIMES["steady speed, ax within ±0.2 m/s²"](s).any()
    assert not lr.REGIMES["traction, ax > 0.5 m/s², lateral grip use < 0.3"](s).any()


def test_the_table_and_figure_name_each_regime_and_the_cells_without_enough_samples(tmp_path) -> None:
    result = {"data_dir": "data/wide", "artifact": "models/artifacts/dk_d5.npz", "band": 0.7, "n_runs": 3,
              "speeds": [10.0, 15.0],
              "plant": [{"yaw_rate": 0.0673, "vy": 0.072}, {"yaw_rate": 0.094, "vy": 0.038}],
              "model": [{"yaw_error_pct": -6.8, "vy": 0.059}, {"yaw_error_pct": -6.4, "vy": -0.005}],
              "regimes": [{"regime": "all samples", "cells": [{"samples": 7074, "yaw_error_pct": -4.6, "vy": 0.062},
                                                              {"samples": 12}]}]}
    text = lr.markdown(result)
    assert "| local fit, all samples | -4.6 % / +0.062 (7074) | too few samples (12) |" in text
    assert "| learned model `dk_d5.npz` | -6.8 % / +0.059 | -6.4 % / -0.005 |" in text
    assert "0.0673 / +0.072" in text
    lr.plot(result, tmp_path / "regimes.png")  # a cell without a fit is drawn as a gap, not an error
    assert (tmp_path / "regimes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_friction_of_runs_reads_each_runs_mu_from_the_manifest(tmp_path):
    assert llf.friction_of_runs(tmp_path) == {}  # recorded logs: no manifest, no known mu
    (tmp_path / "manifest.json").write_text(
        '{"params": {"mu": 0.85}, "runs": [{"file": "run_000.csv", "mu": 0.31},'
        ' {"file": "run_001.csv"}, {"file": null, "mu": 0.5}]}')
    assert llf.friction_of_runs(tmp_path) == {"run_000": 0.31, "run_001": 0.85}  # the dropped run has no file
    (tmp_path / "manifest.json").write_text('{"params": {}}')
    with pytest.raises(DatasetError, match="manifest.json.*run list"):
        llf.friction_of_runs(tmp_path)
