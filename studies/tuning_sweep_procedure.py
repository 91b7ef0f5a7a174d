"""The tuning sweep's procedure (``make tune``, run by ``studies.tuning_sweep``): the
stages for every controller and the choice (:func:`run_sweep`).

The procedure, identical for every controller of ``controller.registry.CONTROLLERS`` (the
paper's four, the ablations and the geometric baseline ``stanley``):

1. Stage ``weights``: every setting of ``WEIGHT_GRID`` (the MPC weights; absolute values,
   the same for every MPC); a controller without MPC weights (a geometric baseline, its
   tuning table's class in ``GAIN_GRIDS``) runs its own grid of gains instead
   (``STANLEY_GRID``; stage ``gains``) and has no stage 2 to 4. A controller with an observer holds its observer
   fields at ``OBSERVER_START`` meanwhile, and runs the grid again at each of
   ``EXTRA_OBSERVER_STARTS``.
2. Stage ``observer``, only for a controller whose tuning table has observer fields
   (``OBSERVER_FIELDS``): every setting of ``OBSERVER_GRID`` at the best weights of stage 1.
3. Only with observer fields, alternating (coordinate descent): the weight grid again at
   the best observer setting so far, then the observer grid at the best weights so far,
   until a round leaves the best setting unchanged (at most ``MAX_EXTRA_ROUNDS`` rounds;
   settings already evaluated are not run again). Without it the choice depended on
   ``OBSERVER_START``: the 2026-12-02 sweep's stage 1 at eso_second_pole 0.97 picked
   q_position 1 for ESO-DKMPC, where no observer setting came within 25 % of the objective
   the previous choice (q_position 3, eso_second_pole 0.995) had.
4. Stage ``low-speed``, every MPC: the weights below the speed schedule's low knot
   (``low_speed_q_position``, ``low_speed_q_yaw``, ``low_speed_r_steer``; controller.tuning
   ``MpcTuning.weights_at``) over ``LOW_SPEED_GRID`` (the weight grid's levels), every
   other field at the best setting of steps 1-3. Steps 1-3 tune one weighting for every
   speed (their settings name no low-speed field: the low-speed weights follow,
   ``controller.tuning.with_fixed_weights``); the tuning set's 40 km/h scenarios and the
   other six wanted different weights (the best weights for each group differed for every
   controller in the 2026-12-02 sweep).
5. The chosen setting is the one with the smallest objective over all stages (ties: the
   first evaluated); it is written with its low-speed weights (equal to the others when
   stage 4 found nothing better: no schedule).

Objective of a setting: the mean over the tuning scenarios of the closed-loop e_Y RMSE (m);
a run that does not complete (the vehicle leaves the path by more than
``studies.closed_loop.ABORT_LATERAL_ERROR_M``, the plant diverges, the controller raises or
cannot be built) counts ``FAILURE_PENALTY_M`` for its scenario.

Controllers are built with their class's ``from_tuning(ControllerTuning)`` from the tuning
file's tables with only the swept fields replaced (``dataclasses.replace``): horizons,
soft-constraint and solver settings stay the file's. Observer gains are computed from the
model at build time, as always.

The runs are cells of the campaign engine (``studies.tuning_sweep_cells``: the grid
``studies/campaign/grids/tuning_sweep.toml``, each setting a value of its ``tuning`` axis,
cached under ``cache``); a stand-in ``runner`` (tests) runs in-memory scenarios through
``studies.tuning_sweep_executor.SweepExecutor`` instead.
"""
from __future__ import annotations

import itertools
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from controller.tuning import LOW_SPEED_WEIGHTS
from hil.errors import StudyError
from hil.scenario import Scenario
from studies.tuning_sweep_executor import Evaluation, Runner, SweepExecutor, best
from studies.tuning_sweep_grids import (GAIN_GRIDS, LOW_SPEED_GRID, OBSERVER_GRID, OBSERVER_START,
                                        WEIGHT_GRID, Setting, SweepGrid, has_low_speed_weights,
                                        stage_one_grid, stage_one_settings, stage_two_settings,
                                        swept_fields, with_low_speed_weights)

#: How many of the best settings the report lists per controller.
TOP_N = 5
#: Rounds of step 3 (weights again, then observer again) at most, per controller.
MAX_EXTRA_ROUNDS = 3


@dataclass(frozen=True)
class ControllerSweep:
    """The sweep of one controller: what was swept, every candidate evaluation (stage 1,
    then stage 2), the choice among them, and the tuning file's setting before the sweep
    (``before``: evaluated for reference, never a candidate; None when not asked for)."""

    controller: str
    weight_fields: tuple[str, ...]
    observer_fields: tuple[str, ...]
    evaluations: tuple[Evaluation, ...]
    chosen: Evaluation
    before: Evaluation | None = None
    #: Stage 1's grid where it is the controller's own (``GAIN_GRIDS``), else None (the
    #: sweep's weight grid).
    own_grid: SweepGrid | None = None

    def top(self, n: int = TOP_N) -> list[Evaluation]:
        """The ``n`` best evaluations, best first (ties in evaluation order)."""
        order = sorted(range(len(self.evaluations)),
                       key=lambda i: (self.evaluations[i].objective_m, i))
        return [self.evaluations[i] for i in order[:n]]


