"""Data set generator: ``python -m models.data generate --out DIR --hours H --seed S``.

Drives ``VehicleBatch`` through many runs at once and writes one CSV per run plus
``manifest.json`` (seed, profile, parameters, content hash, list of runs with their mu),
then an empty ``READY`` file once everything is on disk.

Two profiles (``--profile``, ``PROFILES``): ``nominal`` (the paper's set-up, used for Fig. 7:
nominal mass and mu, 5-30 m/s) and ``wide`` (the range the controller meets: 3-35 m/s,
mu drawn per run in [0.3, 1.0], more segments at and beyond the tyres' limit, steering up
to the actuator limit; the default artefact's data, ``make train``).

Each run (``run_duration`` s, sampled at Ts = 0.025 s) is a chain of segments of 4-12 s.
Every segment draws
- a steering shape: step, ramp, sine, chirp, random smooth (low-pass filtered noise),
  or straight; its amplitude is a lateral acceleration level (nominal: 70 % of segments up
  to 0.6 mu g, 30 % between 0.6 and 1.0 mu g: near and at the handling limit; wide: 40 %
  between 0.6 and 1.3 mu g, i.e. into saturation), turned into
  a wheel angle for the current speed with the steady-state bicycle relation
  delta = a_y (L / vx^2 + K_us), so the same level means the same severity at any speed;
- a longitudinal mode: speed hold with a P controller to a target speed in the profile's
  range (which gives accelerating and decelerating phases), coasting (zero torque) or
  braking (constant negative torque), with guards keeping the speed about 1 m/s inside it.

The recorded ``torque`` and ``steer`` are the COMMANDS (DRIVE_TORQUE_CMD, STEER_ANGLE_CMD,
held for one Ts), because the MPC chooses commands; the actuators' short lags are part of
what the learned model sees. ``steer_measured`` and ``torque_measured`` (actuator outputs)
are extra columns. A run is cut where the car leaves the envelope a [vx, vy, r] model is
for (spin: |vy| > 0.3 vx or |r| > 1.5 rad/s, or vx < 2 m/s); the cut is in the manifest.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
import time as wallclock
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.dataset import DEFAULT_DATASET_DIR, DEFAULT_TS, RUN_COLUMNS, Run, write_run_csv
from models.errors import ModelError
from models.tyre import cornering_stiffness
from models.vehicle import POS_X, POS_Y, STEER, TORQUE, VX, VY, YAW, YAW_RATE, PlantModel, VehicleBatch
from models.vehicle_params import VehicleParams, load_vehicle_params, params_as_dict

#: Default size: 2 h of driving in 160 runs of 45 s.
DEFAULT_HOURS = 2.0
DEFAULT_RUN_DURATION = 45.0
GENERATOR_VERSION = 1
EXTRA_COLUMNS = ("steer_measured", "torque_measured")

STEER_SHAPES = ("step", "ramp", "sine", "chirp", "random", "straight")
# Shares of steering shapes and longitudinal modes among segments.
STEER_SHAPE_WEIGHTS = (0.18, 0.14, 0.2, 0.16, 0.24, 0.08)
LONG_MODES = ("hold", "coast", "brake")
LONG_MODE_WEIGHTS = (0.6, 0.2, 0.2)

#: P gain of the speed-hold controller (1/s) and the target speed rate limit (m/s^2).
SPEED_GAIN = 0.8
TARGET_RATE = 2.5


def speed_hold_torque(params: VehicleParams, drag_factor: float, vx: Any, target: Any) -> Any:
    """Drive torque (N m) of the speed-hold P controller: the driving resistance at ``vx``
    plus SPEED_GAIN times the speed error, as a force at the wheel radius. ``vx`` and
    ``target`` (m/s) are floats or arrays of one shape; ``drag_factor`` is the plant's."""
    resistance = drag_factor * vx * abs(vx) + params.rolling_resistance * params.mass * params.gravity
    return params.radius * (params.mass * SPEED_GAIN * (target - vx) + resistance)


