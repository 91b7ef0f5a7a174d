"""The tuning sweep's grids and settings (``make tune``, run by ``studies.tuning_sweep``).

A setting is ``((field, value), ...)``: values of the swept fields of one controller's
tuning table. This module holds the swept fields, :class:`SweepGrid` and the procedure's
grids (stage 1's MPC-weight grid and the gain grids of the controllers without MPC weights,
the observer starts, stage 2's observer grid, stage 4's low-speed grid), which fields and
which stage-1 grid a tuning table gets, the settings of stages 1 and 2, a setting applied to
a ``ControllerTuning``, and a setting as text. The procedure itself:
``studies.tuning_sweep_procedure``.
"""
from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.tuning import LOW_SPEED_WEIGHTS, SCHEDULED_WEIGHTS, StanleyTuning, low_speed_twins
from hil.errors import StudyError
from studies.campaign.tuning_override import tuning_table_attribute, with_override  # noqa: F401 - importable here

#: One setting of the swept fields: ``((field, value), ...)`` in grid order (hashable).
Setting = tuple[tuple[str, float], ...]

#: The MPC weights of eq. 15 every controller has.
WEIGHT_FIELDS = ("q_position", "q_yaw", "r_steer", "p_steer_rate")
#: The observer fields (ESO error poles of eq. 24, horizon decay of w_hat), where present.
OBSERVER_FIELDS = ("eso_pole", "eso_second_pole", "disturbance_decay")


@dataclass(frozen=True)
class SweepGrid:
    """Levels of each swept field; the settings are their Cartesian product, in order.

    ``levels``: ``((field, (value, ...)), ...)``; every field once, every value list
    non-empty and without repeats.
    """

    levels: tuple[tuple[str, tuple[float, ...]], ...]

    def __post_init__(self) -> None:
        names = [name for name, _ in self.levels]
        if len(set(names)) != len(names):
            raise StudyError(f"grid names a field twice: {names}")
        for name, values in self.levels:
            if not values or len(set(values)) != len(values):
                raise StudyError(f"grid levels of {name} must be non-empty and distinct, got {values}")

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.levels)

    def restricted(self, fields: Sequence[str]) -> "SweepGrid":
        """The grid over the fields of ``fields`` only (in this grid's order)."""
        return SweepGrid(tuple((name, values) for name, values in self.levels if name in fields))

    def settings(self) -> list[Setting]:
        """Every setting, the last field varying fastest; none for a grid of no fields."""
        if not self.levels:
            return []
        names = self.fields
        return [tuple(zip(names, (float(v) for v in combo)))
                for combo in itertools.product(*(values for _, values in self.levels))]

    def __len__(self) -> int:
        return int(np.prod([len(values) for _, values in self.levels], dtype=int)) if self.levels else 0

    def as_dict(self) -> dict[str, list[float]]:
        return {name: [float(v) for v in values] for name, values in self.levels}


#: The MPC-weight grid, the same absolute values for every controller: 6 x 3 x 2 = 36
#: settings (NMPC, about eight times slower per run than the QP MPCs, gets as many
#: evaluations as the others). The MPC's minimiser depends only on the ratios of the weights
#: (up to the soft-constraint slacks, rarely active), so p_steer_rate stays 300 as the
#: normalisation and the three other weights span the ratios. q_position / p_steer_rate
#: matters most (by tens of percent per x3 step of it). The grid of the 2026-12-01 sweep
#: (q_position 3 .. 1000 in 8 levels, q_yaw 5 / 20 / 80) put every controller's choice at
#: q_position 3-60 and five of six at the grid's lower edge of q_position or upper edge of
#: q_yaw, and q_yaw 5 in no top-5 but one controller's fifth: the levels now extend one x3
#: step past those edges (q_position 1, q_yaw 300) and drop the levels no controller came near.
WEIGHT_GRID = SweepGrid((
    ("q_position", (1.0, 3.0, 10.0, 30.0, 100.0, 300.0)),
    ("q_yaw", (20.0, 80.0, 300.0)),
    ("r_steer", (0.3, 3.0)),
    ("p_steer_rate", (300.0,)),
))
#: The observer grid of stage 2: fast pole x slow pole x horizon decay of w_hat = 24. The
#: 2026-12-01 sweep chose the slowest second pole (0.995) and the strongest decay (0.8) of its
#: grid and found the fast pole worth at most 0.1 mm: the grid now reaches 0.998 and 0.6 and
#: spends two levels on the fast pole.
OBSERVER_GRID = SweepGrid((
    ("eso_pole", (0.0, 0.5)),
    ("eso_second_pole", (0.97, 0.99, 0.995, 0.998)),
    ("disturbance_decay", (0.6, 0.8, 1.0)),
))
#: More observer settings stage 1 also runs the weight grid at (controllers with an
#: observer). Coordinate descent ends in the basin of its start: on 2026-12-02, from
#: OBSERVER_START alone, ESO-DKMPC ended at q_position 1 / eso_second_pole 0.97 with a
#: tuning-set objective of 0.048 m, where the setting the 2026-12-01 sweep had chosen on the
#: same tuning set (q_position 3, eso_second_pole 0.995, decay 0.8) has 0.038 m. That
#: observer setting is the second start, so the procedure cannot end worse than it.
EXTRA_OBSERVER_STARTS: tuple[Setting, ...] = (
    (("eso_pole", 0.0), ("eso_second_pole", 0.995), ("disturbance_decay", 0.8)),
)
#: Stage 1's grid of the Stanley baseline (controller/stanley.py), which has no MPC weights:
#: 6 x 2 x 6 x 2 x 2 = 288 settings (a run costs about a twentieth of a QP MPC's, so the
#: grid can cover every gain). cross_track_gain k (1/s) in x2 steps from 2.5; softening_speed
#: at 1 m/s (Hoffmann et al.'s role for it: a finite gain at standstill) and 5 m/s (it also
#: lowers the gain at the tuning speeds); yaw_rate_gain from 0 (the pure law) to 2.5 s;
#: steer_rate_limit at the plant servo's 1 rad/s and at 3 rad/s (never binding behind that
#: servo); steer_time_constant 0 (no low-pass) and 0.05 s: the two production additions,
#: kept only if they win on the tuning set. The first grid (2026-12-04: k up to 40,
#: yaw_rate_gain up to 1.5, 200 settings) chose both at their upper edge (k 40, 1.5 s;
#: tuning-set objective 0.0816 m): each now reaches one step further (k 80, 2.5 s).
STANLEY_GRID = SweepGrid((
    ("cross_track_gain", (2.5, 5.0, 10.0, 20.0, 40.0, 80.0)),
    ("softening_speed", (1.0, 5.0)),
    ("yaw_rate_gain", (0.0, 0.3, 0.6, 1.0, 1.5, 2.5)),
    ("steer_rate_limit", (1.0, 3.0)),
    ("steer_time_constant", (0.0, 0.05)),
))
#: Controllers without MPC weights, by the class of their tuning table: their stage-1 grid.
GAIN_GRIDS: dict[type, SweepGrid] = {StanleyTuning: STANLEY_GRID}
#: Stage 4's grid: the low-speed weights over the levels of WEIGHT_GRID's scheduled weights.
LOW_SPEED_GRID = SweepGrid(tuple((f"low_speed_{name}", values) for name, values in WEIGHT_GRID.levels
                                 if name in SCHEDULED_WEIGHTS))