def current_setting(tuning: Any, name: str) -> Setting:
    """Controller ``name``'s swept fields as ``tuning`` (a ``ControllerTuning``) has them."""
    table = tuning.for_controller(name)
    weight_fields, observer_fields = swept_fields(table)
    low_speed = LOW_SPEED_WEIGHTS if has_low_speed_weights(table) else ()
    return tuple((field, float(getattr(table, field)))
                 for field in weight_fields + observer_fields + low_speed)


def run_sweep(controllers: Sequence[str], scenarios: Sequence[Scenario], tuning: Any, *,
              weight_grid: SweepGrid = WEIGHT_GRID, observer_grid: SweepGrid = OBSERVER_GRID,
              observer_start: Setting = OBSERVER_START, workers: int = 1,
              address: str | None = None, runner: Runner | None = None, show_progress: bool = True,
              evaluate_before: bool = False,
              extra_observer_starts: Sequence[Setting] = (),
              low_speed_grid: SweepGrid = LOW_SPEED_GRID,
              reuse: Mapping[tuple[str, Setting], Evaluation] | None = None,
              gain_grids: Mapping[type, SweepGrid] = GAIN_GRIDS,
              tuning_file: Path | None = None, cache: Path | None = None,
              tally: dict[str, int] | None = None) -> list[ControllerSweep]:
    """The procedure of the module docstring for every controller of ``controllers``.

    Args:
        controllers: registry names.
        scenarios: the tuning scenarios (never the evaluation ones: ``main`` loads the
            tuning set).
        tuning: the ``ControllerTuning`` whose non-swept fields every build keeps.
        weight_grid, observer_grid, observer_start: the procedure's grids (tests shrink them).
        workers: Ray workers of a local Ray (1 without ``address``: in this process).
        address: a Ray cluster to run on (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``).
        runner: None: the runs are campaign cells (``studies.tuning_sweep_cells``; the
            scenarios must be their files as loaded); else a stand-in runner (tests) that
            ``SweepExecutor`` calls on the scenario objects.
        evaluate_before: also evaluate each controller's setting in ``tuning`` (for the
            report; not a candidate, so values chosen elsewhere cannot be re-chosen here).
        extra_observer_starts: more observer settings at which stage 1 runs the weight grid
            too, for controllers with observer fields (``main`` passes
            ``EXTRA_OBSERVER_STARTS``).
        low_speed_grid: stage 4's grid (an empty grid: no stage 4).
        reuse: evaluations of an earlier sweep by (controller, setting) (``--reuse``): a
            job found there takes that evaluation instead of running again (the runs are
            deterministic; the caller checks that scenarios and model are the same).
        gain_grids: stage 1's grid of the controllers without MPC weights, by tuning-table
            class (tests shrink it); they have no stages 2 to 4.
        tuning_file: the file ``tuning`` was loaded from (the cells load it; None: the
            default ``controller/tuning.toml``).
        cache: the campaign cache folder of the cells (None: a temporary one, nothing kept).
        tally: when given, its ``"cached"`` is set to the runs the campaign cache gave.

    Returns:
        One :class:`ControllerSweep` per controller, in ``controllers`` order.
    """
    if not controllers or not scenarios:
        raise StudyError("the sweep needs at least one controller and one scenario")
    if workers < 1:
        raise StudyError(f"workers must be >= 1, got {workers}")
    plans = {}
    grids = {}
    scheduled = set()
    for name in controllers:
        table = tuning.for_controller(name)
        weight_fields, observer_fields = swept_fields(table, gain_grids)
        plans[name] = (weight_fields, observer_fields)
        grids[name] = stage_one_grid(table, weight_grid, gain_grids)
        if has_low_speed_weights(table):
            scheduled.add(name)
    stage_one = {name: [setting for start in (observer_start, *(extra_observer_starts if plans[name][1] else ()))
                        for setting in stage_one_settings(plans[name][1], grids[name], start)]
                 for name in controllers}
    stage_two_size = {name: len(observer_grid.restricted(plans[name][1])) if plans[name][1] else 0
                      for name in controllers}
    before_settings = ({name: current_setting(tuning, name) for name in controllers}
                       if evaluate_before else {})
    total = (sum(len(stage_one[n]) + stage_two_size[n] for n in controllers)
             + len(before_settings)) * len(scenarios)
    evaluations: dict[str, list[Evaluation]] = {name: [] for name in controllers}
    before: dict[str, Evaluation] = {}
    with (tqdm(total=total, desc="make tune", unit="run", disable=not show_progress,
               dynamic_ncols=True) as progress,
          tempfile.TemporaryDirectory(prefix="tuning-sweep-") as scratch):
        executor = _open_executor(scenarios, tuning, runner, workers, progress, address, reuse,
                                  tuning_file, Path(scratch) if cache is None else cache)
        try:
            # Round robin over the controllers: the slow ones' runs spread over the queue, so
            # no worker is left alone with a slow controller's runs at the end.
            rounds = itertools.zip_longest(*(stage_one[name] for name in controllers))
            jobs = [(name, "weights" if grids[name] is weight_grid else "gains", setting) for settings in rounds
                    for name, setting in zip(controllers, settings) if setting is not None]
            jobs += [(name, "before", setting) for name, setting in before_settings.items()]
            for evaluation in executor.evaluate(jobs):
                if evaluation.stage == "before":
                    before[evaluation.controller] = evaluation
                else:
                    evaluations[evaluation.controller].append(evaluation)
            jobs = []
            for name in controllers:
                seen = {e.setting for e in evaluations[name]}
                best_weights = best(evaluations[name]).setting
                for setting in stage_two_settings(best_weights, plans[name][1], observer_grid):
                    if setting in seen:
                        progress.update(len(scenarios))  # already evaluated in stage 1
                    else:
                        jobs.append((name, "observer", setting))
            for evaluation in executor.evaluate(jobs):
                evaluations[evaluation.controller].append(evaluation)
            _alternate(executor, evaluations, {n: plans[n][1] for n in controllers}, weight_grid,
                       observer_grid, progress, len(scenarios))
            jobs = []
            for name in (n for n in controllers if n in scheduled):
                current = best(evaluations[name]).setting
                flat = dict(with_low_speed_weights(current))
                for low_speed in low_speed_grid.settings():
                    # The flat schedule is the best setting itself, already evaluated.
                    if any(flat[field] != value for field, value in low_speed):
                        jobs.append((name, "low-speed", current + low_speed))
            progress.total += len(jobs) * len(scenarios)
            progress.refresh()
            for evaluation in executor.evaluate(jobs):
                evaluations[evaluation.controller].append(evaluation)
        finally:
            executor.close()
            if tally is not None:
                tally["cached"] = getattr(executor, "cached_runs", 0)
    low_speed_fields = low_speed_grid.fields
    return [ControllerSweep(name, plans[name][0] + (low_speed_fields if name in scheduled else ()), plans[name][1],
                            tuple(evaluations[name]), best(evaluations[name]), before.get(name),
                            grids[name] if grids[name] is not weight_grid else None)
            for name in controllers]