class GeneratorError(ModelError):
    """Bad generator settings (hours, duration, output directory, profile)."""


@dataclass(frozen=True)
class DataProfile:
    """The operating range a data set covers.

    Speeds in m/s (targets drawn in [speed_min, speed_max], guards 1 m/s outside); mu per
    run uniform in [mu_min, mu_max] (equal bounds: fixed mu); ``limit_share`` of segments
    at lateral levels in [0.6, limit_level_max] mu g, the rest in [0.03, 0.6] mu g.
    """

    speed_min: float
    speed_max: float
    mu_min: float
    mu_max: float
    limit_share: float
    limit_level_max: float

    @property
    def guard_low(self) -> float:
        return self.speed_min - 1.0

    @property
    def guard_high(self) -> float:
        return self.speed_max + 1.0


def profiles(params: VehicleParams) -> dict[str, DataProfile]:
    """The named profiles; ``nominal`` keeps the vehicle file's mu."""
    return {
        "nominal": DataProfile(5.0, 30.0, params.mu, params.mu, 0.3, 1.0),
        "wide": DataProfile(3.0, 35.0, 0.3, 1.0, 0.4, 1.3),
    }


PROFILE_NAMES = ("nominal", "wide")


@dataclass(frozen=True)
class RunPlan:
    """Pre-drawn manoeuvre of one run, sampled on the Ts grid (all arrays (n_samples,)).

    ``steer_shape`` in [-1.2, 1.2] times ``lateral_level`` (m/s^2) is the requested lateral
    acceleration; ``long_mode`` indexes LONG_MODES; ``long_value`` is the target speed
    (hold) or the brake torque (brake, negative).
    """

    initial_speed: float
    mu: float
    steer_shape: np.ndarray
    lateral_level: np.ndarray
    long_mode: np.ndarray
    long_value: np.ndarray
    segments: list[dict]


def _smooth_noise(rng: np.random.Generator, n: int, ts: float, cutoff_hz: float) -> np.ndarray:
    """Zero-mean noise low-passed (two first-order passes) at ``cutoff_hz``, unit peak."""
    white = rng.standard_normal(n + 200)
    alpha = 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * ts)
    out = np.empty_like(white)
    for _ in range(2):
        acc = 0.0
        for k, value in enumerate(white):
            acc += alpha * (value - acc)
            out[k] = acc
        white = out.copy()
    out = out[200:]
    return out / max(np.max(np.abs(out)), 1e-9)


def _steer_shape(rng: np.random.Generator, kind: str, n: int, ts: float) -> tuple[np.ndarray, dict]:
    """Normalised steering shape of one segment, (n,), and its description."""
    t = np.arange(n) * ts
    sign = rng.choice((-1.0, 1.0))
    if kind == "step":
        start = rng.uniform(0.0, 0.4 * n * ts)
        shape = sign * (t >= start)
        return shape, {"start": round(start, 3)}
    if kind == "ramp":
        start = rng.uniform(0.0, 0.3 * n * ts)
        length = rng.uniform(0.5, max(0.6 * n * ts, 0.5))
        shape = sign * np.clip((t - start) / length, 0.0, 1.0)
        return shape, {"start": round(start, 3), "ramp_time": round(length, 3)}
    if kind == "sine":
        freq = math.exp(rng.uniform(math.log(0.1), math.log(1.5)))
        shape = sign * np.sin(2 * math.pi * freq * t)
        return shape, {"freq_hz": round(freq, 4)}
    if kind == "chirp":
        f0, f1 = rng.uniform(0.05, 0.3), rng.uniform(1.0, 2.5)
        phase = 2 * math.pi * (f0 * t + 0.5 * (f1 - f0) / (n * ts) * t * t)
        return sign * np.sin(phase), {"f0_hz": round(f0, 4), "f1_hz": round(f1, 4)}
    if kind == "random":
        cutoff = math.exp(rng.uniform(math.log(0.2), math.log(2.0)))
        return _smooth_noise(rng, n, ts, cutoff) * 1.2, {"cutoff_hz": round(cutoff, 4)}
    return np.zeros(n), {}


