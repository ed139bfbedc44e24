"""Running many pushes: in process, or in parallel worker processes writing resumable shards.

Paper, Experimental Setup and the parameter tables (500 samples per action for training, 3 per push
condition for ground truth: tens of thousands of pushes). Each worker holds one pybullet DIRECT client
and one :class:`PushWorld`, built once; a task is one shard of consecutive pushes of the plan, simulated
and written by the worker itself (atomically, :mod:`pushtorch.sim.worker`). Because every push's
inputs are fixed by the plan and a world keeps no state from one push to the next, the shards do not
depend on the number of workers or on their order, and a run that was killed resumes by simulating only
the shards that have no finished manifest.

A run claims its shard folder for as long as it runs: it holds the folder's lock
(:func:`pushtorch.io.folder_lock`, a lock file that holds across the nodes of a shared filesystem) while it
checks or writes ``manifest.json`` and simulates, so a second run into the same folder, on this machine or
another, is refused at once (:class:`~pushtorch.errors.FolderInUseError`) and two runs with different plans
can never both pass the manifest check. A killed run's lock is broken at once by the next run on the same
machine, and expires a minute after its last heartbeat on any other.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.io import atomic_write_bytes, folder_lock
from pushtorch.parallel import core_share
from pushtorch.sim.engines import make_world
from pushtorch.sim.geometry import check_inside_world
from pushtorch.sim.plan import PushPlan
from pushtorch.sim.records import TABLE, PushRecords, records_from_arrays, write_table
from pushtorch.sim.run_manifest import RUN_MANIFEST, plan_digests, read_run_manifest
from pushtorch.sim.settings import WORLD_VERSION, ObjectSpec, SimSettings, object_spec
from pushtorch.sim.shards import FORMAT, VERSION, complete_shards
from pushtorch.sim.worker import run_shard_in, simulate_arrays

__all__ = [
    "PushPool",
    "RunSummary",
    "default_workers",
    "run_plan",
    "simulate_plan",
    "simulate_pushes",
]

MANIFEST = RUN_MANIFEST
#: Run-manifest keys derived from the plan (``plan_sha256`` already covers them): a folder written before
#: they existed resumes and gains them; "resume" only says how to resume and is never compared.
_DERIVED_KEYS = ("index_first", "index_sha256", "action_sha256", "action_runs", "actions")


def default_workers() -> int:
    """Simulation workers when none are asked for: this job's share of the cores
    (:func:`pushtorch.parallel.core_share`)."""
    return core_share()


def _check_plan_inside_world(spec: ObjectSpec, settings: SimSettings, plan: PushPlan) -> None:
    check_inside_world(spec, settings, plan.object_initial.p.numpy(), plan.object_initial.q.numpy(),
                       plan.robot_start.p.numpy(), plan.action[:, 0].numpy(), plan.duration)


def simulate_plan(spec: ObjectSpec, plan: PushPlan, settings: SimSettings | None = None) -> PushRecords:
    """Simulate a (small) plan in this process and return its records as float64 tensors, no files.

    Raises:
        InvalidParameterError: the plan is for another object than ``spec``.
    """
    if plan.object_name != spec.name:
        raise InvalidParameterError(f"the plan pushes {plan.object_name!r} but the spec is {spec.name!r}")
    _check_plan_inside_world(spec, settings or SimSettings(), plan)
    with make_world(spec, settings) as world:
        arrays = simulate_arrays(world, plan.arrays(), spec.name, plan.seed, plan.duration)
    return records_from_arrays(arrays, dtype=torch.float64)


def simulate_pushes(
    model,
    robot_start: se3.Pose,
    object_initial: se3.Pose,
    action: torch.Tensor,
    mass: torch.Tensor | float,
    ground_friction: torch.Tensor | float,
    settings: SimSettings | None = None,
    duration: float = 4.0,
) -> PushRecords:
    """Ground truth for arbitrary pushes (e.g. a predicted robot start pose), in this process.

    Args:
        model: the :class:`pushtorch.objects.ObjectModel` pushed.
        robot_start: base poses ``(...)`` on the ground (any pose: prediction chooses it).
        object_initial: object poses ``(...)``.
        action: ``(..., 2)`` (ẋ m/s, θ̇ rad/s).
        mass, ground_friction: ``(...)`` or scalars.
        settings: simulator settings.
        duration: s per push.

    Returns:
        :class:`PushRecords` (float64) of the flattened broadcast batch, in row-major order.

    Raises:
        InvalidParameterError, InvalidPoseError: shapes that do not broadcast, or invalid values.
    """
    action = torch.as_tensor(action, dtype=torch.float64)
    mass = torch.as_tensor(mass, dtype=torch.float64)
    friction = torch.as_tensor(ground_friction, dtype=torch.float64)
    try:
        shape = torch.broadcast_shapes(
            robot_start.batch_shape, object_initial.batch_shape, action.shape[:-1], mass.shape, friction.shape
        )
    except RuntimeError as exc:
        raise InvalidParameterError(f"push inputs do not broadcast: {exc}") from exc
    n = int(np.prod(shape)) if len(shape) else 1

    def flat(pose: se3.Pose) -> se3.Pose:
        return se3.Pose.unchecked(pose.p.double().expand(*shape, 3).reshape(n, 3),
                        pose.q.double().expand(*shape, 4).reshape(n, 4))

    plan = PushPlan(
        object_name=model.name,
        robot_start=flat(robot_start),
        object_initial=flat(object_initial),
        action=action.expand(*shape, 2).reshape(n, 2),
        mass=mass.expand(shape).reshape(n),
        ground_friction=friction.expand(shape).reshape(n),
        duration=duration,
    )
    return simulate_plan(object_spec(model), plan, settings)


# --- worker processes ------------------------------------------------------------------------------

_WORKER_WORLD = None  # the worker's world (make_world)


def _init_worker(spec: ObjectSpec, settings: SimSettings) -> None:
    global _WORKER_WORLD
    _WORKER_WORLD = make_world(spec, settings)


def _run_shard(task: tuple[int, str, dict[str, np.ndarray], str, int, float]) -> tuple[int, int, int]:
    assert _WORKER_WORLD is not None, "worker used before its initializer ran"
    return run_shard_in(_WORKER_WORLD, task)


@dataclass
class RunSummary:
    """What :func:`run_plan` did.

    Attributes:
        folder: the shard folder.
        pushes: pushes in the plan; shards: shards in the plan.
        resumed_shards: shards found finished and skipped; simulated_pushes: pushes simulated now.
        valid_pushes: valid pushes among those simulated now.
        seconds: wall time of the simulation (pool start-up excluded when a pool was passed in).
    """

    folder: Path
    pushes: int
    shards: int
    resumed_shards: int
    simulated_pushes: int
    valid_pushes: int
    seconds: float

    @property
    def pushes_per_second(self) -> float:
        return self.simulated_pushes / self.seconds if self.seconds > 0 else float("nan")


class PushPool:
    """Worker processes, each with its own pybullet client and world for one object.

    Use as a context manager; :meth:`run` may be called several times (e.g. a warm-up and a timed run).

    Args:
        spec: the object.
        settings: simulator settings.
        workers: number of processes (0: all cores).
        start_method: multiprocessing start method; default ``fork`` where available (workers start in
            milliseconds and need no torch), else ``spawn``.
    """

    def __init__(self, spec: ObjectSpec, settings: SimSettings | None = None, workers: int = 0,
                 start_method: str | None = None):
        self.spec = spec
        self.settings = settings or SimSettings()
        self.workers = int(workers) if workers else default_workers()
        if self.workers < 1:
            raise InvalidParameterError(f"workers must be >= 1 (or 0 for all cores), got {workers!r}")
        methods = mp.get_all_start_methods()
        linux_fork = "fork" in methods and sys.platform.startswith("linux")
        method = start_method or ("fork" if linux_fork else "spawn")
        if method not in methods:
            raise InvalidParameterError(
                f"start method {method!r} is not available here ({', '.join(methods)})"
            )
        self._pool = mp.get_context(method).Pool(
            self.workers, initializer=_init_worker, initargs=(self.spec, self.settings)
        )

    def run(
        self, plan: PushPlan, folder: str | Path, shard_size: int = 100, progress: bool = True,
        resume: str | None = None,
    ) -> RunSummary:
        """Simulate ``plan`` into shards in ``folder`` (see :func:`run_plan`)."""
        return _run(plan, Path(folder), self.spec, self.settings, shard_size, progress, self._pool, resume)

    def close(self) -> None:
        self._pool.close()
        self._pool.join()

    def terminate(self) -> None:
        self._pool.terminate()
        self._pool.join()

    def __enter__(self) -> PushPool:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.terminate()


def _manifest(plan: PushPlan, spec: ObjectSpec, settings: SimSettings, shard_size: int,
              resume: str | None = None) -> dict:
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "object": spec.name,
        "pushes": len(plan),
        "seed": plan.seed,
        "duration": plan.duration,
        "shard_size": int(shard_size),
        "plan_sha256": plan.fingerprint(),
        "settings": asdict(settings),
        "world": WORLD_VERSION,
    }
    manifest.update(plan_digests(plan.index.numpy(), plan.action_index.numpy(), plan.action.numpy()))
    manifest["resume"] = resume
    return manifest


def _differences(existing: dict, manifest: dict, changed: list[str]) -> list[str]:
    """The changed manifest keys, with the simulator settings that differ named one by one (``sim.robot:
    'ideal' -> 'p3dx'``): pushes of another robot or world are never mixed into a run."""
    out = []
    for key in changed:
        old, new = existing.get(key), manifest.get(key)
        if key == "settings" and isinstance(old, dict) and isinstance(new, dict):
            out += [f"sim.{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in sorted(set(old) | set(new))
                    if old.get(k) != new.get(k)]
        else:
            out.append(key)
    return out


def _prepare_folder(folder: Path, manifest: dict) -> None:
    """Check ``folder``'s run manifest against ``manifest`` (or write it) and drop killed writers'
    temporaries; the caller holds the folder's lock, so no other writer is between check and write."""
    for stale in folder.glob(".shard-*.tmp-*"):  # left by a killed writer; never a finished shard
        stale.unlink(missing_ok=True)
    for stale in folder.glob(f".{MANIFEST}.tmp-*"):
        stale.unlink(missing_ok=True)
    path = folder / MANIFEST
    existing = read_run_manifest(folder)  # refuses an unreadable manifest and pushes of another world
    if existing is not None:
        changed = [k for k in manifest if k != "resume" and (k not in _DERIVED_KEYS or k in existing)
                   and existing.get(k) != manifest.get(k)]
        if changed:
            differences = ", ".join(_differences(existing, manifest, changed))
            raise RecordFormatError(
                f"{folder} holds shards of a different run (differs in {differences}); "
                "use a fresh folder or the same configuration to resume"
            )
        if any(k not in existing for k in _DERIVED_KEYS) or (existing.get("resume") is None and manifest["resume"]):
            upgraded = {**existing, **{k: manifest[k] for k in _DERIVED_KEYS}}
            upgraded["resume"] = existing.get("resume") or manifest["resume"]
            atomic_write_bytes(path, json.dumps(upgraded, indent=1).encode())
    else:
        atomic_write_bytes(path, json.dumps(manifest, indent=1).encode())


