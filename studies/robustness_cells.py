"""The robustness grid's cells (``make robustness``): the manoeuvres, the study's controllers
and :class:`Cell`, one set of conditions the report groups runs by.

The grid itself is a campaign grid file, ``studies/campaign/grids/robustness_closed_loop.toml``
(axes, run length, the ``closed_loop`` runner); the campaign engine (``studies.campaign``)
builds each cell's scenario and plant and runs it. This module names what the report needs
to read the campaign's rows back as cells.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from controller.registry import ABLATION_NAMES, CONTROLLER_NAMES
from hil.path_files import SLALOM

#: The campaign grid of ``make robustness`` and of its smoke subset.
GRID = "robustness_closed_loop"
SMOKE_GRID = "robustness_closed_loop_smoke"
#: Every controller of the study: the paper's four, then the ablations.
GRID_CONTROLLERS = CONTROLLER_NAMES + ABLATION_NAMES
#: Straight driven after the end of the course (m), to see the controller settle, and the
#: time added to every run (s): the grid file's ``[run]`` distances and margin are these
#: (tests/test_robustness_grid.py checks it).
SETTLE_M = 20.0
MARGIN_S = 1.0


@dataclass(frozen=True)
class Manoeuvre:
    """A course of the grid: its scenario (``hil/scenarios/NAME.toml``) and where the course
    ends in X (m)."""

    name: str
    title: str
    scenario: str
    course_end_x_m: float


#: The manoeuvres, by name. The double lane change's second tanh has settled (Y within 1 mm
#: of its final value) by X = 90 m; the slalom is back on Y = 0 one cone spacing after the
#: last cone.
MANOEUVRES: dict[str, Manoeuvre] = {
    "dlc": Manoeuvre("dlc", "double lane change", "dlc_high_mu", 90.0),
    "slalom": Manoeuvre("slalom", f"slalom, {SLALOM.cone_count} cones "
                        f"{SLALOM.cone_spacing_m:g} m apart", "slalom", SLALOM.exit_x_m),
}
#: A campaign row's scenario -> the manoeuvre.
MANOEUVRE_OF_SCENARIO = {m.scenario: name for name, m in MANOEUVRES.items()}


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