#: The observer values of stage 1 (a point of OBSERVER_GRID).
OBSERVER_START: Setting = (("eso_pole", 0.0), ("eso_second_pole", 0.97), ("disturbance_decay", 1.0))


# ---------------------------------------------------------------------------- settings

def swept_fields(table: Any, gain_grids: Mapping[type, SweepGrid] = GAIN_GRIDS
                 ) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(weight fields, observer fields) of a controller's tuning table (a dataclass); for a
    table of ``gain_grids`` (no MPC weights) its grid's fields and no observer fields.

    Raises StudyError when an MPC table lacks one of the MPC weights."""
    if type(table) in gain_grids:
        return gain_grids[type(table)].fields, ()
    names = {field.name for field in dataclasses.fields(table)}
    missing = [name for name in WEIGHT_FIELDS if name not in names]
    if missing:
        raise StudyError(f"tuning table {type(table).__name__} has no {missing}: cannot sweep its weights")
    return WEIGHT_FIELDS, tuple(name for name in OBSERVER_FIELDS if name in names)


def stage_one_grid(table: Any, weight_grid: SweepGrid = WEIGHT_GRID,
                   gain_grids: Mapping[type, SweepGrid] = GAIN_GRIDS) -> SweepGrid:
    """Stage 1's grid of a controller with tuning table ``table``: its own grid where its
    class is in ``gain_grids`` (no MPC weights), else ``weight_grid``."""
    return gain_grids.get(type(table), weight_grid)


def has_low_speed_weights(table: Any) -> bool:
    """Whether ``table`` has the speed schedule's low-speed weights (stage 4 applies)."""
    return set(LOW_SPEED_WEIGHTS) <= {field.name for field in dataclasses.fields(table)}


def with_setting(tuning: Any, name: str, setting: Setting) -> Any:
    """``tuning`` (a ``ControllerTuning``) with controller ``name``'s table's fields of
    ``setting`` replaced; every other value unchanged, except that a weight replaces its
    low-speed twin too unless the setting names that twin (a flat schedule). The campaign
    engine's override of a cell (``studies.campaign.tuning_override.with_override``)."""
    return with_override(tuning, name, setting)


def with_low_speed_weights(setting: Setting) -> Setting:
    """``setting`` with its low-speed weights named: as given, else equal to its weights
    (the flat schedule ``with_setting`` applies). What is written to the tuning file."""
    return setting + tuple(low_speed_twins(dict(setting)).items())


def stage_one_settings(observer_fields: Sequence[str], weight_grid: SweepGrid = WEIGHT_GRID,
                       observer_start: Setting = OBSERVER_START) -> list[Setting]:
    """Stage 1 of a controller with these observer fields: the weight grid, observer fields
    (if any) at ``observer_start``."""
    start = tuple((name, value) for name, value in observer_start if name in observer_fields)
    return [weights + start for weights in weight_grid.settings()]


def stage_two_settings(best_weights: Setting, observer_fields: Sequence[str],
                       observer_grid: SweepGrid = OBSERVER_GRID) -> list[Setting]:
    """Stage 2: the observer grid (over the controller's observer fields) at the weights of
    ``best_weights`` (its other fields are dropped); empty without observer fields."""
    if not observer_fields:
        return []
    weights = tuple((name, value) for name, value in best_weights if name in WEIGHT_FIELDS)
    return [weights + observer for observer in observer_grid.restricted(observer_fields).settings()]


def setting_text(setting: Setting) -> str:
    """``setting`` as text for reports: ``q_position 3, q_yaw 80`` (values as ``:g``)."""
    return ", ".join(f"{name} {value:g}" for name, value in setting)
