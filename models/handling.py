"""Steady-state handling of the plant, and the parameter table for the README.

``python -m models.handling diagram --out results`` drives the plant to steady state
(constant speed held by a P controller on the drive torque, constant steer) over a steer
sweep at 20 m/s and a speed sweep at a small steer angle, for mu 0.85 and 0.5, and writes

- ``handling_lateral_accel.png``: lateral acceleration against steer angle at 20 m/s;
- ``handling_yaw_gain.png``: yaw rate gain r / delta against speed, with the linear
  bicycle's vx / (L + K_us vx^2) for comparison;
- ``handling.json``: the numbers behind both figures.

``python -m models.handling table`` prints the parameter table (Markdown) from
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
STEER_SWEEP = np.linspace(0.002, 0.12, 24)
SPEED_SWEEP = np.linspace(5.0, 35.0, 13)
GAIN_STEER = 0.005
SETTLE_SECONDS = 5.0
_TS = 0.025


def steady_state(params: VehicleParams, mu: float, speeds: np.ndarray, steers: np.ndarray,
                 seconds: float = SETTLE_SECONDS) -> np.ndarray:
    """Final states (n, N_STATE) after ``seconds`` at each (speed, steer) pair held by a
    P speed controller on the torque (the torque also balances the running resistance)."""
    batch = VehicleBatch(params, len(speeds), mu=mu)
    batch.reset(speeds)
    for _ in range(int(round(seconds / _TS))):
        vx = batch.state[:, VX]
        torque = params.radius * params.mass * (speeds - vx) + params.radius * 300.0
        batch.step(steers, torque, _TS)
    return batch.state


def handling_data(params: VehicleParams | None = None) -> dict:
    """Steady-state sweeps for every mu in FRICTIONS (one batch per mu)."""
    params = params if params is not None else load_vehicle_params()
    bicycle = LinearBicycle(nominal_model_params(params))
    result: dict = {"speed_for_steer_sweep": SWEEP_SPEED, "gain_steer": GAIN_STEER,
                    "understeer_gradient_nominal": bicycle.params.understeer_gradient, "mu": {}}
    for mu in FRICTIONS:
        speeds = np.concatenate([np.full(STEER_SWEEP.size, SWEEP_SPEED), SPEED_SWEEP])
        steers = np.concatenate([STEER_SWEEP, np.full(SPEED_SWEEP.size, GAIN_STEER)])
        state = steady_state(params, mu, speeds, steers)
        n = STEER_SWEEP.size
        # A point whose sideslip grew past 0.3 vx has spun: not a steady state.
        spun = np.abs(state[:, VY]) > 0.3 * np.abs(state[:, VX])
        result["mu"][str(mu)] = {
            "steer": STEER_SWEEP.tolist(),
            "lateral_accel": np.where(spun[:n], np.nan, state[:n, ACCEL_Y_FILT]).tolist(),
            "speed": SPEED_SWEEP.tolist(),
            "yaw_rate_gain": np.where(spun[n:], np.nan, state[n:, YAW_RATE] / GAIN_STEER).tolist(),
            "peak_lateral_accel": float(np.nanmax(np.abs(np.where(spun[:n], np.nan, state[:n, ACCEL_Y_FILT])))),
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
    ax.set_title(f"Handling diagram at {data['speed_for_steer_sweep']:.0f} m/s (dotted: mu g)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    lateral = out_dir / "handling_lateral_accel.png"
    fig.tight_layout()
    fig.savefig(lateral, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for mu, curve in data["mu"].items():
        ax.plot(curve["speed"], curve["yaw_rate_gain"], "o-", ms=3, label=f"plant, mu {mu}")
    ax.plot(data["mu"][str(FRICTIONS[0])]["speed"], data["bicycle_yaw_rate_gain"], "k--",
            label="linear bicycle (nominal)")
    ax.set_xlabel("speed (m/s)")
    ax.set_ylabel("yaw rate gain r / delta (1/s)")
    ax.set_title(f"Steady yaw rate gain at delta = {data['gain_steer']} rad")
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
    parser = argparse.ArgumentParser(prog="python -m models.handling", description=__doc__.splitlines()[0])
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
