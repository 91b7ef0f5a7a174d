"""The tuning set: manoeuvres the controllers are tuned on, disjoint from the evaluation.

Tables II / III (``studies.paper_tables``, ``studies.run_all``) report the two double lane
changes of ``hil/scenarios/`` (``dlc_high_mu``, ``dlc_low_mu``) on ``hil/paths/dlc.csv``.
The tuning sweep (``studies.tuning_sweep``, ``make tune``) never runs those: it runs the
scenarios written here, smooth random paths at several speeds and friction coefficients.

Each manoeuvre is a path whose curvature along the arc length s is a sum of three random
sinusoids (fixed seed per manoeuvre)::

    kappa(s) = ramp(s) * scale * sum_k a_k sin(2 pi s / lambda_k + phi_k)

with wavelengths lambda_k = v_ref T_k for periods T_k in [1.5, 5] s at the manoeuvre's mean
target speed v_ref (so every speed sees the same steering frequencies), a cosine ramp over
the first 1.5 s of travel (the run starts on a straight, on the path, at speed), and
``scale`` set so that the peak path lateral acceleration v_max^2 max|kappa| over the
distance driven is ``lateral_accel_fraction * mu * g``: from 0.4, well within the tyres'
grip, to 1.3, beyond it (half the set asks for more than the tyres give: controllers meet
that on low-mu roads, and how a controller behaves there differs most between settings). The path starts with 20 m of straight behind X = 0 (as
``dlc.csv`` does, for trackers that look back) and runs 60 m beyond the distance the
fastest target speed covers in the scenario's duration (the MPC horizons stay on it).

Written files (committed; regenerate with ``python -m studies.tuning_set`` or
``make tuning-set``; ``tests/test_tuning_sweep.py`` checks they equal the regenerated ones):

- ``hil/paths/tuning/<name>.csv``: the path, contract format (``x,y,yaw``, 0.25 m apart);
- ``hil/scenarios/tuning/<name>.toml``: the scenario (road mu, speed profile, start on the
  path at X = 0).

``hil.scenario.list_scenarios`` lists only ``hil/scenarios/*.toml``, so these files never
appear among the shipped evaluation scenarios; load them with :func:`tuning_scenarios`.
"""
from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.errors import ScenarioError
from hil.path_files import PATH_DIR, format_path_csv
from hil.scenario import SCENARIO_DIR, Scenario

#: Folders of the tuning set's files (beside, never inside, the evaluation ones).
TUNING_PATH_DIR = PATH_DIR / "tuning"
TUNING_SCENARIO_DIR = SCENARIO_DIR / "tuning"

GRAVITY_MPS2 = 9.81
#: Arc-length spacing of the path points (m); the contract allows at most 0.5 m.
POINT_SPACING_M = 0.25
#: Straight behind the start (m) and margin beyond the distance driven (m).
LEAD_IN_M = 20.0
MARGIN_AHEAD_M = 60.0
#: The curvature ramps in over this much time of travel at the reference speed (s).
RAMP_TIME_S = 1.5
#: Range of the sinusoids' periods at the reference speed (s) and their number.
PERIOD_RANGE_S = (1.5, 5.0)
N_SINUSOIDS = 3


class TuningFiles:
    """The files of a tuning scenario named ``self.name``: its path CSV and scenario TOML."""

    name: str

    @property
    def path_file(self) -> Path:
        return TUNING_PATH_DIR / f"{self.name}.csv"

    @property
    def scenario_file(self) -> Path:
        return TUNING_SCENARIO_DIR / f"{self.name}.toml"


@dataclass(frozen=True)
class TuningManoeuvre(TuningFiles):
    """One tuning scenario: a random smooth path (from ``seed``) driven at a target speed.

    ``speed_times_s`` / ``speeds_kmh``: the piecewise-linear target speed (equal lengths,
    times strictly increasing from 0); ``lateral_accel_fraction``: the path's peak lateral
    acceleration at the fastest target speed, as a fraction of mu g; ``path_id``: the
    PLANNER_REQ.PATH_ID the scenario declares (unused by the evaluation scenarios).
    """

    name: str
    seed: int
    path_id: int
    mu: float
    speed_times_s: tuple[float, ...]
    speeds_kmh: tuple[float, ...]
    lateral_accel_fraction: float
    duration_s: float = 10.0

    @property
    def reference_speed_mps(self) -> float:
        """Mean of the target-speed breakpoints (m/s): sets the path's wavelengths."""
        return float(np.mean(self.speeds_kmh)) / 3.6

    @property
    def max_speed_mps(self) -> float:
        """Fastest target speed (m/s): sets the curvature scale and the path length."""
        return max(self.speeds_kmh) / 3.6



