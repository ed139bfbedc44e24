"""Work beyond pushes in worker processes: an experiment's groups of predictions, peers and scores (no paper
section; the paper's experiments ran for days on one machine).

:func:`run_tasks` runs ``function(key)`` for every key in forked worker processes of this machine, one per core
of the job's share (:func:`pushtorch.parallel.core_share`), each with one torch thread: on a small host two
single-threaded processes predict about 1.4 times faster than one process on two threads, and a process's own
rollouts (pybullet, MuJoCo) use one core anyway. The workers are forked, so they inherit what the caller built
before the call (trained models, clouds, the run's context): ``function`` reads it from module state by ``key``,
and only keys and results cross between processes. A task writes its outputs into the run folder atomically, as
a shard does, so a killed run resumes from what the finished tasks wrote.

Tasks run in this process, one after the other, where forking cannot help or is not possible: one task, one
core, a platform without ``fork``, or ``workers=1``. Results are the same either way: a task seeds everything it
draws from its key, never from the order tasks run in. With ``executor=ray`` or ``executor=slurm`` the pushes'
shards go to the cluster and these tasks still run on the submitting machine.
"""

from __future__ import annotations

import multiprocessing as mp
import sys
from collections.abc import Callable, Generator, Hashable, Sequence
from typing import Any

from pushtorch.errors import InvalidParameterError
from pushtorch.parallel import core_share

__all__ = ["iter_tasks", "run_tasks", "task_workers"]


def task_workers(count: int, workers: int = 0) -> int:
    """Processes for ``count`` tasks: ``workers`` (0: the job's cores), at most one per task."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InvalidParameterError(f"workers must be an integer >= 0 (0: all cores), got {workers!r}")
    return max(1, min(int(count), workers or core_share()))


def _init_worker() -> None:
    """One torch thread; and torch.compile able to compile here. Inductor compiles on a pool of threads that a
    fork does not copy, and its after-fork hook clears only its process pool: a worker that compiled a function
    the parent had not would wait for those threads forever (measured: the installed package's tiny quickstart
    hung in ``CppCodeCache.load_async``). With one compile thread Inductor compiles in the calling thread, the
    same code."""
    import torch

    torch.set_num_threads(1)
    if "torch._inductor.async_compile" in sys.modules:
        from torch._inductor import config
        from torch._inductor.async_compile import AsyncCompile

        config.compile_threads = 1
        AsyncCompile.pool.cache_clear()


def run_tasks(function: Callable[[Any], Any], keys: Sequence[Hashable], workers: int = 0,
              on_done: Callable[[Any, Any], None] | None = None) -> list:
    """``[function(key) for key in keys]``, the tasks spread over forked worker processes (module notes).

    Args:
        function: a module-level function (it crosses to the workers by name); what it needs beyond its key it
            reads from state the caller set before this call.
        keys: one per task, small and picklable.
        workers: processes (0: one per core of the job's share, at most one per task; 1: in this process).
        on_done: called in this process as each task finishes, ``on_done(key, result)`` (progress bars).

    Returns:
        The results, in the order of ``keys``.

    Raises:
        Whatever a task raised (the other workers are stopped first).
    """
    keys = list(keys)
    results: list = [None] * len(keys)
    finished = iter_tasks(function, keys, workers)
    try:
        for i, result in finished:
            results[i] = result
            if on_done is not None:
                on_done(keys[i], result)
    finally:
        finished.close()
    return results


def iter_tasks(function: Callable[[Any], Any], keys: Sequence[Hashable],
               workers: int = 0) -> Generator[tuple[int, Any], None, None]:
    """:func:`run_tasks`'s tasks, started before this returns, as ``(index, result)`` in the order of ``keys``, each
    as soon as it finished: the caller works on one result while the workers go on with the later tasks.

    Where the tasks run in this process (module notes) each runs when its result is asked for. Closing the
    iterator early stops the workers; a task's error is raised where its result is asked for (the other workers
    are stopped first)."""
    keys = list(keys)
    count = task_workers(len(keys), workers)
    if count <= 1 or not ("fork" in mp.get_all_start_methods() and sys.platform.startswith("linux")):
        return ((i, function(key)) for i, key in enumerate(keys))
    pool = mp.get_context("fork").Pool(count, initializer=_init_worker)  # forked now, before the caller goes on
    pending = [pool.apply_async(function, (key,)) for key in keys]

    def results() -> Generator[tuple[int, Any], None, None]:
        try:
            yield None  # primed below: from here on, closing the iterator stops the workers
            for i, handle in enumerate(pending):  # in order; each waits for its own task
                yield i, handle.get()
        finally:  # every task ended, one raised, or the caller closed the iterator early
            pool.terminate()

    primed = results()
    next(primed)
    return primed
