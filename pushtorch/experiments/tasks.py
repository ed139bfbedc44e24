"""An experiment's work as tasks in worker processes (no paper section): what a part's serial loop reads from its
run folder's caches, computed first by the runner's task workers (:func:`pushtorch.sim.tasks.run_tasks`).

A part's steps are cached in the run folder (training pushes and models, prediction sets with their peers,
ground truth, likelihood scores), each keyed by what made it. :func:`prefetch` runs a step for many keys in
forked worker processes, one per core with one torch thread each, before the part's own loop: the loop then
finds every cache filled and only reads, records and logs, in its usual order. So a part's records are those of
a serial run, a killed run resumes from whatever the tasks wrote, and the recording is written by one process.

Inside a task the context simulates in its own process (``workers=1``), logs nothing to the recording and shows
no progress bars; the part's bar advances as tasks finish. Nothing is prefetched with one core (the loop does
the work itself, as before), or with ``executor=ray|slurm``, whose pushes go to the cluster from the loop.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

from pushtorch.experiments.context import ExperimentContext
from pushtorch.sim.tasks import run_tasks, task_workers

__all__ = ["prefetch", "warm_up"]

log = logging.getLogger("pushtorch.experiments")

#: What :func:`_run` works on, set before the workers fork: task index → (step, task context, item).
_STATE: dict[int, tuple[Callable[[ExperimentContext, Any], Any], ExperimentContext, Any]] = {}
_WARM: list[bool] = []  # warm_up ran in this process


def _run(index: int) -> float:
    """Task ``index``; returns its seconds."""
    start = time.perf_counter()
    step, ctx, item = _STATE[index]
    step(ctx, item)
    return time.perf_counter() - start


def warm_up(model) -> None:
    """Compile the fast path's fused functions in this process, once, by one prediction of a cube with ``model``:
    workers forked afterwards inherit the compiled code. Without it every worker of every part compiles them
    again (torch.compile traces per process: seconds each on a small host). Nothing to do where the fast path
    runs eagerly (:func:`pushtorch.kde.fast_path_compiled`)."""
    from pushtorch.kde import fast_path_compiled
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.prediction import predict

    if _WARM or not fast_path_compiled(model.motions[0].action.device):
        return
    cube = load_object("cube")
    predict(model, capture_partial_cloud(cube, cube.resting_pose(yaw=0.3), voxel_size=model.settings.voxel_size),
            model.actions[0])
    _WARM.append(True)


def prefetch(ctx: ExperimentContext, step: Callable[[ExperimentContext, Any], Any], items: Sequence[Any],
             on_done: Callable[[Any], None] | None = None, warm=None, what: str = "tasks") -> bool:
    """Run ``step(task_ctx, item)`` for every item in worker processes, for the caches it writes (module notes).

    Args:
        ctx: the part's context; the tasks get a copy that simulates in-process and records nothing.
        step: what fills an item's caches; its return value is dropped (the loop reads the caches).
        items: one per task (they stay in this process: the workers inherit them).
        on_done: called with each item as its task finishes (a progress bar).
        warm: a model the tasks predict with: the fast path is compiled with it here first (:func:`warm_up`).
        what: what the items are, for the log line that times them.

    Returns:
        Whether the items ran in workers (False: nothing was done, the loop does the work).
    """
    items = list(items)
    if ctx.executor.kind != "local" or task_workers(len(items), ctx.workers) <= 1:
        return False
    if warm is not None:
        warm_up(warm)
    task_ctx = dataclasses.replace(ctx, workers=1, recording=None, progress=False, logged_predictions=[])
    _STATE.clear()
    _STATE.update({i: (step, task_ctx, item) for i, item in enumerate(items)})
    start = time.perf_counter()
    try:
        seconds = run_tasks(_run, range(len(items)), ctx.workers,
                            on_done=None if on_done is None else (lambda index, _: on_done(items[index])))
    finally:
        _STATE.clear()
    log.info("%d %s in %d worker processes: %.0f s (%.0f s of work, the longest %.0f s)", len(items), what,
             task_workers(len(items), ctx.workers), time.perf_counter() - start, sum(seconds), max(seconds))
    return True