def plan_run(rng: np.random.Generator, duration: float, ts: float, params: VehicleParams,
             profile: DataProfile | None = None) -> RunPlan:
    """Draw the manoeuvre of one run (segments of 4-12 s) and its mu from ``rng``."""
    profile = profile if profile is not None else profiles(params)["nominal"]
    mu = float(rng.uniform(profile.mu_min, profile.mu_max)) if profile.mu_max > profile.mu_min else profile.mu_min
    n = int(round(duration / ts))
    steer_shape = np.zeros(n)
    lateral_level = np.zeros(n)
    long_mode = np.zeros(n, dtype=int)
    long_value = np.zeros(n)
    segments: list[dict] = []
    start = 0
    mu_g = mu * params.gravity
    while start < n:
        length = min(n - start, int(round(rng.uniform(4.0, 12.0) / ts)))
        kind = str(rng.choice(STEER_SHAPES, p=STEER_SHAPE_WEIGHTS))
        shape, detail = _steer_shape(rng, kind, length, ts)
        near_limit = bool(rng.random() < profile.limit_share)
        level = mu_g * (rng.uniform(0.6, profile.limit_level_max) if near_limit else rng.uniform(0.03, 0.6))
        mode = int(rng.choice(len(LONG_MODES), p=LONG_MODE_WEIGHTS))
        if LONG_MODES[mode] == "hold":
            value = rng.uniform(profile.speed_min, profile.speed_max)
        elif LONG_MODES[mode] == "brake":
            value = -rng.uniform(300.0, params.max_brake_torque)
        else:
            value = 0.0
        steer_shape[start:start + length] = shape
        lateral_level[start:start + length] = level
        long_mode[start:start + length] = mode
        long_value[start:start + length] = value
        segments.append({"t0": round(start * ts, 3), "duration": round(length * ts, 3),
                         "steer": kind, **detail, "lateral_level": round(level, 3),
                         "near_limit": near_limit, "longitudinal": LONG_MODES[mode],
                         "long_value": round(value, 3)})
        start += length
    return RunPlan(float(rng.uniform(profile.speed_min, profile.speed_max)), mu, steer_shape, lateral_level,
                   long_mode, long_value, segments)


def understeer_gradient(params: VehicleParams) -> float:
    """K_us (rad per m/s^2) of the steady-state bicycle at static loads, for scaling."""
    front_load = params.mass * params.gravity * params.lr / params.wheelbase / 2
    rear_load = params.mass * params.gravity * params.lf / params.wheelbase / 2
    c_front = 2 * float(cornering_stiffness(np.array(front_load), params))
    c_rear = 2 * float(cornering_stiffness(np.array(rear_load), params, params.cornering_stiffness_rear_scale))
    return params.mass / params.wheelbase * (params.lr / c_front - params.lf / c_rear)