def _run(plan: PushPlan, folder: Path, spec: ObjectSpec, settings: SimSettings, shard_size: int,
         progress: bool, pool, resume: str | None = None) -> RunSummary:
    if plan.object_name != spec.name:
        raise InvalidParameterError(
            f"the plan pushes {plan.object_name!r} but the workers hold {spec.name!r}"
        )
    if isinstance(shard_size, bool) or int(shard_size) != shard_size or shard_size < 1:
        raise InvalidParameterError(f"shard_size must be a positive integer, got {shard_size!r}")
    _check_plan_inside_world(spec, settings, plan)  # before any folder is made
    folder.mkdir(parents=True, exist_ok=True)
    # claimed for the whole run: the manifest check and write, and every shard written under it
    with folder_lock(folder, wait=False, holder="another simulation run (it holds the folder's lock)"):
        return _run_claimed(plan, folder, spec, settings, int(shard_size), progress, pool, resume)


def _run_claimed(plan: PushPlan, folder: Path, spec: ObjectSpec, settings: SimSettings, shard_size: int,
                 progress: bool, pool, resume: str | None) -> RunSummary:
    from tqdm import tqdm

    _prepare_folder(folder, _manifest(plan, spec, settings, shard_size, resume))
    n = len(plan)
    n_shards = (n + shard_size - 1) // shard_size
    done = {k for k in complete_shards(folder) if k < n_shards}
    todo = [k for k in range(n_shards) if k not in done]
    done_pushes = sum(min(shard_size, n - k * shard_size) for k in done)
    tasks = [
        (k, str(folder), plan.arrays(k * shard_size, min(n, (k + 1) * shard_size)), spec.name, plan.seed,
         plan.duration)
        for k in todo
    ]
    simulated = valid = 0
    start = time.perf_counter()
    with tqdm(total=n, initial=done_pushes, unit="push", desc=f"pushing {spec.name}", disable=not progress,
              dynamic_ncols=True) as bar:
        if pool is None:
            global _WORKER_WORLD
            previous = _WORKER_WORLD
            _WORKER_WORLD = make_world(spec, settings)
            try:
                results = (_run_shard(task) for task in tasks)
                for _, count, ok in results:
                    simulated, valid = simulated + count, valid + ok
                    bar.update(count)
            finally:
                _WORKER_WORLD.close()
                _WORKER_WORLD = previous
        else:
            for _, count, ok in pool.imap_unordered(_run_shard, tasks):
                simulated, valid = simulated + count, valid + ok
                bar.update(count)
    seconds = time.perf_counter() - start
    if not (folder / TABLE).is_file() or todo:  # the per-push table of the finished run (pushtorch.sim.records.TABLE)
        write_table(folder)
    return RunSummary(folder, n, n_shards, len(done), simulated, valid, seconds)


