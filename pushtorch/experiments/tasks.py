"""An experiment's work as tasks in worker processes (no paper section): what a part's serial loop reads from its
run folder's caches, computed by the runner's task workers (:func:`pushtorch.sim.tasks.iter_tasks`).

A part's steps are cached in the run folder (training pushes and models, prediction sets with their peers,
ground truth, likelihood scores), each keyed by what made it. :func:`prefetched` starts a step for many keys in
forked worker processes, one per core with one torch thread each, and hands the part's loop each key, in order,
as soon as its task and every earlier one ended: the loop finds that key's caches filled and only reads, records
and logs, in its usual order, while the later tasks run (:func:`prefetch` waits for all of them). So a part's
records are those of a serial run, a killed run resumes from whatever the tasks wrote, and the recording is
written by one process. Work that writes its own outputs (the report's figures) is spread by
:func:`spread_calls`.

Inside a task the context simulates in its own process (``workers=1``), logs nothing to the recording and shows
no progress bars; the part's bar advances as tasks finish. Nothing is prefetched with one core on the local
executor (the loop does the work itself, as before).

With ``executor=ray`` or ``executor=slurm`` the same tasks run on the cluster
(:func:`pushtorch.sim.executors.submit_remote_tasks`), one CPU and one torch thread each, into the run folder that
every node shares; the submitting process plans, then its loop reads the caches and writes the report. What a
task needs crosses by pickle, with two exceptions: a model an experiment trained travels as its file's path and
is read again there (:func:`saved_as`), and an experiment context travels
as the task's context (no recording, no model cache, the local executor with one worker), wherever a step holds
one. A task compiles the fast path exactly when the submitting process does, so that its records are those of
a local run on the same host and thread count; on nodes with other CPUs floats may differ in their last bits.
Tasks that predict share the submitter's compiled functions (:func:`share_with_tasks`): saved once per code
version and machine kind, each task loads them instead of tracing them again, with the same generated code.
Each task says where it ran; the counts per kind and host are kept in the context (``task_counts``) and written
to results.json (``tasks``).
"""

from __future__ import annotations

import copyreg
import dataclasses
import logging
import os
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from pushtorch.experiments.context import ExperimentContext
from pushtorch.sim.executors import Executor, run_remote_tasks, submit_remote_tasks, task_host
from pushtorch.sim.tasks import iter_tasks, run_tasks, task_workers

__all__ = ["models_by_path", "prefetch", "prefetched", "saved_as", "saved_models", "share_with_tasks", "spread_calls",
           "warm_up"]

log = logging.getLogger("pushtorch.experiments")

#: Every live model this process trained or read for an experiment, by ``id``: (a weak reference to it, how to
#: read it again, its arguments). An entry leaves with its model.
_SAVED: dict[int, tuple[weakref.ref, Callable, tuple]] = {}

#: What :func:`_run` works on, set before the workers fork: task index → (step, task context, item).
_STATE: dict[int, tuple[Callable[[ExperimentContext, Any], Any], ExperimentContext, Any]] = {}
_WARM: list[bool] = []  # warm_up ran in this process


def _run(index: int) -> tuple[float, str]:
    """Task ``index``; returns its seconds and where it ran."""
    start = time.perf_counter()
    step, ctx, item = _STATE[index]
    step(ctx, item)
    return time.perf_counter() - start, f"{task_host()} (local workers)"


def saved_as(model, reader: Callable, *arguments):
    """``model``, noted as one that ``reader(*arguments)`` reads again from its file on the shared run folder:
    a task on a cluster receives it as that path, not as pickled tensors. Returns ``model``."""
    key = id(model)

    def forget(ref: weakref.ref) -> None:
        if _SAVED.get(key, (None,))[0] is ref:
            del _SAVED[key]

    _SAVED[key] = (weakref.ref(model, forget), reader, arguments)
    return model


def saved_models() -> dict[int, tuple[Any, Callable, tuple]]:
    """``{id(model): (model, reader, arguments)}`` of every live model :func:`saved_as` noted in this process."""
    return {key: (model, reader, arguments) for key, (ref, reader, arguments) in list(_SAVED.items())
            if (model := ref()) is not None}


def warm_up(model) -> None:
    """Compile the fast path's fused functions in this process, once, by predictions of a cube with ``model`` on
    one torch thread, as the workers run, one of them keeping its annealing history, as the workers that log
    examples do: workers forked afterwards inherit the compiled code. Without it every worker of every part
    compiles them again (torch.compile traces per process: seconds each on a small host); compiled on the
    parent's threads, the same (Inductor's guards hold the thread count: a 1-thread worker compiled again, its
    first prediction 20 s on a 2-core host against 0.45 s, ``tools/bench_worker_compile.py``). Nothing to do
    where the fast path runs eagerly (:func:`pushtorch.kde.fast_path_compiled`)."""
    import torch

    from pushtorch.kde import fast_path_compiled

    if _WARM or not fast_path_compiled(model.motions[0].action.device):
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _predict_a_cube(model, history=True)
    finally:
        torch.set_num_threads(threads)
    _WARM.append(True)


