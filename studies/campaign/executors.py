"""Where the studies' tasks run: Ray (local or a cluster) or this process, one code path.

Every long study hands its independent tasks (campaign cells, the tuning sweep's runs,
the robustness grid's runs, Table I's trainings) to an executor:

    executor = open_executor(address=None, workers=None, serial=False, task_function=f)
    for job, result, error in executor.run(jobs):   # as they finish
        ...
    executor.close()

``task_function(job) -> result`` must be a module-level function (Ray pickles it by
reference) that handles its own failures: it returns a result that says the task failed
rather than raising. ``error`` is None for a result, or a one-line message when the worker
itself died (Ray) and no result exists; the study decides what such a task becomes.

Ray: by default a local Ray on this machine (one worker per core, bound to 127.0.0.1, no
dashboard, a small object store, usage statistics off); ``address`` (``auto``,
``HOST:PORT``, ``ray://HOST:PORT``) joins an existing cluster instead. Workers get one
BLAS / OpenMP thread through the runtime environment (tiny matrices; the cores are
already busy with one task each). At most ``2 x workers`` tasks are in flight, so a
Ctrl-C (the generator closed) cancels little and keeps every finished task.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

from hil.errors import HilError

#: Environment of every worker: one BLAS / OpenMP thread (tiny matrices, cores are busy).
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Object store of the local Ray (bytes): the tasks pass a few kB each.
LOCAL_OBJECT_STORE_BYTES = 128 * 1024 * 1024

#: A finished task: (job, result or None, None or the message of a worker's death).
Finished = tuple[Any, Any, "str | None"]


class ExecutorError(HilError):
    """Ray is missing or cannot start / be reached."""


class Executor(Protocol):
    """What a study needs of an executor."""

    workers: int
    description: str

    def run(self, jobs: Sequence[Any]) -> Iterator[Finished]:
        """Run ``task_function`` on every job; yield them as they finish (any order)."""

    def close(self) -> None:
        """Release the workers (Ray: shut the local Ray down / disconnect)."""


class SerialExecutor:
    """Runs the tasks one by one in this process (``--serial``; tests, debugging)."""

    workers = 1
    description = "this process, one task at a time"

    def __init__(self, task_function: Callable[[Any], Any]) -> None:
        self.task_function = task_function

    def run(self, jobs: Sequence[Any]) -> Iterator[Finished]:
        for job in jobs:
            yield job, self.task_function(job), None

    def close(self) -> None:
        pass


def _ray():
    try:
        import ray
    except ImportError as e:
        raise ExecutorError("Ray is not installed: `make setup` installs it (the campaign "
                            "extra of pyproject.toml), or use --serial") from e
    return ray


class RayExecutor:
    """Tasks as Ray tasks (one CPU each), at most ``2 x workers`` in flight.

    Args:
        task_function: the module-level function each task runs.
        address: None starts a local Ray; ``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``
            joins that cluster.
        workers: local Ray's CPUs (default: this machine's cores); on a cluster the
            limit of tasks running at once (default: the cluster's CPUs).
    """

    def __init__(self, task_function: Callable[[Any], Any], address: str | None = None,
                 workers: int | None = None) -> None:
        ray = _ray()
        self.ray = ray
        # No usage statistics (they would leave the machine); keep 127.0.0.1 as given.
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        runtime_env = {"env_vars": dict(WORKER_ENV)}
        try:
            if address is None:
                cpus = workers or os.cpu_count() or 1
                ray.init(num_cpus=cpus, include_dashboard=False, _node_ip_address="127.0.0.1",
                         object_store_memory=LOCAL_OBJECT_STORE_BYTES, runtime_env=runtime_env,
                         log_to_driver=False, configure_logging=False)
                self.description = f"local Ray on 127.0.0.1, {cpus} workers"
            else:
                ray.init(address=address, runtime_env=runtime_env, log_to_driver=False,
                         configure_logging=False)
                cpus = int(ray.cluster_resources().get("CPU", 1))
                self.description = f"Ray cluster at {address}, {cpus} CPUs"
        except Exception as e:  # noqa: BLE001 - Ray raises many kinds: one message
            raise ExecutorError(f"cannot start or reach Ray ({address or 'local'}): {e}") from e
        self.workers = max(1, workers or cpus)
        self.remote = ray.remote(num_cpus=1, max_retries=0)(task_function)

    def run(self, jobs: Sequence[Any]) -> Iterator[Finished]:
        ray = self.ray
        pending = list(jobs)[::-1]
        in_flight: dict[Any, Any] = {}
        try:
            while pending or in_flight:
                while pending and len(in_flight) < 2 * self.workers:
                    job = pending.pop()
                    in_flight[self.remote.remote(job)] = job
                done, _ = ray.wait(list(in_flight), num_returns=1)
                for ref in done:
                    job = in_flight.pop(ref)
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayError as e:  # the worker died, not the task
                        yield job, None, f"{type(e).__name__}: {str(e).splitlines()[0]}"
                    else:
                        yield job, result, None
        finally:
            for ref in in_flight:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        self.ray.shutdown()


def open_executor(task_function: Callable[[Any], Any], *, address: str | None = None,
                  workers: int | None = None, serial: bool = False) -> SerialExecutor | RayExecutor:
    """The executor the command line asked for: ``serial`` -> this process, else Ray
    (local, or the cluster at ``address``). Raises ExecutorError for bad choices."""
    if workers is not None and workers < 1:
        raise ExecutorError(f"--workers must be >= 1, got {workers}")
    if serial and address:
        raise ExecutorError("--serial and --address exclude each other")
    if serial:
        return SerialExecutor(task_function)
    return RayExecutor(task_function, address, workers)


def add_executor_arguments(parser: Any, *, default_workers: str = "one per core") -> None:
    """``--address``, ``--workers``, ``--serial`` on an argparse parser (every study alike)."""
    parser.add_argument("--address", default=None,
                        help="Ray cluster to use: auto, HOST:PORT or ray://HOST:PORT "
                             "(default: start a local Ray on 127.0.0.1)")
    parser.add_argument("--workers", type=int, default=None,
                        help=f"local Ray: its workers (default: {default_workers}); cluster: the "
                             "most tasks at once (default: its CPUs)")
    parser.add_argument("--serial", action="store_true",
                        help="no Ray: run the tasks one by one in this process")