def run_plan(
    spec: ObjectSpec,
    plan: PushPlan,
    folder: str | Path,
    settings: SimSettings | None = None,
    workers: int = 0,
    shard_size: int = 100,
    progress: bool = True,
    start_method: str | None = None,
    resume: str | None = None,
    executor=None,
) -> RunSummary:
    """Simulate every push of ``plan`` into shards in ``folder``, in parallel, resuming a killed run.

    Shard ``k`` holds pushes ``k*shard_size ...``; shards already finished in ``folder`` are skipped. A
    ``manifest.json`` ties the folder to its plan and settings: resuming with anything changed raises.

    Args:
        spec: the object (its :class:`ObjectSpec`).
        plan: the pushes.
        folder: where the shards go (created).
        settings: simulator settings.
        workers: processes (0: all cores; 1: in this process, no pool).
        shard_size: pushes per shard (and per task).
        progress: show a tqdm progress bar.
        start_method: see :class:`PushPool`.
        resume: how a user resumes this run if it is killed (e.g. the command line), kept in the run
            manifest for the message of :func:`pushtorch.sim.records.load_records`.
        executor: where the shards run (:class:`pushtorch.sim.executors.Executor`; None or ``local``: this
            machine's processes, ``workers`` of them). The records do not depend on it.

    Returns:
        A :class:`RunSummary`.

    Raises:
        InvalidParameterError: bad sizes, or a plan for another object.
        RecordFormatError: ``folder`` holds shards of a different run.
        FolderInUseError: another run is writing into ``folder`` now.
    """
    settings = settings or SimSettings()
    folder = Path(folder)
    if executor is not None and executor.kind != "local":
        from pushtorch.sim.executors import executor_pool

        with executor_pool(executor, spec, settings) as pool:  # refused before anything is written
            return _run(plan, folder, spec, settings, shard_size, progress, pool, resume)
    workers = int(workers) if workers else default_workers()
    if workers == 1:
        return _run(plan, folder, spec, settings, shard_size, progress, None, resume)
    with PushPool(spec, settings, workers, start_method) as pool:
        return pool.run(plan, folder, shard_size, progress, resume)