def _predict_a_cube(model, history: bool = False) -> None:
    """One prediction of a cube with ``model``: what compiles the fast path's fused functions; with ``history``, a
    second one that keeps its annealing history, as an example for the recording does (the generic annealing
    steps, compiled on their own)."""
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.prediction import predict

    cube = load_object("cube")
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.3), voxel_size=model.settings.voxel_size)
    for record_history in (False, True) if history else (False,):
        predict(model, cloud, model.actions[0], record_history=record_history)


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
    return any([done for _, done in prefetched(ctx, step, items, on_done, warm, what)])  # a list: every item taken


def prefetched(ctx: ExperimentContext, step: Callable[[ExperimentContext, Any], Any], items: Sequence[Any],
               on_done: Callable[[Any], None] | None = None, warm=None,
               what: str = "tasks") -> Iterator[tuple[Any, bool]]:
    """:func:`prefetch`'s tasks, started before this returns; then every item, in order, with whether a task filled
    its caches, each as soon as its task and every earlier one finished. A part's loop reads, records and logs one
    item while the tasks go on with the later ones, and does its other work (what it draws from the training
    pushes) while they start; its records stay those of a serial run. The tasks' counts and the line that times
    them come when the last item is taken."""
    items = list(items)
    if not items:
        return iter(())
    start = time.perf_counter()
    if ctx.executor.kind != "local":
        return _in_order(ctx, items, _submit_remote(ctx, step, items, warm), on_done, what, start,
                         f"as {ctx.executor.kind} tasks on {{hosts}}")
    workers = task_workers(len(items), ctx.workers)
    if workers <= 1:
        return ((item, False) for item in items)
    if warm is not None:
        warm_up(warm)
    task_ctx = dataclasses.replace(ctx, workers=1, recording=None, progress=False, logged_predictions=[],
                                   keep_examples=_keeps_examples(ctx))
    keys = _keep(_STATE, [(step, task_ctx, item) for item in items])
    return _in_order(ctx, items, iter_tasks(_run, keys, ctx.workers), on_done, what, start,
                     f"in {workers} worker processes", keys)


def _in_order(ctx: ExperimentContext, items: list, finished: Iterator[tuple[int, tuple[float, str]]],
              on_done: Callable[[Any], None] | None, what: str, start: float, how: str,
              keys: range | None = None) -> Iterator[tuple[Any, bool]]:
    """Every item with True as soon as it and every earlier one finished (``finished`` gives each task's index,
    seconds and host as it ends); then the tasks' counts and their timing line, which says ``how`` they ran (its
    ``{hosts}``: each host with its task count)."""
    seconds: list[float] = []
    hosts: dict[str, int] = {}
    ended: set[int] = set()
    taken = 0
    try:
        for index, (took, where) in finished:
            seconds.append(took)
            hosts[where] = hosts.get(where, 0) + 1
            if on_done is not None:
                on_done(items[index])
            ended.add(index)
            while taken in ended:
                taken += 1
                yield items[taken - 1], True
    finally:
        getattr(finished, "close", lambda: None)()
        for key in keys or ():
            _STATE.pop(key, None)
    for where, count in hosts.items():
        _count(ctx, what, where, count)
    where = ", ".join(f"{h} ({n})" for h, n in sorted(hosts.items()))
    log.info("%d %s %s: %.0f s (%.0f s of work, the longest %.0f s)", len(items), what, how.format(hosts=where),
             time.perf_counter() - start, sum(seconds), max(seconds))


def spread_calls(ctx: ExperimentContext, function: Callable, calls: Sequence[tuple], what: str) -> list:
    """``[function(*call) for call in calls]``, spread where the context's executor allows: Ray tasks on
    ``executor=ray`` (``function`` and the calls cross by pickle), forked worker processes on the local executor,
    and this process on Slurm (an array's queue costs more than such small work) or with one worker. For work
    that writes its own outputs, such as the figures; results in the order of ``calls``."""
    calls = list(calls)
    if ctx.executor.kind == "ray" and len(calls) > 1:
        start = time.perf_counter()
        results = run_remote_tasks(ctx.executor, function, calls, ctx.run_dir / ".submitit" / what)
        log.info("%d %s as ray tasks: %.1f s", len(calls), what, time.perf_counter() - start)
        return results
    if ctx.executor.kind != "local" or task_workers(len(calls), ctx.workers) <= 1:
        return [function(*call) for call in calls]
    keys = _keep(_CALLS, [(function, call) for call in calls])
    try:
        return run_tasks(_call, keys, ctx.workers)
    finally:
        for key in keys:
            _CALLS.pop(key, None)


#: What :func:`_call` works on, set before the workers fork: key → (function, its arguments).
_CALLS: dict[int, tuple[Callable, tuple]] = {}


def _call(key: int):
    function, call = _CALLS[key]
    return function(*call)


def _keep(state: dict[int, Any], values: list) -> range:
    """``values`` put in ``state`` (what forked workers read by key) under keys of their own, which it returns:
    another batch's entries may still be there."""
    base = len(state) and max(state) + 1
    keys = range(base, base + len(values))
    state.update(zip(keys, values, strict=True))
    return keys


