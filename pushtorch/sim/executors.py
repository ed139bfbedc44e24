"""Where a run's shards are simulated: this machine's process pool, a Ray cluster, or a Slurm array job.

Paper, Experimental Setup (tens of thousands of simulated pushes per experiment). A run's shards are a pure
function of its plan (:mod:`pushtorch.sim.runner`), so any worker on any node may simulate any shard: each
task simulates one shard and writes it atomically into the run folder, which every node shares. The run that
submitted the tasks holds the folder's lock, checks the manifest once, and merges nothing: the folder *is*
the result (:func:`pushtorch.sim.records.load_records`).

``executor`` (the config group ``conf/executor``; :class:`Executor`):

* ``local`` (default): worker processes on this machine (:class:`pushtorch.sim.runner.PushPool`).
* ``ray``: Ray tasks, retried when a worker dies (``max_retries``). ``address``: ``auto`` or a head node's
  ``host:port`` to join a running cluster; none starts a local instance with ``num_cpus`` (0: all cores).
* ``slurm``: one submitit array job, a task per block of shards (``tasks`` blocks; ``timeout_min``,
  ``partition``, ``array_parallelism``). A pre-empted task is requeued by submitit and skips the shards it
  had finished. ``cluster=local`` runs the array as local processes (tests, laptops).

An experiment's work beyond pushes (training its models, prediction sets with their peers, scores) goes to the
same executor as tasks (:func:`run_remote_tasks`, called by :mod:`pushtorch.experiments.tasks`): one CPU each,
``task_memory_mb`` each (Ray's ``memory`` resource, Slurm's ``--mem``), their outputs written into the shared
run folder. Each task says where it ran (:func:`task_host`).

Ray and submitit are optional extras (``pip install "pushtorch[ray]"`` / ``"pushtorch[slurm]"``); a missing
one, or a Ray address nobody answers at, is a one-line :class:`~pushtorch.errors.InvalidParameterError` raised
before any file is written.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from pushtorch.errors import InvalidParameterError, MissingDependencyError

__all__ = ["EXECUTORS", "Executor", "connect", "executor_from_config", "run_remote_tasks", "slurm_problem",
           "submit_remote_tasks", "task_host"]

#: The executors ``executor.kind`` may name.
EXECUTORS = ("local", "ray", "slurm")


@dataclass(frozen=True)
class Executor:
    """Where shards run (see the module notes). Every field but ``kind`` belongs to one executor.

    Attributes:
        kind: ``local``, ``ray`` or ``slurm``.
        address: ray: ``auto`` or ``host:port`` of a running cluster's head; None starts a local instance.
        num_cpus: ray: CPUs of a local instance (0: all cores).
        max_retries: ray: how often a task whose worker died is run again.
        cluster: slurm: submitit's cluster (None: Slurm; ``local``: local processes).
        folder: slurm: where submitit keeps its job files (None: ``<run folder>/.submitit``).
        timeout_min: slurm: minutes per array task.
        partition: slurm: the partition (None: the site's default).
        array_parallelism: slurm: array tasks running at once.
        tasks: slurm: array tasks, each a block of consecutive shards (0: one per shard, at most 256).
        task_memory_mb: ray and slurm: the memory an experiment task states (training a part's model,
            one group of predictions with its peers and scores); Ray schedules by it, Slurm requests it.
    """

    kind: str = "local"
    address: str | None = None
    num_cpus: int = 0
    max_retries: int = 3
    cluster: str | None = None
    folder: str | None = None
    timeout_min: int = 60
    partition: str | None = None
    array_parallelism: int = 64
    tasks: int = 0
    task_memory_mb: int = 3000

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise InvalidParameterError(f"executor.kind must be one of {', '.join(EXECUTORS)}, got {self.kind!r}")
        for name in ("num_cpus", "max_retries", "tasks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InvalidParameterError(f"executor.{name} must be a non-negative integer, got {value!r}")
        for name in ("timeout_min", "array_parallelism", "task_memory_mb"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidParameterError(f"executor.{name} must be a positive integer, got {value!r}")


def executor_from_config(config: Mapping | None) -> Executor:
    """The :class:`Executor` of a config's ``executor`` mapping (None or empty: local).

    Raises:
        InvalidParameterError: an unknown key or value.
    """
    entry = dict(config or {})
    known = {f.name for f in fields(Executor)}
    unknown = sorted(set(entry) - known)
    if unknown:
        raise InvalidParameterError(f"unknown executor keys {unknown}; known: {', '.join(sorted(known))}")
    return Executor(**entry)


def _require(module: str, extra: str):
    try:
        return __import__(module)
    except ImportError as exc:
        raise MissingDependencyError(
            f"executor={extra} needs {module}, which is not installed: pip install \"pushtorch[{extra}]\""
        ) from exc


# --- the worker side: one world per (object, settings) and process ---------------------------------------

_WORLDS: dict[str, object] = {}


def _spec_key(spec, settings) -> str:
    digest = hashlib.sha256(repr(settings).encode())
    digest.update(spec.name.encode())
    for part in spec.parts:
        digest.update(part.tobytes())
    return digest.hexdigest()


def run_shard_task(spec, settings, task) -> tuple[int, int, int]:
    """Simulate and write one shard (a runner task) in this process, building its world on first use."""
    from pushtorch.sim.engines import make_world
    from pushtorch.sim.worker import run_shard_in

    key = _spec_key(spec, settings)
    if key not in _WORLDS:
        for old in _WORLDS.values():
            old.close()
        _WORLDS.clear()
        _WORLDS[key] = make_world(spec, settings)
    return run_shard_in(_WORLDS[key], task)


def run_shard_block(spec, settings, tasks) -> list[tuple[int, int, int]]:
    """An array task: its block of shards, skipping those already finished (a requeued task resumes)."""
    from pushtorch.sim.shards import complete_shards

    done = complete_shards(Path(tasks[0][1]), verify=False) if tasks else {}  # a block's shards share a folder
    return [run_shard_task(spec, settings, task) for task in tasks if task[0] not in done]


# --- the submitting side -------------------------------------------------------------------------------


def _check_address(address: str) -> None:
    """Refuse a Ray head that does not answer within 5 s (``ray.init`` would wait for minutes)."""
    if address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        with socket.create_connection((host or "localhost", int(port)), timeout=5.0):
            pass
    except (OSError, ValueError) as exc:
        raise InvalidParameterError(
            f"executor.address={address!r}: no Ray head answers there ({exc}); start one with `ray start --head`"
            " or give its host:port"
        ) from exc


def connect(executor: Executor) -> None:
    """Join (or start) the executor's Ray cluster in this process now, once, before threads submit to it. Call it
    from a thread that lives as long as the run (the main thread): a local instance's processes are tied to the
    thread that starts them (Linux's parent-death signal) and end with it. Nothing for the local and Slurm
    executors."""
    if executor.kind == "ray":
        _ray_session(executor)


def _ray_session(executor: Executor):
    """Ray, joined to ``executor.address`` or started locally with ``num_cpus`` (once per process)."""
    ray = _require("ray", "ray")
    if not ray.is_initialized():
        _ray_init(ray, executor)
    return ray


def _ray_init(ray, executor: Executor) -> None:
    """Join ``executor.address``, or start a local instance of ``num_cpus``."""
    if executor.address:
        _check_address(executor.address)
        try:
            ray.init(address=executor.address, include_dashboard=False, log_to_driver=False)
        except ConnectionError as exc:
            raise InvalidParameterError(f"executor.address={executor.address!r}: {exc}") from exc
    else:
        # address="local": a new instance even where `ray start` left a cluster's address in Ray's temp folder
        # (ray.init() would join that cluster, or refuse num_cpus)
        ray.init(address="local", num_cpus=executor.num_cpus or os.cpu_count(), include_dashboard=False,
                 log_to_driver=False)


class _RemotePool:
    """What the remote pools share: nothing to release (Ray and the array's jobs outlive the pool), and the
    context-manager protocol :func:`pushtorch.sim.runner.run_plan` uses."""

    def close(self) -> None:
        """A local Ray instance ends with this process, a cluster is the user's; an array's jobs have ended."""

    terminate = close

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RayPool(_RemotePool):
    """Shards as Ray tasks (retried when a worker dies); :meth:`imap_unordered` yields as they finish."""

    def __init__(self, spec, settings, executor: Executor):
        ray = self.ray = _ray_session(executor)
        self._spec = ray.put(spec)
        self._settings = settings
        self._remote = ray.remote(num_cpus=1, max_retries=int(executor.max_retries))(run_shard_task)

    def imap_unordered(self, _function, tasks) -> Iterator[tuple[int, int, int]]:
        pending = [self._remote.remote(self._spec, self._settings, task) for task in tasks]
        while pending:
            done, pending = self.ray.wait(pending, num_returns=1)
            yield self.ray.get(done[0])


def slurm_problem(executor: Executor) -> str | None:
    """Why ``executor`` (kind ``slurm``) cannot reach Slurm from this machine, or None.

    submitit's ``AutoExecutor`` falls back to local processes without a word when it finds no Slurm, and so
    does a partition Slurm does not know: a paper-size run would then run on a login node. So a Slurm array
    asks for ``sbatch`` on the ``PATH``, and a named partition must be one ``sinfo`` lists (when ``sinfo``
    answers). ``cluster=local`` is the explicit way to run an array as local processes.
    """
    if executor.kind != "slurm" or executor.cluster == "local":
        return None
    if executor.cluster not in (None, "slurm"):
        return f"executor.cluster must be null (Slurm) or local, got {executor.cluster!r}"
    if shutil.which("sbatch") is None:
        return ("executor=slurm needs Slurm, but sbatch is not on this machine's PATH: run from a Slurm login "
                "node, or set executor.cluster=local to run the array as local processes")
    if executor.partition and shutil.which("sinfo") is not None:
        try:
            listed = subprocess.run(["sinfo", "-h", "-o", "%P"], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            return None  # Slurm is there; its own submission names a bad partition
        known = {name.strip().rstrip("*") for name in listed.stdout.split()} if listed.returncode == 0 else set()
        if known and executor.partition not in known:
            return (f"executor.partition={executor.partition!r} is not a Slurm partition here; sinfo lists "
                    f"{', '.join(sorted(known))}")
    return None


class SlurmPool(_RemotePool):
    """Shards as one submitit array job, a task per block of shards; yields each block's results as it ends.

    Raises:
        InvalidParameterError: no Slurm reachable, or an unknown partition (:func:`slurm_problem`).
    """

    def __init__(self, spec, settings, executor: Executor):
        if problem := slurm_problem(executor):
            raise InvalidParameterError(problem)
        self.submitit = _require("submitit", "slurm")
        self.spec, self.settings, self.executor = spec, settings, executor

    def imap_unordered(self, _function, tasks) -> Iterator[tuple[int, int, int]]:
        tasks = list(tasks)
        if not tasks:
            return
        e = self.executor
        blocks = min(len(tasks), e.tasks or 256)
        chunks = [tasks[k * len(tasks) // blocks:(k + 1) * len(tasks) // blocks] for k in range(blocks)]
        jobs = _slurm_array(self.submitit, e, Path(tasks[0][1]) / ".submitit", run_shard_block,
                            [[self.spec] * blocks, [self.settings] * blocks, chunks])
        for _, result in _as_they_end(jobs):
            yield from result


def _slurm_array(submitit, executor: Executor, folder: Path, function: Callable, columns: list[list],
                 **parameters) -> list:
    """One submitit array job of ``function`` over ``columns`` (one list per argument), its job files under
    ``executor.folder`` or ``folder``, with the executor's time limit (and, on Slurm, its parallelism and partition)
    and ``parameters``; returns its jobs."""
    runner = submitit.AutoExecutor(folder=str(Path(executor.folder) if executor.folder else folder),
                                   cluster=executor.cluster)
    parameters["timeout_min"] = executor.timeout_min
    if runner.cluster == "slurm":
        parameters["slurm_array_parallelism"] = executor.array_parallelism
        if executor.partition:
            parameters["slurm_partition"] = executor.partition
    runner.update_parameters(**parameters)
    return runner.map_array(function, *columns)


def _as_they_end(jobs: list) -> Iterator[tuple[int, Any]]:
    """``(index, result)`` of each submitit job as it ends (a job's error raised here)."""
    pending = dict(enumerate(jobs))
    while pending:
        finished = [index for index, job in pending.items() if job.done()]
        for index in finished:
            yield index, pending.pop(index).result()
        if pending and not finished:
            time.sleep(0.2)


def task_host() -> str:
    """Where this process runs: the host's name, and the Ray node's id (its first 8 characters) inside a Ray
    task, so that two nodes on one machine are told apart."""
    host = socket.gethostname()
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        try:
            return f"{host}/ray-node-{ray.get_runtime_context().get_node_id()[:8]}"
        except Exception:  # noqa: BLE001 - not inside a task of a connected worker: the host alone
            return host
    return host


def run_remote_tasks(executor: Executor, function: Callable, calls: Sequence[tuple], folder: Path,
                     on_done: Callable[[int, Any], None] | None = None) -> list:
    """``[function(*call) for call in calls]`` as tasks of a ``ray`` or ``slurm`` executor, one CPU and
    ``executor.task_memory_mb`` each; results in the order of ``calls``.

    ``function`` and its arguments cross to the workers by pickle (cloudpickle), at submission: what should travel
    by path is the caller's to arrange (:mod:`pushtorch.experiments.tasks`). A Ray task whose worker dies is run
    again (``max_retries``); a Slurm array (submitit, its job files under ``folder``) runs one task per call.
    ``on_done(index, result)`` is called here as each finishes.

    Raises:
        InvalidParameterError: a local executor, one that cannot start (:func:`slurm_problem`), or a Ray cluster
            without a node of ``task_memory_mb``;
        MissingDependencyError: its extra is not installed; whatever a task raised.
    """
    calls = list(calls)
    results: list = [None] * len(calls)
    for index, result in submit_remote_tasks(executor, function, calls, folder):
        results[index] = result
        if on_done is not None:
            on_done(index, result)
    return results


def submit_remote_tasks(executor: Executor, function: Callable, calls: Sequence[tuple],
                        folder: Path) -> Iterator[tuple[int, Any]]:
    """:func:`run_remote_tasks`'s tasks, every one submitted (and so pickled) before this returns; then
    ``(index, result)`` of each as it finishes, in the order they finish (a task's error raised there)."""
    calls = list(calls)
    if not calls:
        return iter(())
    if executor.kind == "ray":
        ray = _ray_session(executor)
        largest = max((node["Resources"].get("memory", 0.0) for node in ray.nodes() if node.get("Alive")),
                      default=0.0) / 2**20
        if largest < executor.task_memory_mb:  # Ray would wait for such a node forever
            raise InvalidParameterError(
                f"executor.task_memory_mb={executor.task_memory_mb}: no node of this Ray cluster offers that much "
                f"memory (the largest offers {largest:.0f} MB); lower it, or add a larger node")
        remote = ray.remote(num_cpus=1, memory=int(executor.task_memory_mb) * 2**20,
                            max_retries=int(executor.max_retries))(function)
        # each argument is put once: a closure shared by every call is serialised once, not per task
        puts: dict[int, Any] = {}
        refs = {}
        for index, call in enumerate(calls):
            args = [puts[id(a)] if id(a) in puts else puts.setdefault(id(a), ray.put(a)) for a in call]
            refs[remote.remote(*args)] = index
        return _as_ray_ends(ray, refs)
    if executor.kind != "slurm":
        raise InvalidParameterError(f"executor {executor.kind!r} runs no remote tasks")
    if problem := slurm_problem(executor):
        raise InvalidParameterError(problem)
    jobs = _slurm_array(_require("submitit", "slurm"), executor, folder, function,
                        [list(column) for column in zip(*calls, strict=True)], cpus_per_task=1,
                        mem_gb=executor.task_memory_mb / 1024)
    return _as_they_end(jobs)


def _as_ray_ends(ray, refs: dict) -> Iterator[tuple[int, Any]]:
    """``(index, result)`` of each Ray task of ``refs`` (object ref → index) as it ends."""
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield refs[done[0]], ray.get(done[0])


def executor_pool(executor: Executor, spec, settings):
    """The pool of a non-local executor (:class:`RayPool` or :class:`SlurmPool`)."""
    if executor.kind == "ray":
        return RayPool(spec, settings, executor)
    if executor.kind == "slurm":
        return SlurmPool(spec, settings, executor)
    raise InvalidParameterError(f"executor {executor.kind!r} has no remote pool")