def scenario_body(path_id: int, path_file: Path, mu: float, times_s: Sequence[float],
                  speeds_kmh: Sequence[float]) -> str:
    """The TOML tables of a tuning scenario from ``[path]`` on: the path (relative to the
    scenario file), the road, the nominal vehicle, the start on the path at X = 0 at the first
    target speed, and the speed profile."""
    relative_path = Path("..", "..", "paths", "tuning", path_file.name).as_posix()
    return (
        f"\n[path]\nid = {path_id}\n"
        f'file = "{relative_path}"\n'
        f"\n[road]\nmu = {mu:g}\n"
        f"\n[vehicle]\nmass_offset_kg = 0.0\n"
        f"\n[start]\nx_m = 0.0\ny_m = 0.0\nyaw_rad = 0.0\nspeed_kmh = {speeds_kmh[0]:.1f}\n"
        f"\n[speed_profile]\ntime_s = {_number_list(times_s)}\n"
        f"target_speed_kmh = {_number_list(speeds_kmh)}\n"
    )


def _speeds(kmh: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return (0.0,), (kmh,)


#: The tuning set: within the tyres' grip and beyond it (peak path demand from 0.4 to
#: 1.3 mu g), on high- and low-mu roads, at 40 / 60 / 80 km/h, plus a speed-up and a
#: slow-down. 8 x 10 s of driving; the double lane change is not in it.
TUNING_SET: tuple[TuningManoeuvre, ...] = (
    TuningManoeuvre("tuning_40kmh_mu085", 101, 10, 0.85, *_speeds(40.0), 0.6),
    TuningManoeuvre("tuning_60kmh_mu085", 102, 11, 0.85, *_speeds(60.0), 1.2),
    TuningManoeuvre("tuning_80kmh_mu085", 103, 12, 0.85, *_speeds(80.0), 0.4),
    TuningManoeuvre("tuning_40kmh_mu04", 104, 13, 0.4, *_speeds(40.0), 1.3),
    TuningManoeuvre("tuning_60kmh_mu04", 105, 14, 0.4, *_speeds(60.0), 1.1),
    TuningManoeuvre("tuning_80kmh_mu03", 106, 15, 0.3, *_speeds(80.0), 0.9),
    TuningManoeuvre("tuning_speedup_mu06", 107, 16, 0.6, (0.0, 2.0, 8.0), (40.0, 40.0, 70.0), 1.0),
    TuningManoeuvre("tuning_slowdown_mu04", 108, 17, 0.4, (0.0, 2.0, 7.0), (70.0, 70.0, 45.0), 1.3),
)


def path_curvature(manoeuvre: TuningManoeuvre, arc_length: np.ndarray) -> np.ndarray:
    """Curvature (1/m) of the manoeuvre's path at arc lengths ``arc_length`` (m), shape
    (n,) -> (n,); zero behind the start (s < 0). See the module docstring."""
    rng = np.random.default_rng(manoeuvre.seed)
    periods = rng.uniform(*PERIOD_RANGE_S, size=N_SINUSOIDS)
    amplitudes = rng.uniform(0.5, 1.0, size=N_SINUSOIDS)
    phases = rng.uniform(0.0, 2.0 * math.pi, size=N_SINUSOIDS)
    wavelengths = manoeuvre.reference_speed_mps * periods
    s = np.asarray(arc_length, dtype=float)
    shape = np.sum(amplitudes[:, None] * np.sin(2.0 * math.pi * s[None, :] / wavelengths[:, None]
                                                  + phases[:, None]), axis=0)
    ramp_length = manoeuvre.reference_speed_mps * RAMP_TIME_S
    ramp = np.where(s <= 0.0, 0.0,
                    np.where(s >= ramp_length, 1.0,
                             0.5 * (1.0 - np.cos(math.pi * np.clip(s, 0.0, ramp_length) / ramp_length))))
    unscaled = ramp * shape
    # The peak over the part the run drives (the margin beyond only feeds the horizons).
    driven = s <= manoeuvre.max_speed_mps * manoeuvre.duration_s
    peak = float(np.max(np.abs(unscaled[driven]), initial=0.0))
    if peak == 0.0:
        raise ScenarioError(f"{manoeuvre.name}: seed {manoeuvre.seed} gives a straight path")
    peak_curvature = (manoeuvre.lateral_accel_fraction * manoeuvre.mu * GRAVITY_MPS2
                      / manoeuvre.max_speed_mps ** 2)
    return unscaled * (peak_curvature / peak)


def path_points(manoeuvre: TuningManoeuvre) -> np.ndarray:
    """The manoeuvre's path, ``[x, y, yaw]`` of shape (n, 3), points ``POINT_SPACING_M``
    apart along the arc, starting ``LEAD_IN_M`` behind the origin with the origin, heading
    +X, on it. Heading and position by trapezoidal integration of the curvature."""
    length_ahead = manoeuvre.max_speed_mps * manoeuvre.duration_s + MARGIN_AHEAD_M
    n_behind = int(round(LEAD_IN_M / POINT_SPACING_M))
    n_ahead = int(math.ceil(length_ahead / POINT_SPACING_M))
    s = POINT_SPACING_M * np.arange(-n_behind, n_ahead + 1)
    kappa = path_curvature(manoeuvre, s)
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * POINT_SPACING_M)])
    yaw -= yaw[n_behind]  # heading 0 at the origin (it is 0 on the whole lead-in anyway)
    dx = 0.5 * (np.cos(yaw[1:]) + np.cos(yaw[:-1])) * POINT_SPACING_M
    dy = 0.5 * (np.sin(yaw[1:]) + np.sin(yaw[:-1])) * POINT_SPACING_M
    x = np.concatenate([[0.0], np.cumsum(dx)])
    y = np.concatenate([[0.0], np.cumsum(dy)])
    x -= x[n_behind]
    y -= y[n_behind]
    return np.column_stack([x, y, yaw])


