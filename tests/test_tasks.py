"""Work beyond pushes in worker processes (pushtorch.sim.tasks): real forked processes, real torch work."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch

from pushtorch.parallel import available_cores
from pushtorch.sim.tasks import run_tasks, task_workers

#: What the workers inherit from this process (set before run_tasks forks them).
_INHERITED: dict = {}


def _draw(key: int) -> tuple[int, list[float], int]:
    """A task seeded by its key only: its pid, its draws (a matmul of the inherited tensor) and its threads."""
    g = torch.Generator().manual_seed(1000 + key)
    x = torch.randn(64, 64, generator=g) @ _INHERITED["weights"]
    return os.getpid(), x.sum(0)[:4].tolist(), torch.get_num_threads()


def _fail(key: int) -> int:
    if key == 2:
        raise ValueError(f"task {key} went wrong")
    return key


def test_tasks_in_workers_give_what_they_give_in_this_process_in_order():
    _INHERITED["weights"] = torch.randn(64, 64, generator=torch.Generator().manual_seed(0))
    keys = [5, 1, 4, 2, 3]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the workers run: a matmul's rounding may depend on its threads
    try:
        serial = run_tasks(_draw, keys, workers=1)
    finally:
        torch.set_num_threads(threads)
    assert {pid for pid, _, _ in serial} == {os.getpid()} and {t for _, _, t in serial} == {1}
    spread = run_tasks(_draw, keys, workers=2)
    assert [draws for _, draws, _ in spread] == [draws for _, draws, _ in serial]  # same numbers, same order
    if available_cores() >= 2:
        assert os.getpid() not in {pid for pid, _, _ in spread}
        assert {threads for _, _, threads in spread} == {1}  # one torch thread per worker: no oversubscription


def test_a_failing_task_raises_its_own_error_in_the_caller():
    with pytest.raises(ValueError, match="task 2 went wrong"):
        run_tasks(_fail, [0, 1, 2, 3], workers=2)


def test_finished_tasks_are_reported_as_they_finish():
    done = []
    assert run_tasks(_fail, [0, 1, 3], workers=2, on_done=lambda key, result: done.append((key, result))) == [0, 1, 3]
    assert done == [(0, 0), (1, 1), (3, 3)]


def test_task_workers_are_bounded_by_tasks_and_checked():
    assert task_workers(1, 8) == 1 and task_workers(10, 3) == 3 and task_workers(0) == 1
    assert 1 <= task_workers(100) <= available_cores()
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="workers must be an integer"):
            task_workers(3, bad)


_COMPILES_IN_A_WORKER = textwrap.dedent("""
    import torch
    from pushtorch.sim.tasks import run_tasks

    def task(key):  # a function the parent never compiled: Inductor compiles it in the worker
        f = torch.compile(lambda x: torch.cos(x) * (2 + key), dynamic=False)
        return float(f(torch.ones(3)).sum())

    if __name__ == "__main__":
        g = torch.compile(lambda x: torch.sin(x) + 1)
        g(torch.ones(3))  # the parent compiles first: Inductor's compile threads exist here, not in a fork
        print(run_tasks(task, [0, 1], workers=2))
""")


@pytest.mark.skipif(available_cores() < 2, reason="needs two cores for a worker process")
def test_a_worker_compiles_what_the_parent_did_not_without_hanging(tmp_path):
    """torch.compile in a forked worker after the parent compiled: Inductor's compile threads are not forked, and
    a worker waited for them forever until run_tasks set it to compile in its own thread."""
    pytest.importorskip("torch._inductor")
    import shutil

    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("Inductor needs a C++ compiler on CPU")
    script = tmp_path / "compile_in_worker.py"
    script.write_text(_COMPILES_IN_A_WORKER)
    try:
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                              env={**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor")})
    except subprocess.TimeoutExpired:
        pytest.fail("a worker compiling with torch.compile hung")
    assert done.returncode == 0, done.stderr[-2000:]
    import math

    results = [float(v) for v in done.stdout.strip().splitlines()[-1].strip("[]").split(",")]
    assert results == pytest.approx([6 * math.cos(1.0), 9 * math.cos(1.0)], rel=1e-6)


_OPEN3D_STARTS_NO_THREADS = textwrap.dedent("""
    import os
    import torch
    torch.set_num_threads(1)
    from pushtorch.deps import import_open3d
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud

    def threads():
        return len(os.listdir("/proc/self/task"))

    import_open3d()  # its own threads, before any work
    before = threads()
    cube = load_object("cube")  # its symmetry found by casting rays
    for yaw in (0.0, 0.3, 0.6):
        capture_partial_cloud(cube, cube.resting_pose(yaw=yaw))
    print(before, threads())
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts a process's threads in /proc")
def test_capturing_clouds_starts_no_thread_a_forked_worker_would_lack(tmp_path):
    """Capturing clouds (open3d's ray casting and voxel down-sampling, limited to pushtorch.deps.OPEN3D_THREADS)
    leaves the process with the threads it had: unlimited, the first capture starts a TBB thread, which a fork does
    not copy, and a worker forked from such a parent hung in its own cast."""
    script = tmp_path / "casts.py"
    script.write_text(_OPEN3D_STARTS_NO_THREADS)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    before, after = (int(v) for v in done.stdout.strip().splitlines()[-1].split())
    assert after == before, f"casting rays started {after - before} thread(s)"
