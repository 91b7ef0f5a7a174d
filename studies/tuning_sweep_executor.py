"""Settings of controllers evaluated on tuning scenarios: what an evaluation is, and the
in-memory executor.

An :class:`Evaluation` is one setting of one controller on every scenario; its
:func:`objective` is the mean e_Y RMSE, ``FAILURE_PENALTY_M`` for a run that does not
complete (:func:`evaluation_of` assembles one from its runs).

``make tune`` runs its settings on the campaign engine (``studies.tuning_sweep_cells``: the
grid ``studies/campaign/grids/tuning_sweep.toml``, cached cells). :class:`SweepExecutor`
runs (controller, setting) x scenario tasks on the same executors
(``studies.campaign.executors``: this process or Ray) for what the engine's scenario files
cannot express: scenario objects changed in memory (``make tune-observer``'s disturbed
tuning set, ``studies.observer_tuning``; ``make tradeoff``, ``studies.weight_tradeoff``) and
stand-in runners (tests). Both take stored evaluations where they are given them
(``--reuse``: :func:`reused_evaluations`).
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from hil.errors import StudyError
from hil.scenario import Scenario
from studies.campaign.tuning_override import build_controller  # noqa: F401 - importable here as before
from studies.closed_loop import ABORT_LATERAL_ERROR_M, ClosedLoopResult, run_closed_loop
from studies.tuning_sweep_grids import Setting, with_low_speed_weights, with_setting

#: e_Y RMSE (m) a scenario counts when its run does not complete.
FAILURE_PENALTY_M = ABORT_LATERAL_ERROR_M


@dataclass(frozen=True)
class Evaluation:
    """One setting of one controller on the whole tuning set.

    ``rmse_m`` / ``max_abs_m`` / ``completed`` / ``failure``: per scenario name; ``objective_m``
    the mean over scenarios of the e_Y RMSE, ``FAILURE_PENALTY_M`` for a run that did not
    complete; ``seconds`` the wall-clock time of its runs (build included).
    """

    controller: str
    stage: str
    setting: Setting
    rmse_m: dict[str, float]
    max_abs_m: dict[str, float]
    completed: dict[str, bool]
    failure: dict[str, str | None]
    objective_m: float
    seconds: float

    def as_dict(self) -> dict[str, Any]:
        return {"controller": self.controller, "stage": self.stage, "setting": dict(self.setting),
                "objective_m": self.objective_m, "rmse_m": self.rmse_m, "max_abs_m": self.max_abs_m,
                "completed": self.completed, "failure": self.failure, "seconds": self.seconds}


def objective(rmse_m: Mapping[str, float], completed: Mapping[str, bool]) -> float:
    """Mean e_Y RMSE (m) over the scenarios, ``FAILURE_PENALTY_M`` for an incomplete run."""
    if not rmse_m:
        raise StudyError("objective of no runs")
    values = [rmse_m[name] if completed[name] and np.isfinite(rmse_m[name]) else FAILURE_PENALTY_M
              for name in rmse_m]
    return float(np.mean(values))


def best(evaluations: Sequence[Evaluation]) -> Evaluation:
    """The evaluation with the smallest objective; the first such one on ties."""
    if not evaluations:
        raise StudyError("no evaluations to choose from")
    return min(enumerate(evaluations), key=lambda pair: (pair[1].objective_m, pair[0]))[1]


# ---------------------------------------------------------------------------- running

#: Runs one controller through one scenario (``studies.closed_loop.run_closed_loop``).
Runner = Callable[[Scenario, Any], ClosedLoopResult]


@dataclass(frozen=True)
class RunOutcome:
    """One closed-loop run of the sweep (a controller setting on one scenario)."""

    rmse_m: float
    max_abs_m: float
    completed: bool
    failure: str | None
    seconds: float


def run_one(name: str, setting: Setting, scenario: Scenario, tuning: Any,
            runner: Runner = run_closed_loop) -> RunOutcome:
    """Build controller ``name`` with ``setting`` applied to ``tuning`` and run it through
    ``scenario``. A controller that cannot be built or a runner that raises gives an
    incomplete outcome with the reason (never raised: one bad setting does not stop a sweep)."""
    started = time.perf_counter()
    try:
        controller = build_controller(name, with_setting(tuning, name, setting))
        result = runner(scenario, controller)
    except Exception as e:  # noqa: BLE001 - recorded as this setting's failure
        return RunOutcome(float("nan"), float("nan"), False, f"{type(e).__name__}: {e}",
                          time.perf_counter() - started)
    lateral = result.tracking.lateral
    return RunOutcome(float(lateral.rmse), float(lateral.max_abs), bool(result.completed),
                      result.failure, time.perf_counter() - started)


@dataclass(frozen=True)
class SweepTask:
    """One run of the sweep for a worker (picklable): evaluation ``index``'s controller and
    setting on scenario ``scenario_index`` of the tuning set."""

    key: str
    index: int
    controller: str
    setting: Setting
    scenario_index: int
    scenario: Scenario
    tuning: Any
    runner: Runner


def reuse_key(setting: Setting) -> Setting:
    """The controller tables a setting builds, as a key: low-speed weights named, fields
    sorted (a stage-1 setting and the same weights with a flat schedule are one key)."""
    return tuple(sorted(with_low_speed_weights(setting)))


def _run_task(task: SweepTask) -> RunOutcome:
    return run_one(task.controller, task.setting, task.scenario, task.tuning, task.runner)


#: A job of an executor: (controller, stage, setting).
Job = tuple[str, str, Setting]


def reused_evaluations(reuse: Mapping[tuple[str, Setting], Evaluation], jobs: Sequence[Job]) -> dict[int, Evaluation]:
    """The jobs (by index) that ``reuse`` (keyed by (controller, :func:`reuse_key`)) holds,
    as its evaluations relabelled with the job's stage and setting."""
    return {i: dataclasses.replace(reuse[(name, reuse_key(setting))], stage=stage, setting=setting)
            for i, (name, stage, setting) in enumerate(jobs) if (name, reuse_key(setting)) in reuse}


