"""How well each prediction model steers like the plant: ``make model-fidelity``.

Two tables into ``results/model_fidelity.md`` (figures also in ``model_fidelity.json``):

1. Step steer: from straight driving at 10, 15, 20 and 25 m/s, a 0.02 rad steer command
   held 1 s (the plant's speed-holding torque sequence fed to every model, open loop);
   yaw rate and lateral velocity after 1 s for the plant and each model, and the yaw-rate
   error in %.
2. Open-loop prediction on the default artefact's held-out test runs (of its own data set):
   RMSE of vx, vy and yaw rate over 1 s (40 steps) and 2 s (80 steps), started every 5
   samples, with the true inputs.

Models: the default learned model (``models/artifacts/dk_d5``, the form its artefact
states), the paper's linear form trained on nominal data (``dk_paper_nominal``, Fig. 7's
model), LMPC's linear bicycle (speed held at the start value, as LMPC does) and NMPC's
nonlinear single track (nominal parameters, RK4 at Ts).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from models.bicycle import LinearBicycle, nominal_model_params
from models.data import speed_hold_torque
from models.koopman import ARTIFACT_DIR, DEFAULT_ARTIFACT, KoopmanModel
from models.koopman_metrics import open_loop_windows
from models.koopman_train import load_trajectories
from models.single_track import single_track_rk4_step
from models.vehicle import FourWheelVehicle, PlantModel, VehicleCommand

TS = 0.025
STEP_SPEEDS = (10.0, 15.0, 20.0, 25.0)
STEP_STEER = 0.02  # rad
STEP_SECONDS = 1.0
LEAD_IN_SECONDS = 0.5  # straight driving before the step
HORIZONS = {"1 s": 40, "2 s": 80}
PAPER_NOMINAL = ARTIFACT_DIR / "dk_paper_nominal.npz"


class BicyclePredictor:
    """LMPC's prediction model: the linear bicycle at the start speed, vx held."""

    def __init__(self) -> None:
        self.bicycle = LinearBicycle()

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, 3), inputs (batch, n, 2) -> states (batch, n, 3)."""
        out = np.empty(inputs.shape[:2] + (3,))
        for b in range(len(x0)):
            a, bb = self.bicycle.discrete_matrices(max(float(x0[b, 0]), 1.0), TS)
            lateral = x0[b, 1:].copy()
            for i in range(inputs.shape[1]):
                lateral = a @ lateral + np.asarray(bb).reshape(2) * inputs[b, i, 1]
                out[b, i, 1:] = lateral
            out[b, :, 0] = x0[b, 0]
        return out


class SingleTrackPredictor:
    """NMPC's prediction model: the nonlinear single track, nominal parameters, RK4 at Ts."""

    def __init__(self) -> None:
        self.params = nominal_model_params()

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, 3), inputs (batch, n, 2) -> states (batch, n, 3), batched."""
        state = np.asarray(x0, dtype=float)
        out = np.empty(inputs.shape[:2] + (3,))
        for i in range(inputs.shape[1]):
            state = single_track_rk4_step(state, inputs[:, i, 1], inputs[:, i, 0], self.params, TS)
            out[:, i] = state
        return out


def plant_step_steer(speed: float) -> tuple[np.ndarray, np.ndarray]:
    """The plant's step: states (n + 1, 4) = [vx, vy, r, measured wheel angle] and commands
    (n, 2) from the step onset on."""
    vehicle = FourWheelVehicle()
    vehicle.reset(vx=speed)
    p = vehicle.params
    drag = PlantModel(p).drag_factor
    lead, steps = round(LEAD_IN_SECONDS / TS), round(STEP_SECONDS / TS)
    states, commands = [], []
    out = vehicle.outputs()
    for k in range(lead + steps):
        torque = speed_hold_torque(p, drag, out.vx, speed)
        steer = STEP_STEER if k >= lead else 0.0
        if k >= lead:
            states.append([out.vx, out.vy, out.yaw_rate, out.steer_angle])
            commands.append([torque, steer])
        out = vehicle.step(VehicleCommand(drive_torque=torque, steer_angle=steer), TS)
    states.append([out.vx, out.vy, out.yaw_rate, out.steer_angle])
    return np.array(states), np.array(commands)


def step_steer_table(models: dict[str, object]) -> list[dict]:
    """Rows {speed, model, yaw_rate, vy, yaw_error_pct} after 1 s of the step."""
    rows = []
    for speed in STEP_SPEEDS:
        states, commands = plant_step_steer(speed)
        plant_r, plant_vy = states[-1, 2], states[-1, 1]
        rows.append({"speed": speed, "model": "plant", "yaw_rate": plant_r, "vy": plant_vy, "yaw_error_pct": 0.0})
        for name, model in models.items():
            final = step_steer_final(model, states, commands)
            rows.append({"speed": speed, "model": name, "yaw_rate": float(final[2]), "vy": float(final[1]),
                         "yaw_error_pct": float(100.0 * (final[2] / plant_r - 1.0))})
    return rows


def step_steer_final(model: object, states: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """The model's state 1 s after the step: open loop from the plant's first state
    (``states`` (n + 1, 4)) with the plant's ``commands`` (n, 2) -> (>= 3,) [vx, vy, r, ...]."""
    return model.predict(states[:1, :model_states(model)], commands[None])[0, -1]


