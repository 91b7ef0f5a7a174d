"""Steady-state handling of the plant, and the parameter table for the README.

``python -m studies.handling diagram --out results`` drives the plant to steady state
(constant speed held by a P controller on the drive torque, constant steer; points that
do not settle are left out) over a steer
sweep at 20 m/s and a speed sweep at a small steer angle, for mu 0.85 and 0.5, and writes

- ``handling_lateral_accel.png``: lateral acceleration against steer angle at 20 m/s;
- ``handling_yaw_gain.png``: yaw rate gain r / delta against speed at two steer angles
  (linear range and 0.03 rad), with the linear bicycle's vx / (L + K_us vx^2);
- ``handling.json``: the numbers behind both figures.

``python -m studies.handling table`` prints the parameter table (Markdown) from
``models/vehicle.toml``, with each value's source comment.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from models.bicycle import LinearBicycle, nominal_model_params
from models.errors import ModelError
from models.vehicle import ACCEL_Y_FILT, VX, VY, YAW_RATE, VehicleBatch
from models.vehicle_params import DEFAULT_PARAMS_PATH, VehicleParams, load_vehicle_params

FRICTIONS = (0.85, 0.5)
SWEEP_SPEED = 20.0
STEER_SWEEP = np.linspace(0.0025, 0.15, 60)
SPEED_SWEEP = np.linspace(5.0, 35.0, 13)
GAIN_STEERS = (0.005, 0.03)
SETTLE_SECONDS = 8.0
_TS = 0.025
#: P gain (1/s) of the speed hold: strong, so the speed stays on target near the limit.
SPEED_GAIN = 4.0


def steady_state(params: VehicleParams, mu: float | np.ndarray, speeds: np.ndarray, steers: np.ndarray,
                 seconds: float = SETTLE_SECONDS) -> tuple[np.ndarray, np.ndarray]:
    """Final states (n, N_STATE) after ``seconds`` at each (speed, steer) pair held by a
    P speed controller on the torque (the torque also balances the running resistance),
    and a mask (n,) of the points that really are steady: speed within 1 m/s of the
    target, yaw rate changed by < 2 % over the last second, no spin (|vy| < 0.3 vx)."""
    batch = VehicleBatch(params, len(speeds), mu=mu)
    batch.reset(speeds)
    n_steps = int(round(seconds / _TS))
    yaw_rate_before = np.zeros(len(speeds))
    for k in range(n_steps):
        if k == n_steps - int(round(1.0 / _TS)):
            yaw_rate_before = batch.state[:, YAW_RATE].copy()
        vx = batch.state[:, VX]
        torque = params.radius * params.mass * SPEED_GAIN * (speeds - vx) + params.radius * 300.0
        batch.step(steers, torque, _TS)
    state = batch.state
    yaw_rate = state[:, YAW_RATE]
    steady = ((np.abs(state[:, VX] - speeds) < 1.0)
              & (np.abs(yaw_rate - yaw_rate_before) <= 0.02 * np.abs(yaw_rate) + 1e-4)
              & (np.abs(state[:, VY]) < 0.3 * np.abs(state[:, VX])))
    return state, steady


def handling_data(params: VehicleParams | None = None) -> dict:
    """Steady-state sweeps for every mu in FRICTIONS (one batch per mu)."""
    params = params if params is not None else load_vehicle_params()
    bicycle = LinearBicycle(nominal_model_params(params))
    result: dict = {"speed_for_steer_sweep": SWEEP_SPEED, "gain_steers": list(GAIN_STEERS),
                    "understeer_gradient_nominal": bicycle.params.understeer_gradient, "mu": {}}
    # One batch for every mu (each row has its own friction).
    n = STEER_SWEEP.size
    speeds_one = np.concatenate([np.full(n, SWEEP_SPEED), np.tile(SPEED_SWEEP, len(GAIN_STEERS))])
    steers_one = np.concatenate([STEER_SWEEP, np.repeat(GAIN_STEERS, SPEED_SWEEP.size)])
    per_mu = speeds_one.size
    mus = np.repeat(np.array(FRICTIONS), per_mu)
    states, steady = steady_state(params, mus, np.tile(speeds_one, len(FRICTIONS)),
                                  np.tile(steers_one, len(FRICTIONS)))
    for index, mu in enumerate(FRICTIONS):
        rows = slice(index * per_mu, (index + 1) * per_mu)
        state, ok = states[rows], steady[rows]
        lateral = np.where(ok[:n], state[:n, ACCEL_Y_FILT], np.nan)
        gains = np.where(ok[n:], state[n:, YAW_RATE] / steers_one[n:], np.nan)
        result["mu"][str(mu)] = {
            "steer": STEER_SWEEP.tolist(),
            "lateral_accel": lateral.tolist(),
            "speed": SPEED_SWEEP.tolist(),
            "yaw_rate_gain": {str(d): gains[i * SPEED_SWEEP.size:(i + 1) * SPEED_SWEEP.size].tolist()
                              for i, d in enumerate(GAIN_STEERS)},
            "peak_lateral_accel": float(np.nanmax(np.abs(lateral))),
        }
    result["bicycle_yaw_rate_gain"] = [bicycle.steady_state_yaw_rate_gain(v) for v in SPEED_SWEEP]
    return result


def plot_handling(data: dict, out_dir: Path) -> list[Path]:
    """Write the two PNGs into ``out_dir``; returns their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    for mu, curve in data["mu"].items():
        ax.plot(np.degrees(curve["steer"]), curve["lateral_accel"], "o-", ms=3, label=f"plant, mu {mu}")
        ax.axhline(float(mu) * 9.81, ls=":", lw=1, color="grey")
    ax.set_xlabel("front wheel angle (deg)")
    ax.set_ylabel("steady lateral acceleration (m/s$^2$)")
    ax.set_title(f"Handling diagram at {data['speed_for_steer_sweep']:.0f} m/s (dotted: mu g; "
                 "gaps: no steady state)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend()
    lateral = out_dir / "handling_lateral_accel.png"
    fig.tight_layout()
    fig.savefig(lateral, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for (mu, curve), color in zip(data["mu"].items(), ("C0", "C1")):
        for (steer, gains), style in zip(curve["yaw_rate_gain"].items(), ("o-", "s:")):
            ax.plot(curve["speed"], gains, style, ms=3, color=color, label=f"plant, mu {mu}, delta {steer} rad")
    ax.plot(data["mu"][str(FRICTIONS[0])]["speed"], data["bicycle_yaw_rate_gain"], "k--",
            label="linear bicycle (nominal)")
    ax.set_xlabel("speed (m/s)")
    ax.set_ylabel("yaw rate gain r / delta (1/s)")
    ax.set_title("Steady yaw rate gain (missing points: no steady state)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    gain = out_dir / "handling_yaw_gain.png"
    fig.tight_layout()
    fig.savefig(gain, dpi=120)
    plt.close(fig)
    return [lateral, gain]


def parameter_table(path: Path = DEFAULT_PARAMS_PATH) -> str:
    """Markdown table of every parameter in the TOML with its section and source comment.

    A comment block applies to the keys that follow it until the next comment block.
    """
    load_vehicle_params(path)  # validate first: a table of a broken file is no use
    lines = ["| section | parameter | value | source / reason |", "|---|---|---|---|"]
    section, comment, pending, shown = "", "", [], None
    for raw in Path(path).read_text().splitlines():
        text = raw.strip()
        if text.startswith("#"):
            if not pending:
                comment = ""
            pending.append(text.lstrip("# ").strip())
            continue
        if text.startswith("[") and text.endswith("]"):
            section, comment, pending, shown = text[1:-1], "", [], None
            continue
        if "=" in text:
            if pending:
                comment = " ".join(pending)
                pending = []
            key, value = (part.strip() for part in text.split("=", 1))
            source = comment.replace("|", "/")
            lines.append(f"| {section} | `{key}` | {value} | {'(as above)' if source == shown else source} |")
            shown = source
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.handling", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)
    diagram = sub.add_parser("diagram", help="steady-state handling diagram PNGs")
    diagram.add_argument("--out", type=Path, default=Path("results"), help="output directory")
    sub.add_parser("table", help="print the parameter table (Markdown)")
    args = parser.parse_args(argv)
    try:
        if args.command == "table":
            print(parameter_table())
            return 0
        data = handling_data()
        paths = plot_handling(data, args.out)
        (args.out / "handling.json").write_text(json.dumps(data, indent=1))
    except ModelError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"understeer gradient (nominal bicycle) {data['understeer_gradient_nominal']:.5f} rad/(m/s^2)")
    for mu, curve in data["mu"].items():
        print(f"mu {mu}: peak steady lateral acceleration {curve['peak_lateral_accel']:.2f} m/s^2 "
              f"({curve['peak_lateral_accel'] / (float(mu) * 9.81):.3f} mu g)")
    print("wrote " + ", ".join(str(p) for p in paths) + f", {args.out / 'handling.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
