"""Fig. 7: accuracy and robustness of DK against ESO-DK (paper Sec. IV-A).

A drive starting at 40 km/h with mixed steering and speed changes is run on the four-wheel
plant (``models.vehicle``) under three conditions: (a) nominal (1648 kg, mu 0.85), (b) mu
0.55, (c) mass + 200 kg. The deep Koopman model was trained on nominal conditions only.
At every sample k both predictors start from the measured state x[k] and the known inputs
u[k..k+H-1]:

- DK:      z[k+i+1|k] = A z[k+i|k] + B u[k+i] + offset
- ESO-DK:  the same plus w_hat, the ESO estimate after seeing x[0..k] (eq. 13), held over
           the horizon as eq. 15 does.

Outputs (``make fig7``): ``results/fig7_<case>.png`` (true vs DK vs ESO-DK one-step
predictions of Vx, Vy, yaw rate), ``results/fig7_rmse.md`` (one-step and 10-step RMSE per
condition and state, and the improvement), ``results/fig7_gain_sweep.md`` (RMSE against
the observer pole, the basis of the gain choice). The simulated drives are cached in
``results/fig7_drives.npz`` (keyed by the drive and plant settings).

CLI: ``python -m studies.fig7 [--artifact PATH] [--pole P] [--out DIR] [--resimulate]``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from models.errors import ModelError
from models.eso import EsoParams, design_gains
from models.eso_dk import EsoDkPredictor, rollout_lifted
from models.eso_dk import observer_params as model_observer_params
from models.koopman import ARTIFACT_DIR, KoopmanModel

#: Fig. 7 keeps, as in the paper, a model trained on nominal conditions only: the paper's
#: linear form on the nominal data set (the default artefact before the scheduled form).
PAPER_NOMINAL_ARTIFACT = ARTIFACT_DIR / "dk_paper_nominal.npz"
from models import tyre as tyre_module
from models import vehicle as vehicle_module
from models.vehicle import VehicleBatch
from models.vehicle_params import VehicleParams, load_vehicle_params

TS = 0.025
KMH = 1.0 / 3.6
STATE_LABELS = ("Vx (m/s)", "Vy (m/s)", "yaw rate (rad/s)")
STATE_KEYS = ("vx", "vy", "yaw_rate")
#: Multi-step horizon of the table (10 steps = 0.25 s).
HORIZON = 10
#: Default observer pole (both error poles of eq. 24); chosen from the gain sweep, see
#: docs/readme/50-eso.md.
DEFAULT_POLE = 0.5
#: VEH_DYN signal resolutions [VX, VY, YAW_RATE] of the CAN contract (m/s, m/s, rad/s).
CAN_RESOLUTION = np.array([0.01, 0.001, 0.0001])
#: Poles of the gain sweep.
SWEEP_POLES = (0.0, 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


@dataclass(frozen=True)
class Condition:
    """One column of Fig. 7: a name and the plant overrides."""

    key: str
    title: str
    mu: float
    mass: float


CONDITIONS = (
    Condition("a_nominal", "(a) 1648 kg, mu 0.85 (nominal)", 0.85, 1648.0),
    Condition("b_low_mu", "(b) 1648 kg, mu 0.55", 0.55, 1648.0),
    Condition("c_mass", "(c) 1848 kg, mu 0.85", 0.85, 1848.0),
)


@dataclass(frozen=True)
class DriveSettings:
    """The test drive: duration, start speed, seed of the manoeuvre sequence."""

    duration_s: float = 60.0
    start_speed: float = 40.0 * KMH
    seed: int = 7
    #: Speed P controller gain (N m per m/s) of the decoupled structure (Fig. 4).
    speed_gain: float = 400.0
    #: Range of the steady-state lateral acceleration the manoeuvres ask for (m/s^2):
    #: up to ~60 % of the grip limit at mu 0.85, up to ~95 % at mu 0.55.
    min_lateral_accel: float = 2.0
    max_lateral_accel: float = 5.0
    max_steer: float = 0.15


#: Manoeuvre sequence of the drive (parameters drawn from the seeded generator).
MANOEUVRES = ("corner", "sine", "lane_change", "slalom", "corner", "straight", "sine", "lane_change", "slalom")


def _manoeuvre_shape(rng: np.random.Generator, kind: str, tau: np.ndarray) -> np.ndarray:
    """Normalised steering shape in [-1, 1] of one manoeuvre over local time tau (n,)."""
    sign = rng.choice((-1.0, 1.0))
    if kind == "corner":  # enter in ~1 s, hold, leave in the last second
        ramp = rng.uniform(0.8, 1.5)
        return sign * np.clip(tau / ramp, 0.0, 1.0) * np.clip((tau[-1] - tau) / 1.0, 0.0, 1.0)
    if kind == "sine":
        return sign * np.sin(2 * np.pi * rng.uniform(0.15, 0.6) * tau)
    if kind == "lane_change":
        period = rng.uniform(2.5, 4.0)
        return sign * np.sin(2 * np.pi * tau / period) * (tau < period)
    if kind == "slalom":
        return sign * np.sin(2 * np.pi * rng.uniform(0.5, 0.8) * tau)
    return np.zeros_like(tau)


def drive_profile(settings: DriveSettings, params: VehicleParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Target speed (n,) m/s and front-wheel steer command (n,) rad of the drive.

    3 s straight at 40 km/h, then 5-9 s manoeuvres (corner, sine 0.15-0.6 Hz, lane change,
    slalom 0.5-0.8 Hz, straight), each asking for a steady-state lateral acceleration in
    [min, max]_lateral_accel, turned into a wheel angle with the nominal car's
    steady-state bicycle relation delta = a_y (L / v^2 + K_us) at the target speed; speed
    targets 30-60 km/h with 10 s ramps. The same commands drive all three conditions, so
    only the plant differs. ``params``: the nominal car (default ``models/vehicle.toml``).
    """
    from models.data import understeer_gradient  # the data generator's scaling, same formula

    params = params if params is not None else load_vehicle_params()
    rng = np.random.default_rng(settings.seed)
    n = int(round(settings.duration_s / TS))
    t = np.arange(n) * TS
    levels = np.array([40.0, 50.0, 35.0, 55.0, 30.0, 60.0, 40.0]) * KMH
    target_speed = np.interp(t, np.linspace(0.0, t[-1], levels.size), levels)
    lateral = np.zeros(n)
    start, index = int(3.0 / TS), 0
    while start < n:
        stop = min(n, start + int(rng.uniform(5.0, 9.0) / TS))
        level = rng.uniform(settings.min_lateral_accel, settings.max_lateral_accel)
        lateral[start:stop] = level * _manoeuvre_shape(rng, MANOEUVRES[index % len(MANOEUVRES)], t[start:stop] - t[start])
        index += 1
        start = stop
    # A driver, not a square wave: 0.2 s moving average over the manoeuvre edges.
    width = int(0.2 / TS)
    lateral = np.convolve(lateral, np.ones(width) / width, mode="same")
    gain = params.wheelbase / target_speed**2 + understeer_gradient(params)
    steer = np.clip(lateral * gain, -settings.max_steer, settings.max_steer)
    return target_speed, steer