def evaluation_of(job: Job, runs: Mapping[str, RunOutcome]) -> Evaluation:
    """The evaluation of ``job`` from its runs (scenario name -> outcome, in scenario order)."""
    name, stage, setting = job
    rmse = {s: r.rmse_m for s, r in runs.items()}
    completed = {s: r.completed for s, r in runs.items()}
    return Evaluation(controller=name, stage=stage, setting=setting, rmse_m=rmse,
                      max_abs_m={s: r.max_abs_m for s, r in runs.items()}, completed=completed,
                      failure={s: r.failure for s, r in runs.items()},
                      objective_m=objective(rmse, completed), seconds=sum(r.seconds for r in runs.values()))


class SweepExecutor:
    """Runs (controller, setting) x scenario tasks on the campaigns' executors
    (``studies.campaign.executors``): in this process (one worker, no address), else as
    Ray tasks on a local Ray with ``workers`` CPUs or on the cluster at ``address``."""

    def __init__(self, scenarios: Sequence[Scenario], tuning: Any, runner: Runner, workers: int,
                 progress: tqdm, address: str | None = None,
                 reuse: Mapping[tuple[str, Setting], Evaluation] | None = None) -> None:
        from studies.campaign.executors import open_executor

        self.reuse = {(name, reuse_key(setting)): e for (name, setting), e in (reuse or {}).items()}
        self.scenarios = list(scenarios)
        self.tuning = tuning
        self.runner = runner
        self.progress = progress
        self.executor = open_executor(_run_task, address=address, workers=workers,
                                      serial=workers <= 1 and address is None)

    def close(self) -> None:
        self.executor.close()

    def evaluate(self, jobs: Sequence[tuple[str, str, Setting]]) -> list[Evaluation]:
        """Evaluate (controller, stage, setting) jobs on every scenario, in job order (a job
        in ``reuse`` takes the stored evaluation, relabelled with this job's stage)."""
        reused = reused_evaluations(self.reuse, jobs)
        self.progress.update(len(reused) * len(self.scenarios))
        tasks = [SweepTask(f"{name} {setting} on {scenario.name}", i, name, setting, k, scenario,
                           self.tuning, self.runner)
                 for i, (name, _, setting) in enumerate(jobs) if i not in reused
                 for k, scenario in enumerate(self.scenarios)]
        outcomes: dict[int, dict[int, RunOutcome]] = {i: {} for i in range(len(jobs))}
        for task, outcome, worker_error in self.executor.run(tasks):
            if worker_error is not None:
                outcome = RunOutcome(float("nan"), float("nan"), False, f"worker died: {worker_error}", 0.0)
            outcomes[task.index][task.scenario_index] = outcome
            self.progress.set_postfix_str(task.controller, refresh=False)
            self.progress.update(1)
        return [reused[i] if i in reused else
                evaluation_of(job, {self.scenarios[k].name: outcomes[i][k] for k in range(len(self.scenarios))})
                for i, job in enumerate(jobs)]
