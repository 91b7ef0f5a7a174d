"""The robustness grid's cells (``make robustness``, run by ``studies.robustness_grid``):
the axes and controllers of the grid, the manoeuvres, :class:`Cell` and :func:`grid_cells`,
and a cell as a run: its length, its scenario and its plant (mu, mass, steering lag).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from controller.registry import ABLATION_NAMES, CONTROLLER_NAMES
from hil.errors import StudyError
from hil.path_files import DLC_PATH_FILE, SLALOM, SLALOM_PATH_FILE, read_path_csv
from hil.scenario import Scenario, SpeedProfile, StartState
from studies.closed_loop import CONTROL_PERIOD_MS

#: The grid's axes.
MUS = (0.3, 0.5, 0.85, 1.0)
SPEEDS_KMH = (30.0, 50.0, 70.0)
MASS_OFFSETS_KG = (0.0, 300.0)
LAG_FACTORS = (1.0, 3.0)
#: Every controller of the study: the paper's four, then the ablations.
GRID_CONTROLLERS = CONTROLLER_NAMES + ABLATION_NAMES

#: Straight driven after the end of the course (m), to see the controller settle.
SETTLE_M = 20.0
#: Time added to every run (s).
MARGIN_S = 1.0
#: Path the MPC horizons need beyond the last position of a run (m): 30 steps of 25 ms at
#: 70 km/h is 14.6 m.
HORIZON_ROOM_M = 15.0

_KMH = 1.0 / 3.6


@dataclass(frozen=True)
class Manoeuvre:
    """A course of the grid: its path file and where the course ends in X (m)."""

    name: str
    title: str
    path_file: Path
    path_id: int
    course_end_x_m: float


#: The manoeuvres, by name. The double lane change's second tanh has settled (Y within 1 mm
#: of its final value) by X = 90 m; the slalom is back on Y = 0 one cone spacing after the
#: last cone.
MANOEUVRES: dict[str, Manoeuvre] = {
    "dlc": Manoeuvre("dlc", "double lane change", DLC_PATH_FILE, 1, 90.0),
    "slalom": Manoeuvre("slalom", f"slalom, {SLALOM.cone_count} cones "
                        f"{SLALOM.cone_spacing_m:g} m apart", SLALOM_PATH_FILE, 2, SLALOM.exit_x_m),
}


@dataclass(frozen=True)
class Cell:
    """One set of conditions of the grid (a run per controller)."""

    manoeuvre: str
    mu: float
    speed_kmh: float
    mass_offset_kg: float
    lag_factor: float

    @property
    def name(self) -> str:
        """File-name-safe identifier: ``dlc_mu0.85_50kmh_+0kg_lag1``."""
        return (f"{self.manoeuvre}_mu{self.mu:g}_{self.speed_kmh:g}kmh_"
                f"{self.mass_offset_kg:+g}kg_lag{self.lag_factor:g}")

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: ``--quick``: two fast controllers on two cells that touch every axis.
QUICK_CONTROLLERS = ("lmpc", "dkmpc")
QUICK_CELLS = (Cell("dlc", 0.85, 50.0, 0.0, 1.0), Cell("slalom", 0.5, 50.0, 300.0, 3.0))


def grid_cells(manoeuvres: Sequence[str] = tuple(MANOEUVRES)) -> list[Cell]:
    """Every cell of the grid for ``manoeuvres``: 48 per manoeuvre, manoeuvre-major."""
    for name in manoeuvres:
        if name not in MANOEUVRES:
            raise StudyError(f"unknown manoeuvre {name!r}; choose from {', '.join(MANOEUVRES)}")
    return [Cell(*values) for values in
            itertools.product(manoeuvres, MUS, SPEEDS_KMH, MASS_OFFSETS_KG, LAG_FACTORS)]



# ---------------------------------------------------------------------------- a cell's run

def run_duration_s(cell: Cell) -> float:
    """Run length (s): to the end of the course plus ``SETTLE_M`` at the target speed, plus
    ``MARGIN_S``; a whole number of control periods."""
    manoeuvre = MANOEUVRES[cell.manoeuvre]
    seconds = (manoeuvre.course_end_x_m + SETTLE_M) / (cell.speed_kmh * _KMH) + MARGIN_S
    period = CONTROL_PERIOD_MS / 1000.0
    return round(math.ceil(seconds / period) * period, 3)


@functools.lru_cache(maxsize=None)
def _path_end_x_m(path_file: Path) -> float:
    return float(read_path_csv(path_file)[-1, 0])


def cell_scenario(cell: Cell) -> Scenario:
    """The cell as a ``Scenario``: its path, mu and mass offset, a constant target speed
    and a start on the path at X = 0 at that speed.

    Raises:
        StudyError: a path that ends before the run's last position plus the horizons.
    """
    manoeuvre = MANOEUVRES[cell.manoeuvre]
    speed = cell.speed_kmh * _KMH
    duration = run_duration_s(cell)
    needed = speed * duration + HORIZON_ROOM_M
    if _path_end_x_m(manoeuvre.path_file) < needed:
        raise StudyError(f"{cell.name}: {manoeuvre.path_file.name} ends at X = "
                         f"{_path_end_x_m(manoeuvre.path_file):.0f} m; the run needs {needed:.0f} m")
    return Scenario(
        name=cell.name,
        description=f"{manoeuvre.title}, {cell.speed_kmh:g} km/h, mu = {cell.mu:g}, "
                    f"{cell.mass_offset_kg:+g} kg, steering lag x{cell.lag_factor:g}",
        source=manoeuvre.path_file,
        duration_s=duration,
        path_id=manoeuvre.path_id,
        path_file=manoeuvre.path_file,
        mu=cell.mu,
        mass_kg=None,
        mass_offset_kg=cell.mass_offset_kg,
        start=StartState(x_m=0.0, y_m=0.0, yaw_rad=0.0, speed_mps=speed),
        speed_profile=SpeedProfile((0.0,), (speed,)),
    )


def plant_params(cell: Cell) -> Any:
    """The plant's ``VehicleParams`` for the cell: the scenario's mu and mass, the steering
    time constant times ``lag_factor`` (rate limit unchanged)."""
    params = cell_scenario(cell).vehicle_params()
    return dataclasses.replace(params,
                               steer_time_constant=params.steer_time_constant * cell.lag_factor)


def build_plant(cell: Cell) -> tuple[Any, Any]:
    """``(FourWheelVehicle, VehicleCommand)`` with :func:`plant_params`."""
    from models.vehicle import FourWheelVehicle, VehicleCommand

    return FourWheelVehicle(plant_params(cell)), VehicleCommand