def _drive_torque(params: VehicleParams, vx: np.ndarray, target: float, gain: float) -> np.ndarray:
    """Speed P control plus drag / rolling feed-forward: total torque (N m), (batch,)."""
    drag = 0.5 * params.air_density * params.drag_coefficient * params.frontal_area * vx**2
    rolling = params.rolling_resistance * params.mass * params.gravity
    return gain * (target - vx) + (drag + rolling) * params.radius


def simulate_drive(
    params: VehicleParams, mus: np.ndarray, settings: DriveSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Run the drive on ``len(mus)`` plants with ``params`` at once.

    Returns states (batch, n + 1, 3) [vx, vy, yaw_rate] and applied commands
    (batch, n, 2) [torque, steer]; command k is held over [t_k, t_k+1).
    """
    target_speed, steer = drive_profile(settings)
    n = steer.size
    plants = VehicleBatch(params, len(mus), mu=np.asarray(mus, dtype=float))
    plants.reset(np.full(len(mus), settings.start_speed))
    states = np.empty((len(mus), n + 1, 3))
    inputs = np.empty((len(mus), n, 2))
    states[:, 0] = plants.state[:, :3]
    for k in range(n):
        torque = _drive_torque(params, plants.state[:, 0], target_speed[k], settings.speed_gain)
        torque = np.clip(torque, -params.max_brake_torque, params.max_drive_torque)
        steer_cmd = np.full(len(mus), steer[k])
        plants.step(steer_cmd, torque, TS)
        if not np.all(np.isfinite(plants.state)):
            raise ModelError(f"fig7 drive diverged at t = {k * TS:.2f} s")
        inputs[:, k, 0] = torque
        inputs[:, k, 1] = steer_cmd
        states[:, k + 1] = plants.state[:, :3]
    return states, inputs


def _cache_key(settings: DriveSettings) -> str:
    """Hash of everything the drives depend on: the commands, plant parameters and code."""
    digest = hashlib.sha256()
    nominal = load_vehicle_params()
    digest.update(json.dumps({"drive": asdict(settings), "plant": asdict(nominal),
                              "conditions": [asdict(c) for c in CONDITIONS]}, sort_keys=True).encode())
    for array in drive_profile(settings, nominal):
        digest.update(array.tobytes())
    for module in (vehicle_module, tyre_module):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:16]


def load_or_simulate(settings: DriveSettings, cache: Path, resimulate: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """States (n + 1, 3) and inputs (n, 2) per condition key, from the cache when it matches."""
    key = _cache_key(settings)
    if cache.is_file() and not resimulate:
        with np.load(cache) as stored:
            if str(stored["key"]) == key:
                return {c.key: (stored[f"{c.key}_states"], stored[f"{c.key}_inputs"]) for c in CONDITIONS}
    drives: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    # Conditions that share the plant parameters (all but mu) run as one batch.
    by_mass: dict[float, list[Condition]] = {}
    for condition in CONDITIONS:
        by_mass.setdefault(condition.mass, []).append(condition)
    for mass, group in by_mass.items():
        print(f"simulating {', '.join(c.key for c in group)} ({settings.duration_s:.0f} s drive)", flush=True)
        params = load_vehicle_params(mass=mass)
        states, inputs = simulate_drive(params, np.array([c.mu for c in group]), settings)
        for i, condition in enumerate(group):
            drives[condition.key] = (states[i], inputs[i])
    cache.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"{k}_{part}": v[j] for k, v in drives.items() for j, part in enumerate(("states", "inputs"))}
    np.savez(cache, key=np.array(key), **arrays)
    return drives


@dataclass(frozen=True)
class Predictions:
    """Predictions along one drive, aligned with the truth.

    ``truth`` (n, 3): x[k+1]; ``one_step_*`` (n, 3): x[k+1|k]; ``multi_*``
    (n - H + 1, H, 3): x[k+1..k+H|k]; ``multi_truth`` the same shape.
    """

    truth: np.ndarray
    one_step_dk: np.ndarray
    one_step_eso: np.ndarray
    multi_truth: np.ndarray
    multi_dk: np.ndarray
    multi_eso: np.ndarray


def quantise_like_can(states: np.ndarray) -> np.ndarray:
    """States (..., 3) rounded to the VEH_DYN resolutions: what the ECU receives."""
    return np.round(states / CAN_RESOLUTION) * CAN_RESOLUTION


def predict_along(
    model: KoopmanModel,
    params: EsoParams,
    states: np.ndarray,
    inputs: np.ndarray,
    horizon: int = HORIZON,
    measured: np.ndarray | None = None,
) -> Predictions:
    """DK and ESO-DK predictions from every sample; states (n + 1, 3), inputs (n, 2).

    ``measured`` (n + 1, 3), default ``states``: what the predictors see (e.g. CAN-quantised
    states); the errors are always taken against the true ``states``.
    """
    n = inputs.shape[0]
    truth = states
    states = truth if measured is None else measured
    predictor = EsoDkPredictor(model, params)
    predictor.reset(states[0])
    disturbances = np.empty((n, model.n_z))
    for k in range(n):
        # Causal: w_hat used from x[k] has seen x[0..k] only (u[k] does not enter it).
        predictor.observe(states[k], inputs[k])
        disturbances[k] = predictor.disturbance_estimate
    starts = n - horizon + 1
    windows = np.lib.stride_tricks.sliding_window_view(inputs, horizon, axis=0)  # (starts, 2, H)
    windows = np.ascontiguousarray(np.moveaxis(windows, -1, 1))  # (starts, H, 2)
    lifted = model.lift(states[:starts])
    c_t = model.C_P.T
    multi_dk = rollout_lifted(model, lifted, windows) @ c_t
    multi_eso = rollout_lifted(model, lifted, windows, disturbances[:starts]) @ c_t
    multi_truth = np.lib.stride_tricks.sliding_window_view(truth[1:], horizon, axis=0)
    multi_truth = np.moveaxis(multi_truth, -1, 1)
    lifted_all = model.lift(states[:n])
    one_dk = rollout_lifted(model, lifted_all, inputs[:, None, :])[:, 0] @ c_t
    one_eso = rollout_lifted(model, lifted_all, inputs[:, None, :], disturbances)[:, 0] @ c_t
    return Predictions(truth[1:], one_dk, one_eso, multi_truth, multi_dk, multi_eso)


def rmse(error: np.ndarray) -> np.ndarray:
    """Root mean square over all but the last axis: (..., 3) -> (3,)."""
    return np.sqrt(np.mean(error.reshape(-1, error.shape[-1]) ** 2, axis=0))


def prediction_rmse(p: Predictions) -> dict[str, np.ndarray]:
    """RMSE (3,) per state for one-step and H-step (the H-th step of each window) predictions."""
    return {
        "one_dk": rmse(p.one_step_dk - p.truth),
        "one_eso": rmse(p.one_step_eso - p.truth),
        "multi_dk": rmse(p.multi_dk[:, -1] - p.multi_truth[:, -1]),
        "multi_eso": rmse(p.multi_eso[:, -1] - p.multi_truth[:, -1]),
    }


def observer_params(model: KoopmanModel, pole: float) -> EsoParams:
    """ESO on the model's A, B, offset with matrix gains placing both error poles at ``pole``."""
    gains = design_gains(model.A, pole)
    return model_observer_params(model, gains.beta1, gains.beta2)


def rmse_table(results: dict[str, dict[str, np.ndarray]], heading: str) -> str:
    """Markdown table of one-step and H-step RMSE per condition and state under ``heading``."""
    lines = [
        f"## {heading}",
        "",
        f"| condition | state | 1-step DK | 1-step ESO-DK | 1-step impr. | {HORIZON}-step DK | "
        f"{HORIZON}-step ESO-DK | {HORIZON}-step impr. |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for condition in CONDITIONS:
        r = results[condition.key]
        for i, label in enumerate(STATE_LABELS):
            one = 100.0 * (r["one_dk"][i] - r["one_eso"][i]) / r["one_dk"][i]
            multi = 100.0 * (r["multi_dk"][i] - r["multi_eso"][i]) / r["multi_dk"][i]
            lines.append(
                f"| {condition.title} | {label} | {r['one_dk'][i]:.4f} | {r['one_eso'][i]:.4f} | "
                f"{one:+.1f} % | {r['multi_dk'][i]:.4f} | {r['multi_eso'][i]:.4f} | {multi:+.1f} % |"
            )
    return "\n".join(lines) + "\n"


def table_header(pole: float, artifact: str, duration_s: float) -> str:
    """Title and how to read the tables."""
    bandwidth = "dead-beat" if pole == 0 else f"{-math.log(pole) / (2 * math.pi * TS):.1f} Hz error bandwidth"
    return (
        "# Fig. 7: DK vs ESO-DK prediction RMSE\n\n"
        f"Model `{artifact}` (trained on nominal conditions only), {duration_s:.0f} s drive from 40 km/h "
        f"(`studies/fig7.py`). ESO: matrix gains from `design_gains` with both error poles of eq. 24 at "
        f"{pole} (spectral radius {pole}, {bandwidth}). 1-step: RMSE of x[k+1|k]; {HORIZON}-step: RMSE "
        f"of x[k+{HORIZON}|k] with w_hat held over the horizon (eq. 15). Improvement = (DK - ESO-DK) / DK, "
        "positive = ESO-DK better. Errors always against the true plant state. Generated by `make fig7`.\n\n"
    )


def plot_condition(p: Predictions, condition: Condition, path: Path) -> None:
    """Fig. 7 style: true vs DK vs ESO-DK one-step predictions of the three states (left)
    and the one-step prediction errors (right, where the difference is visible)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = (np.arange(p.truth.shape[0]) + 1) * TS
    fig, axes = plt.subplots(3, 2, figsize=(14, 8), sharex=True)
    for i, label in enumerate(STATE_LABELS):
        ax, err_ax = axes[i]
        ax.plot(t, p.truth[:, i], color="black", lw=1.6, label="true")
        ax.plot(t, p.one_step_dk[:, i], color="tab:blue", lw=1.0, ls="--", label="DK")
        ax.plot(t, p.one_step_eso[:, i], color="tab:red", lw=1.0, ls=":", label="ESO-DK")
        ax.set_ylabel(label)
        err_ax.plot(t, p.one_step_dk[:, i] - p.truth[:, i], color="tab:blue", lw=0.8, label="DK error")
        err_ax.plot(t, p.one_step_eso[:, i] - p.truth[:, i], color="tab:red", lw=0.8, label="ESO-DK error")
        err_ax.set_ylabel(f"error {label}")
        for a in (ax, err_ax):
            a.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", ncol=3)
    axes[0, 1].legend(loc="upper right", ncol=2)
    axes[0, 0].set_title(f"Fig. 7 {condition.title}: one-step predictions")
    axes[0, 1].set_title("one-step prediction error (prediction - true)")
    for a in axes[-1]:
        a.set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def gain_sweep(model: KoopmanModel, drives: dict[str, tuple[np.ndarray, np.ndarray]]) -> str:
    """RMSE (mean over the three conditions) against the observer pole, for exact and
    CAN-quantised measurements: the basis of the gain choice."""
    lines = [
        "# ESO gain sweep (Fig. 7 drives)",
        "",
        "Both error poles of eq. 24 at the value shown (matrix gains from `design_gains`; 0 is "
        "dead-beat). RMSE averaged over the three conditions. `exact`: the predictors see the "
        "plant state; `CAN`: they see it rounded to the VEH_DYN resolutions (0.01 m/s, 0.001 m/s, "
        "0.0001 rad/s), as the ECU does; errors always against the true state. "
        "Generated by `make fig7`.",
        "",
        f"| pole | bandwidth (Hz) | measured | 1-step Vx | 1-step Vy | 1-step r | {HORIZON}-step Vx | "
        f"{HORIZON}-step Vy | {HORIZON}-step r |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    dk_rows: dict[str, np.ndarray] = {}
    for pole in SWEEP_POLES:
        params = observer_params(model, pole)
        bandwidth = "inf" if pole == 0 else f"{-math.log(pole) / (2 * math.pi * TS):.1f}"
        for label, quantise in (("exact", False), ("CAN", True)):
            eso, dk = np.zeros(6), np.zeros(6)
            for states, inputs in drives.values():
                measured = quantise_like_can(states) if quantise else None
                r = prediction_rmse(predict_along(model, params, states, inputs, measured=measured))
                eso += np.concatenate([r["one_eso"], r["multi_eso"]]) / len(drives)
                dk += np.concatenate([r["one_dk"], r["multi_dk"]]) / len(drives)
            dk_rows[label] = dk
            lines.append(f"| {pole} | {bandwidth} | {label} | " + " | ".join(f"{v:.4f}" for v in eso) + " |")
    for label, dk in dk_rows.items():
        lines.append(f"| DK (no ESO) | - | {label} | " + " | ".join(f"{v:.4f}" for v in dk) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.fig7", description=__doc__.splitlines()[0])
    parser.add_argument("--artifact", default=str(PAPER_NOMINAL_ARTIFACT),
                        help="Koopman artefact (.npz); default: the paper's linear form trained on nominal data")
    parser.add_argument("--pole", type=float, default=DEFAULT_POLE, help="observer error pole in [0, 1)")
    parser.add_argument("--out", default="results", help="output directory")
    parser.add_argument("--duration", type=float, default=DriveSettings.duration_s, help="drive length (s)")
    parser.add_argument("--resimulate", action="store_true", help="ignore the cached drives")
    parser.add_argument("--no-sweep", action="store_true", help="skip the gain sweep table")
    args = parser.parse_args(argv)
    try:
        if not 0.0 <= args.pole < 1.0:
            raise ModelError(f"--pole must be in [0, 1), got {args.pole}")
        model = KoopmanModel.load(args.artifact)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        settings = DriveSettings(duration_s=args.duration)
        drives = load_or_simulate(settings, out / "fig7_drives.npz", args.resimulate)
        params = observer_params(model, args.pole)
        exact, quantised = {}, {}
        for condition in CONDITIONS:
            states, inputs = drives[condition.key]
            predictions = predict_along(model, params, states, inputs)
            exact[condition.key] = prediction_rmse(predictions)
            quantised[condition.key] = prediction_rmse(
                predict_along(model, params, states, inputs, measured=quantise_like_can(states)))
            plot_condition(predictions, condition, out / f"fig7_{condition.key}.png")
        table = (table_header(args.pole, Path(args.artifact).name, settings.duration_s)
                 + rmse_table(exact, "Exact plant states (as the paper's simulation)") + "\n"
                 + rmse_table(quantised, "CAN-quantised measurements (as the ECU receives them)"))
        (out / "fig7_rmse.md").write_text(table)
        print(table)
        if not args.no_sweep:
            sweep = gain_sweep(model, drives)
            (out / "fig7_gain_sweep.md").write_text(sweep)
            print(sweep)
    except ModelError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