class _Commander:
    """Turns the plans into commands at each Ts from the measured speed (vectorised)."""

    def __init__(self, plans: list[RunPlan], params: VehicleParams, ts: float, profile: DataProfile) -> None:
        self.params = params
        self.profile = profile
        self.ts = ts
        self.steer_shape = np.stack([p.steer_shape for p in plans])
        self.lateral_level = np.stack([p.lateral_level for p in plans])
        self.long_mode = np.stack([p.long_mode for p in plans])
        self.long_value = np.stack([p.long_value for p in plans])
        self.target = np.array([p.initial_speed for p in plans])
        self.k_us = understeer_gradient(params)
        self.model = PlantModel(params)
        # Latched guard: once a coast/brake segment reached the low guard, hold speed.
        self.recovering = np.zeros(len(plans), dtype=bool)

    def commands(self, k: int, vx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(steer_cmd, torque_cmd), each (n_runs,), for sample ``k`` at speed ``vx``."""
        p = self.params
        speed = np.maximum(vx, 3.0)
        low, high, floor = self.profile.guard_low, self.profile.guard_high, self.profile.speed_min
        lateral = self.steer_shape[:, k] * self.lateral_level[:, k]
        steer = np.clip(lateral * (p.wheelbase / speed ** 2 + self.k_us), -p.steer_limit, p.steer_limit)

        mode = self.long_mode[:, k]
        if k > 0:
            new_segment = mode != self.long_mode[:, k - 1]
            self.recovering &= ~new_segment
        self.recovering |= (mode != 0) & (vx < low)
        wanted = np.where(mode == 0, self.long_value[:, k], np.maximum(vx, floor + 3.0))
        wanted = np.where(self.recovering, floor + 3.0, wanted)
        step = TARGET_RATE * self.ts
        self.target = np.where(mode == 0, self.target + np.clip(wanted - self.target, -step, step), wanted)
        hold = speed_hold_torque(p, self.model.drag_factor, vx, self.target)
        torque = np.where(mode == 1, 0.0, np.where(mode == 2, self.long_value[:, k], hold))
        torque = np.where(self.recovering, hold, torque)
        torque = np.where(vx > high, -0.5 * p.max_brake_torque, torque)
        torque = np.clip(torque, -p.max_brake_torque, p.max_drive_torque)
        return steer, torque


def simulate_runs(plans: list[RunPlan], params: VehicleParams, ts: float,
                  progress: bool = True, profile: DataProfile | None = None
                  ) -> tuple[list[dict[str, np.ndarray]], list[int]]:
    """Simulate all ``plans`` together (each on its own mu); per-run columns and valid lengths."""
    n_runs = len(plans)
    n_samples = len(plans[0].steer_shape)
    batch = VehicleBatch(params, n_runs, mu=np.array([p.mu for p in plans]))
    batch.reset(np.array([p.initial_speed for p in plans]))
    commander = _Commander(plans, params, ts, profile if profile is not None else profiles(params)["nominal"])
    names = (*RUN_COLUMNS, *EXTRA_COLUMNS)
    record = {name: np.zeros((n_runs, n_samples)) for name in names}
    valid_length = np.full(n_runs, n_samples)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_samples, desc=f"simulating {n_runs} runs", unit="sample", file=sys.stderr,
                   mininterval=2.0)
    for k in range(n_samples):
        s = batch.state
        vx = s[:, VX]
        steer, torque = commander.commands(k, vx)
        left_envelope = (~np.all(np.isfinite(s), axis=1) | (np.abs(s[:, VY]) > 0.3 * np.abs(vx))
                         | (np.abs(s[:, YAW_RATE]) > 1.5) | (vx < 2.0))
        valid_length = np.where(left_envelope & (valid_length == n_samples), k, valid_length)
        for name, column in (("time", np.full(n_runs, k * ts)), ("vx", vx), ("vy", s[:, VY]),
                             ("yaw_rate", s[:, YAW_RATE]), ("x", s[:, POS_X]), ("y", s[:, POS_Y]),
                             ("yaw", s[:, YAW]), ("torque", torque), ("steer", steer),
                             ("steer_measured", s[:, STEER]), ("torque_measured", s[:, TORQUE])):
            record[name][:, k] = column
        # Runs that left the envelope keep being simulated (harmlessly) but are cut.
        batch.step(steer, torque, ts)
        batch.state = np.where(np.isfinite(batch.state), batch.state, 0.0)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    runs = [{name: record[name][i, :valid_length[i]].copy() for name in names} for i in range(n_runs)]
    return runs, [int(v) for v in valid_length]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def generate_dataset(out_dir: str | Path, hours: float = DEFAULT_HOURS, seed: int = 0,
                     run_duration: float = DEFAULT_RUN_DURATION, ts: float = DEFAULT_TS,
                     params: VehicleParams | None = None, progress: bool = True,
                     min_run_seconds: float = 5.0, profile: str = "nominal") -> dict:
    """Generate the data set of ``profile`` into ``out_dir``; returns the manifest (also written)."""
    if profile not in PROFILE_NAMES:
        raise GeneratorError(f"profile: must be one of {PROFILE_NAMES}, got {profile!r}")
    if not (math.isfinite(hours) and hours > 0):
        raise GeneratorError(f"hours: must be > 0, got {hours!r}")
    if not (math.isfinite(run_duration) and run_duration >= 5.0):
        raise GeneratorError(f"run_duration: must be >= 5 s, got {run_duration!r}")
    params = params if params is not None else load_vehicle_params()
    coverage = profiles(params)[profile]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for stale in (*out.glob("run_*.csv"), out / "manifest.json", out / "READY"):
        stale.unlink(missing_ok=True)
    n_runs = max(1, int(round(hours * 3600.0 / run_duration)))
    rng = np.random.default_rng(seed)
    plans = [plan_run(rng, run_duration, ts, params, coverage) for _ in range(n_runs)]
    started = wallclock.perf_counter()
    runs, lengths = simulate_runs(plans, params, ts, progress, coverage)
    elapsed = wallclock.perf_counter() - started
    entries = []
    for index, (plan, columns, length) in enumerate(zip(plans, runs, lengths)):
        if length * ts < min_run_seconds:
            entries.append({"index": index, "file": None, "dropped": f"left envelope at {length * ts:.2f} s"})
            continue
        path = out / f"run_{index:04d}.csv"
        write_run_csv(path, Run(name=path.stem, columns=columns))
        entries.append({"index": index, "file": path.name, "samples": length,
                        "duration_s": round(length * ts, 3),
                        "cut": length < len(plan.steer_shape),
                        "initial_speed": round(plan.initial_speed, 3), "mu": round(plan.mu, 4),
                        "sha256": _sha256(path), "segments": plan.segments})
    content = hashlib.sha256("".join(e["sha256"] for e in entries if e["file"]).encode()).hexdigest()
    kept = [e for e in entries if e["file"]]
    manifest = {
        "generator": "models.data", "generator_version": GENERATOR_VERSION, "seed": seed,
        "profile": profile, "coverage": dataclasses.asdict(coverage),
        "hours_requested": hours, "run_duration_s": run_duration, "ts": ts,
        "columns": list(RUN_COLUMNS) + list(EXTRA_COLUMNS),
        "inputs": {"torque": "DRIVE_TORQUE_CMD (N m), held for one Ts",
                   "steer": "STEER_ANGLE_CMD (rad), held for one Ts"},
        "yaw": "continuous (not wrapped)",
        "n_runs": len(kept), "n_dropped": len(entries) - len(kept),
        "total_hours": round(sum(e["duration_s"] for e in kept) / 3600.0, 4),
        "content_sha256": content, "simulation_seconds": round(elapsed, 1),
        "params": params_as_dict(params), "runs": entries,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    (out / "READY").write_text(content + "\n")
    return manifest


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m models.data", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="generate a data set of simulated runs")
    gen.add_argument("--out", type=Path, default=DEFAULT_DATASET_DIR, help="output directory")
    gen.add_argument("--hours", type=float, default=DEFAULT_HOURS, help="hours of driving")
    gen.add_argument("--seed", type=int, default=0, help="random seed (deterministic output)")
    gen.add_argument("--run-duration", type=float, default=DEFAULT_RUN_DURATION, help="seconds per run")
    gen.add_argument("--profile", choices=PROFILE_NAMES, default="nominal",
                     help="operating range: nominal (Fig. 7) or wide (3-35 m/s, mu 0.3-1.0, saturation)")
    gen.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        manifest = generate_dataset(args.out, args.hours, args.seed, args.run_duration,
                                    progress=not args.no_progress, profile=args.profile)
    except ModelError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {manifest['n_runs']} runs ({manifest['total_hours']} h, "
          f"{manifest['n_dropped']} dropped) to {args.out} in {manifest['simulation_seconds']} s; "
          f"content sha256 {manifest['content_sha256'][:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