def _count(ctx: ExperimentContext, what: str, where: str, count: int) -> None:
    """``count`` more tasks of kind ``what`` ran at ``where`` (results.json's ``tasks``)."""
    key = f"{what} | {where}"
    ctx.task_counts[key] = ctx.task_counts.get(key, 0) + count


def _keeps_examples(ctx: ExperimentContext) -> bool:
    """Whether a task of ``ctx`` keeps the examples its recording logs (the run records, or ``ctx`` is a task's)."""
    return ctx.recording is not None or ctx.keep_examples


def _task_context(ctx: ExperimentContext) -> ExperimentContext:
    """What a remote task works with: the context without its recording and model cache, simulating in its own
    process on the local executor; it keeps the examples a recording logs (``keep_examples``)."""
    return dataclasses.replace(ctx, workers=1, executor=Executor(), recording=None, progress=False,
                               keep_examples=_keeps_examples(ctx), logged_predictions=[],
                               task_counts={}, _models={}, _slots=[0], _truth_plan=None)


def _rebuild_context(fields: dict) -> ExperimentContext:
    return ExperimentContext(**fields)


def _reduce_context(ctx: ExperimentContext):
    task = _task_context(ctx)
    return _rebuild_context, ({f.name: getattr(task, f.name) for f in dataclasses.fields(task)},)


def _reduce_saved(model):
    """A model this process trained or read: its file's path, read again where it is unpickled."""
    entry = _SAVED.get(id(model))
    if entry is None or entry[0]() is not model:
        return model.__reduce_ex__(4)
    return entry[1], entry[2]


@contextmanager
def models_by_path() -> Iterator[None]:
    """While open, pickling sends trained models as their files' paths and contexts as task contexts."""
    reducers: dict[type, Callable] = {type(entry[0]): _reduce_saved for entry in saved_models().values()}
    reducers[ExperimentContext] = _reduce_context
    before = {kind: copyreg.dispatch_table.get(kind) for kind in reducers}
    copyreg.dispatch_table.update(reducers)
    try:
        yield
    finally:
        for kind, old in before.items():
            if old is None:
                copyreg.dispatch_table.pop(kind, None)
            else:
                copyreg.dispatch_table[kind] = old


def _remote_task(step: Callable[[ExperimentContext, Any], Any], ctx: ExperimentContext, item: Any,
                 compiled: bool, shared: bool) -> tuple[float, str]:
    """One task on a cluster's worker: ``step(ctx, item)`` on one torch thread, compiled as its submitter
    compiles (with ``shared``, by the compiled functions it shares); returns its seconds and where it ran."""
    import torch

    from pushtorch.kde import share_compiled

    start = time.perf_counter()
    torch.set_num_threads(1)
    os.environ["PUSHTORCH_COMPILE"] = "1" if compiled else "0"
    if shared:
        share_compiled()
    step(ctx, item)
    return time.perf_counter() - start, task_host()


def share_with_tasks(model) -> None:
    """Share this process's compiled fast path with the tasks it submits (:func:`pushtorch.kde.share_compiled`):
    where this code has not been compiled ahead of time on this machine kind, a prediction of a cube with
    ``model`` on one torch thread, as a task predicts, and one that keeps its annealing history, as the tasks that
    log examples do, compile and save what a prediction needs (once: about 40 s on a 2-core CPU); a task then
    loads them (about 2 s) instead of compiling them (about 11 s, and 2.5 s more in each worker that logs an
    example)."""
    import torch

    from pushtorch.kde import share_compiled

    folder = share_compiled(produce=True)
    if not (folder / _SHARED_READY).is_file():
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # as a task runs: Inductor's code, and so its guards, depend on the threads
        try:
            _predict_a_cube(model, history=True)  # the tasks that log examples keep histories
        finally:
            torch.set_num_threads(threads)
        try:
            (folder / _SHARED_READY).write_text("a prediction's fused functions are saved here\n")
        except OSError as exc:  # a read-only cache: the tasks compile in-process, as without sharing
            log.warning("compiled functions not shared with the tasks: %s", exc)


_SHARED_READY = "ready"


def _submit_remote(ctx: ExperimentContext, step: Callable[[ExperimentContext, Any], Any],
                   items: list, warm=None) -> Iterator[tuple[int, tuple[float, str]]]:
    """Every item as a task of the context's Ray or Slurm executor, submitted before this returns (module notes);
    then each task's index, seconds and host as it ends."""
    from pushtorch.kde import fast_path_compiled

    compiled = fast_path_compiled("cpu")
    shared = compiled and warm is not None
    if shared:
        share_with_tasks(warm)
    with models_by_path():
        task_ctx = _task_context(ctx)  # one object: put once for every task
        return submit_remote_tasks(ctx.executor, _remote_task,
                                   [(step, task_ctx, item, compiled, shared) for item in items],
                                   ctx.run_dir / ".submitit" / "tasks")
