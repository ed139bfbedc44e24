"""Thread and process policy (issue 18; no paper section): how many torch threads and simulation workers a
pushtorch process uses, decided here and nowhere else, so that threads × processes never exceed the cores.

* **Cores** are the CPUs this process may run on (``sched_getaffinity``: a Slurm allocation or a ``taskset``
  is respected).
* **Jobs.** A Hydra sweep with the joblib launcher runs ``n_jobs`` jobs at once (its default -1: one per
  core); each job's share is ``cores // n_jobs``, at least 1. The experiment app declares it
  (:func:`declare_parallel_jobs`, inherited by child processes through ``PUSHTORCH_PARALLEL_JOBS``).
* **Within a job** simulation and prediction take turns: an experiment predicts, then simulates the ground
  truth with its worker pool while it waits. The pool has one single-threaded worker (pybullet and numpy,
  no torch) per core of the share, and prediction uses the share's cores as torch threads.
* **Beside other work** (:func:`share_cores` with ``busy`` CPU-bound processes next to this one) prediction
  uses ``max(1, share // (busy + 1))`` threads.
* **OpenMP keeps its default (active) wait.** Threads matched to the share leave no core to fight over;
  waiting passively (``OMP_WAIT_POLICY=PASSIVE``) only pays when a process oversubscribes. Measured on a
  2-core host, quickstart-size predictions: with another process busy, two threads took 1.23–1.48 s
  spinning in the active wait, 0.24–0.63 s waiting passively and 0.22–0.24 s on one thread; with the
  cores free (a niced job beside), two threads took 0.16–0.17 s actively and 0.24 s passively.
* **A niced background job must be niced as a session.** Linux's autogroup scheduling (on by default:
  ``/proc/sys/kernel/sched_autogroup_enabled``) shares the CPU fairly between *sessions* first; ``nice``
  orders processes only within one. A job started with ``setsid``/``nohup`` from another terminal is its own
  session, so ``nice -n 19`` leaves it an equal partner of your foreground work, and with OpenMP's active
  wait both slow down badly. Measured on host B (2 cores), warm paper-size predictions under the profiler
  (``tools/profile_predict.py``) beside a ``nice -n 19`` paper run in its own session: 4.2 s each, against
  0.17 s with it paused and 0.14 s after ``echo 19 > /proc/<its pid>/autogroup`` (the whole session niced).
  pushtorch does not write that file itself: it would lower every process of the caller's session.
"""

from __future__ import annotations

import os

from pushtorch.errors import InvalidParameterError

__all__ = ["available_cores", "core_share", "declare_parallel_jobs", "parallel_jobs", "resident_mb",
           "return_freed_memory", "share_cores"]

_JOBS_ENV = "PUSHTORCH_PARALLEL_JOBS"


_LIBC: list = []  # glibc's handle, looked up once ([None] where there is none)
_AFTER_TRIM = [0.0]  # resident MB after the last trim


def resident_mb() -> float:
    """This process's resident memory (MB), from ``/proc/self/statm``; 0 where there is none."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):  # pragma: no cover - not Linux
        return 0.0


def return_freed_memory(slack_mb: float = 0.0) -> bool:
    """Hand the heap's freed pages back to the system (glibc's ``malloc_trim(0)``) and return True; False where the
    C library is not glibc, or where resident memory grew by no more than ``slack_mb`` since the last trim.

    Training calls it between its blocks of pushes (slack 256 MB): glibc keeps freed blocks below its adaptive
    mmap threshold (up to 32 MB each) in its heaps, so a long loop over blocks of large tensors holds far more
    than one block's memory. The slack keeps the trims few, as each costs a walk of the heaps and the next
    block's page faults. Unlike lowering the mmap threshold (``mallopt``), it changes no allocation policy of the
    caller's process. Measured in docs/speed.md, "Training from a push table"."""
    if not _LIBC:
        import ctypes
        import ctypes.util

        name = ctypes.util.find_library("c")
        try:
            libc = ctypes.CDLL(name) if name else None
            _LIBC.append(libc if libc is not None and hasattr(libc, "malloc_trim") else None)
        except OSError:  # pragma: no cover - no loadable C library
            _LIBC.append(None)
    if _LIBC[0] is None or (slack_mb > 0 and resident_mb() - _AFTER_TRIM[0] <= slack_mb):
        return False
    _LIBC[0].malloc_trim(0)
    _AFTER_TRIM[0] = resident_mb()
    return True


def available_cores() -> int:
    """The number of CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def parallel_jobs() -> int:
    """How many jobs of a sweep run at once on this machine (1 unless declared)."""
    raw = os.environ.get(_JOBS_ENV, "1")
    try:
        jobs = int(raw)
    except ValueError:
        raise InvalidParameterError(f"{_JOBS_ENV} must be an integer >= 1, got {raw!r}") from None
    if jobs < 1:
        raise InvalidParameterError(f"{_JOBS_ENV} must be an integer >= 1, got {raw!r}")
    return jobs


def declare_parallel_jobs(jobs: int) -> None:
    """Declare that ``jobs`` jobs share this machine (``-1`` or more than the cores: one per core)."""
    cores = available_cores()
    jobs = cores if jobs < 1 or jobs > cores else int(jobs)
    os.environ[_JOBS_ENV] = str(jobs)


def core_share() -> int:
    """The cores of this job: ``cores // parallel_jobs()``, at least 1 (simulation workers by default)."""
    return max(1, available_cores() // parallel_jobs())


def share_cores(busy: int = 0) -> int:
    """Set torch's intra-op threads for prediction beside ``busy`` other CPU-bound processes of this job:
    ``max(1, core_share() // (busy + 1))``; returns the count."""
    import torch

    if isinstance(busy, bool) or int(busy) != busy or busy < 0:
        raise InvalidParameterError(f"busy must be an integer >= 0, got {busy!r}")
    threads = max(1, core_share() // (int(busy) + 1))
    torch.set_num_threads(threads)
    return threads