def _open_executor(scenarios: Sequence[Scenario], tuning: Any, runner: Runner | None, workers: int,
                   progress: Any, address: str | None, reuse: Mapping[tuple[str, Setting], Evaluation] | None,
                   tuning_file: Path | None, cache: Path | None) -> Any:
    """The campaign engine's cells (``runner`` None) or, for a stand-in runner, the
    in-memory executor; both evaluate (controller, stage, setting) jobs."""
    if runner is not None:
        return SweepExecutor(scenarios, tuning, runner, workers, progress, address, reuse)
    from studies.tuning_sweep_cells import CampaignSweepExecutor

    return CampaignSweepExecutor(scenarios, tuning_file=tuning_file, cache=cache, workers=workers,
                                 progress=progress, address=address, reuse=reuse)


def _alternate(executor: Any, evaluations: dict[str, list[Evaluation]],
               observer_fields: Mapping[str, Sequence[str]], weight_grid: SweepGrid,
               observer_grid: SweepGrid, progress: Any, n_scenarios: int) -> None:
    """Step 3 of the procedure, in place on ``evaluations``: for the controllers with
    observer fields, the weight grid at the best observer setting, then the observer grid
    at the best weights, until the best setting stays (``MAX_EXTRA_ROUNDS`` at most)."""
    active = [name for name, fields in observer_fields.items() if fields]
    for _ in range(MAX_EXTRA_ROUNDS):
        if not active:
            return
        start = {name: best(evaluations[name]).setting for name in active}
        for stage in ("weights", "observer"):
            jobs = []
            for name in active:
                current = best(evaluations[name]).setting
                fields = observer_fields[name]
                if stage == "weights":
                    held = tuple((f, v) for f, v in current if f in fields)
                    candidates = [weights + held for weights in weight_grid.settings()]
                else:
                    candidates = stage_two_settings(current, fields, observer_grid)
                seen = {e.setting for e in evaluations[name]}
                jobs += [(name, stage, s) for s in candidates if s not in seen]
            progress.total += len(jobs) * n_scenarios
            progress.refresh()
            for evaluation in executor.evaluate(jobs):
                evaluations[evaluation.controller].append(evaluation)
        active = [name for name in active if best(evaluations[name]).setting != start[name]]
