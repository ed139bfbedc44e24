"""Work beyond pushes in worker processes (pushtorch.sim.tasks): real forked processes, real torch work."""

from __future__ import annotations

import os

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