def _number_list(values: Sequence[float]) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def scenario_text(manoeuvre: TuningManoeuvre) -> str:
    """The scenario TOML of ``manoeuvre`` (``hil.scenario`` format; its path file relative
    to the scenario file)."""
    speeds = manoeuvre.speeds_kmh
    speed_words = (f"{speeds[0]:g} km/h" if len(set(speeds)) == 1
                   else " -> ".join(f"{v:g}" for v in speeds) + " km/h")
    return (
        f"# Tuning set (make tune), never an evaluation scenario. Generated by\n"
        f"# `python -m studies.tuning_set` (make tuning-set): edit studies/tuning_set.py, not this file.\n"
        f'name = "{manoeuvre.name}"\n'
        f'description = "Tuning set: smooth random path (seed {manoeuvre.seed}), {speed_words}, '
        f'mu = {manoeuvre.mu:g}, peak path lateral acceleration {manoeuvre.lateral_accel_fraction:g} mu g"\n'
        f"duration_s = {manoeuvre.duration_s:.1f}\n"
        + scenario_body(manoeuvre.path_id, manoeuvre.path_file, manoeuvre.mu, manoeuvre.speed_times_s, speeds)
    )


def write_tuning_set(manoeuvres: Sequence[TuningManoeuvre] = TUNING_SET) -> list[Path]:
    """Write every manoeuvre's path CSV and scenario TOML; returns the files written."""
    TUNING_PATH_DIR.mkdir(parents=True, exist_ok=True)
    TUNING_SCENARIO_DIR.mkdir(parents=True, exist_ok=True)
    written = []
    for manoeuvre in manoeuvres:
        manoeuvre.path_file.write_text(format_path_csv(path_points(manoeuvre)), encoding="ascii")
        manoeuvre.scenario_file.write_text(scenario_text(manoeuvre), encoding="utf-8")
        written += [manoeuvre.path_file, manoeuvre.scenario_file]
    return written


def tuning_scenarios(names: Sequence[str] | None = None) -> list[Scenario]:
    """The committed tuning scenarios (``hil/scenarios/tuning/``), all or those named, in
    ``TUNING_SET`` order. Raises ScenarioError for an unknown name or a missing file
    (run ``python -m studies.tuning_set``)."""
    by_name = {m.name: m for m in TUNING_SET}
    chosen = list(by_name) if names is None else list(names)
    unknown = [n for n in chosen if n not in by_name]
    if unknown:
        raise ScenarioError(f"unknown tuning scenario(s) {unknown}; choose from {', '.join(by_name)}")
    scenarios = []
    for name in chosen:
        file = by_name[name].scenario_file
        if not file.is_file():
            raise ScenarioError(f"{file}: missing; write the tuning set with `python -m studies.tuning_set`")
        scenarios.append(Scenario.load(file))
    return scenarios


def main(argv: list[str] | None = None) -> int:
    """CLI: write the tuning set's paths and scenarios."""
    parser = argparse.ArgumentParser(prog="python -m studies.tuning_set",
                                     description=__doc__.splitlines()[0])
    parser.parse_args(argv)
    try:
        written = write_tuning_set()
    except (ScenarioError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for manoeuvre in TUNING_SET:
        points = path_points(manoeuvre)
        print(f"{manoeuvre.name}: {len(points)} points, "
              f"{manoeuvre.path_file.relative_to(PATH_DIR.parent.parent)}")
    print(f"wrote {len(written)} files under {TUNING_PATH_DIR.parent.parent.name}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
