"""The tuning sweep's settings as campaign cells (``make tune``): each (controller, setting)
of a stage becomes one cell per tuning scenario of the grid
``studies/campaign/grids/tuning_sweep.toml`` (closed loop without CAN, a run stops only
beyond 10 m), its setting a value of the grid's ``tuning`` axis (an override of the
controller's table, ``studies.campaign.tuning_override``). The campaign engine runs them
(``studies.campaign.runner.run_campaign``: its executors, Ray local or a cluster, or this
process; its cache, ``DIR/cache/<key>.json`` per finished cell), and the cells' rows become
the sweep's :class:`~studies.tuning_sweep_executor.Evaluation` s.

A cell is the run the sweep made before it ran on the engine: the controller built by its
class's ``from_tuning`` from the tuning file with the setting's fields replaced, the
scenario's plant, ``studies.closed_loop.run_closed_loop`` stopping beyond
``ABORT_LATERAL_ERROR_M``; ``tests/test_tuning_sweep_cells.py`` checks the figures equal a
direct run's to the last bit.

The cache makes an interrupted ``make tune`` resume where it stopped (``--cache``, default
``build/tuning_sweep``). Its keys hash the code and the default tuning file
(``studies.campaign.runner.code_version``), so a sweep that writes ``controller/tuning.toml``
leaves the next sweep nothing to take from it; ``--reuse`` (``studies.tuning_sweep_reuse``)
is what carries evaluations across such changes.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hil.errors import StudyError
from hil.scenario import Scenario
from studies.campaign.grid import CLOSED_LOOP_RUNNER, ROOT, Cell, Grid, load_grid
from studies.tuning_sweep_executor import Evaluation, Job, RunOutcome, evaluation_of, reuse_key, reused_evaluations
from studies.tuning_sweep_grids import Setting

#: The sweep's grid file (a name of ``studies/campaign/grids/`` or a path).
SWEEP_GRID = "tuning_sweep"
#: Where ``make tune`` keeps its cells (``--cache``).
DEFAULT_CACHE = ROOT / "build" / "tuning_sweep"


def tuning_name(setting: Setting) -> str:
    """The tuning axis value of ``setting``: its fields with their exact values."""
    return ", ".join(f"{field}={value!r}" for field, value in setting)


def sweep_grid(scenarios: Sequence[Scenario], tuning_file: Path | None = None,
               grid_file: str | Path = SWEEP_GRID) -> tuple[Grid, dict[str, str]]:
    """The sweep's grid on ``scenarios`` (scenario files, as loaded) with ``tuning_file`` as
    every cell's base tuning file (None or the default file: the controllers' own), and the
    scenario axis value of each scenario name.

    Raises:
        StudyError: a scenario that is not its file as loaded (changed in memory: the
            engine runs files; ``SweepExecutor`` runs such scenarios).
    """
    from controller.tuning import DEFAULT_TUNING_PATH

    grid = load_grid(grid_file)
    by_file = {path.resolve(): value for value, path in grid.scenario_files.items()}
    values: dict[str, str] = {}
    files: dict[str, Path] = {}
    for scenario in scenarios:
        source = Path(scenario.source).resolve()
        if Scenario.load(source) != scenario:
            raise StudyError(f"scenario {scenario.name}: differs from its file {source}; the campaign "
                             "engine runs scenario files")
        value = by_file.get(source, str(source))  # the grid's own value where it lists the file
        values[scenario.name] = value
        files[value] = source
    if tuning_file is not None and Path(tuning_file).resolve() == DEFAULT_TUNING_PATH.resolve():
        tuning_file = None  # the cells' keys as those of `python -m studies.campaign tuning_sweep`
    grid = dataclasses.replace(grid, scenario_files=files, cells=(),
                               tuning_file=None if tuning_file is None else Path(tuning_file).resolve())
    return grid, values


def outcome_of(row: Mapping[str, Any]) -> RunOutcome:
    """A campaign row of a ``closed_loop`` cell as the sweep's run outcome: a run that did
    not start (``error``) or stopped (``failure``) is incomplete with that reason."""
    failure = row.get("error") or row.get("failure") or None
    return RunOutcome(rmse_m=float(row.get("e_y_rmse", math.nan)), max_abs_m=float(row.get("e_y_max", math.nan)),
                      completed=bool(row.get("completed")), failure=failure,
                      seconds=float(row.get("wall_s", 0.0)))


class CampaignSweepExecutor:
    """Evaluates (controller, stage, setting) jobs on every scenario as campaign cells
    (module docstring), on the campaigns' executors: in this process (one worker, no
    address), else Ray tasks on a local Ray with ``workers`` CPUs or on the cluster at
    ``address``. ``progress``: a tqdm bar advanced per run (cached or computed)."""

    def __init__(self, scenarios: Sequence[Scenario], *, tuning_file: Path | None, cache: Path, workers: int,
                 progress: Any, address: str | None = None,
                 reuse: Mapping[tuple[str, Setting], Evaluation] | None = None,
                 grid_file: str | Path = SWEEP_GRID) -> None:
        from studies.campaign.cell import run_cell
        from studies.campaign.executors import open_executor

        self.grid, self.values = sweep_grid(scenarios, tuning_file, grid_file)
        self.names = [scenario.name for scenario in scenarios]
        self.cache = Path(cache)
        self.progress = progress
        self.reuse = {(name, reuse_key(setting)): e for (name, setting), e in (reuse or {}).items()}
        #: Runs taken from the campaign cache so far (not run again).
        self.cached_runs = 0
        self.executor = open_executor(run_cell, address=address, workers=workers,
                                      serial=workers <= 1 and address is None)

    def close(self) -> None:
        self.executor.close()

    def evaluate(self, jobs: Sequence[Job]) -> list[Evaluation]:
        """Evaluate the jobs on every scenario, in job order (a job in ``reuse`` takes the
        stored evaluation, relabelled with this job's stage)."""
        from studies.campaign.runner import run_campaign

        reused = reused_evaluations(self.reuse, jobs)
        self.progress.update(len(reused) * len(self.names))
        tunings = dict(self.grid.tunings)
        cells = []
        for i, (name, _, setting) in enumerate(jobs):
            if i not in reused:
                tunings[tuning_name(setting)] = tuple(setting)
                cells += [Cell(controller=name, scenario=self.values[s], runner=CLOSED_LOOP_RUNNER,
                               tuning=tuning_name(setting)) for s in self.names]
        rows: dict[tuple[str, str, str], Mapping[str, Any]] = {}
        if cells:
            grid = dataclasses.replace(self.grid, cells=tuple(cells), tunings=tunings)
            result = run_campaign(grid, self.cache, self.executor, progress=False,
                                  on_row=lambda row: self.progress.update(1))
            if result.interrupted:
                raise KeyboardInterrupt
            self.progress.update(result.cached)
            self.cached_runs += result.cached
            rows = {(row["controller"], row["tuning"], row["scenario"]): row for row in result.rows}
        evaluations = []
        for i, job in enumerate(jobs):
            if i in reused:
                evaluations.append(reused[i])
                continue
            name, _, setting = job
            try:
                runs = {s: outcome_of(rows[(name, tuning_name(setting), self.values[s])]) for s in self.names}
            except KeyError as e:
                raise StudyError(f"the campaign returned no row for {name} {setting} on {e}") from None
            evaluations.append(evaluation_of(job, runs))
        return evaluations