def model_states(model: object) -> int:
    """How many leading states of [vx, vy, r, wheel angle] a model takes (3 for the physics models)."""
    return getattr(model, "n_x", 3)


def prediction_table(models: dict[str, object], data_dir: Path, test_runs: Sequence[str]) -> list[dict]:
    """Rows {model, horizon, rmse {state: value}} on the named test runs."""
    runs = {r.name: r for r in load_trajectories(data_dir, states=("vx", "vy", "yaw_rate", "steer_measured"))}
    missing = [n for n in test_runs if n not in runs]
    if missing:
        raise SystemExit(f"error: {data_dir} lacks the artefact's test runs {missing[:3]}...: "
                         "generate the data set the artefact was trained on (make train does)")
    test = [runs[n] for n in test_runs]
    rows = []
    for label, steps in HORIZONS.items():
        x0, inputs, truth = open_loop_windows(test, steps, 5)
        for name, model in models.items():
            n = model_states(model)
            error = model.predict(x0[:, :n], inputs)[..., :3] - truth[..., :3]
            rmse = np.sqrt(np.mean(error ** 2, axis=(0, 1)))
            rows.append({"model": name, "horizon": label,
                         "rmse": dict(zip(("vx", "vy", "yaw_rate"), map(float, rmse)))})
    return rows


def markdown(step_rows: list[dict], prediction_rows: list[dict], names: list[str], data_dir: Path) -> str:
    """The two tables as markdown."""
    lines = ["# Model fidelity: step steer and open-loop prediction", "",
             "Written by `make model-fidelity` (studies/model_fidelity.py).", "",
             "## Step steer", "",
             f"Yaw rate (rad/s) / lateral velocity (m/s) {STEP_SECONDS:.0f} s after a {STEP_STEER} rad steer "
             "step from straight driving, open loop with the plant's torque; in brackets the yaw-rate "
             "error against the plant.", "",
             "| speed (m/s) | plant | " + " | ".join(names) + " |",
             "|---|---|" + "---|" * len(names)]
    for speed in STEP_SPEEDS:
        rows = {r["model"]: r for r in step_rows if r["speed"] == speed}
        cells = [f"{rows['plant']['yaw_rate']:.3f} / {rows['plant']['vy']:+.3f}"]
        cells += [f"{rows[n]['yaw_rate']:.3f} / {rows[n]['vy']:+.3f} ({rows[n]['yaw_error_pct']:+.1f} %)"
                  for n in names]
        lines.append(f"| {speed:.0f} | " + " | ".join(cells) + " |")
    lines += ["", "## Open-loop prediction on held-out runs", "",
              f"RMSE over every predicted step, windows started every 5 samples, on the default "
              f"artefact's test runs of `{data_dir}`.", "",
              "| model | horizon | vx (m/s) | vy (m/s) | yaw rate (rad/s) |", "|---|---|---|---|---|"]
    for row in prediction_rows:
        r = row["rmse"]
        lines.append(f"| {row['model']} | {row['horizon']} | {r['vx']:.4f} | {r['vy']:.4f} | {r['yaw_rate']:.4f} |")
    return "\n".join(lines) + "\n"


def learned_form(model: KoopmanModel) -> str:
    """The learned model's form in words for the tables, e.g. "scheduled, mirror-symmetric,
    steer-bilinear, gain anchor" (the options from its training settings)."""
    settings = model.metadata.get("settings", {})
    return ", ".join([model.form] + [words for words, present in (
        ("mirror-symmetric", settings.get("mirror_symmetric")), ("steer-bilinear", model.scheduled_bilinear),
        ("gain anchor", settings.get("gain_anchor"))) if present])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.model_fidelity", description=__doc__.splitlines()[0])
    parser.add_argument("--artifact", type=Path, default=DEFAULT_ARTIFACT, help="the default learned model")
    parser.add_argument("--data", type=Path, default=None,
                        help="data set of the artefact's test runs (default: the artefact's data_dir)")
    parser.add_argument("--out", type=Path, default=Path("results"))
    args = parser.parse_args(argv)
    learned = KoopmanModel.load(args.artifact)
    data_dir = args.data or Path(learned.metadata.get("data_dir", "data/wide"))
    models = {f"learned ({learned_form(learned)})": learned,
              "paper form, nominal data": KoopmanModel.load(PAPER_NOMINAL),
              "linear bicycle (LMPC)": BicyclePredictor(),
              "single track (NMPC)": SingleTrackPredictor()}
    step_rows = step_steer_table(models)
    prediction_rows = prediction_table(models, data_dir, learned.metadata["split"]["test"])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "model_fidelity.md").write_text(markdown(step_rows, prediction_rows, list(models), data_dir))
    (args.out / "model_fidelity.json").write_text(json.dumps(
        {"step_steer": step_rows, "prediction": prediction_rows, "artifact": str(args.artifact),
         "data_dir": str(data_dir)}, indent=1) + "\n")
    print(f"wrote {args.out / 'model_fidelity.md'} and {args.out / 'model_fidelity.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
