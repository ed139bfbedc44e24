"""Executors: the same plan's shards on this machine, as Ray tasks (a real local Ray instance) and as a submitit
array (its local backend) give the same records; a killed Ray worker is retried; refused configs write nothing.

Paper, Experimental Setup (the simulated pushes); docs/cluster.md.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from pushtorch.errors import InvalidParameterError, MissingDependencyError
from pushtorch.objects import load_object
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.executors import Executor, executor_from_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cube_plan():
    cube = load_object("cube")
    return cube, plan_training_pushes(cube, make_actions(3), 8, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=3)


@pytest.fixture(scope="module")
def local_records(cube_plan, tmp_path_factory):
    cube, plan = cube_plan
    folder = tmp_path_factory.mktemp("local") / "pushes"
    run_plan(object_spec(cube), plan, folder, workers=2, shard_size=4, progress=False)
    return load_records(folder)


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def _same(a, b) -> None:
    assert len(a) == len(b)
    for name in ("object_final", "object_initial", "robot_start", "object_trajectory", "robot_trajectory"):
        assert torch.equal(getattr(a, name).p, getattr(b, name).p), name
        assert torch.equal(getattr(a, name).q, getattr(b, name).q), name
    assert torch.equal(a.index, b.index) and torch.equal(a.mass, b.mass) and torch.equal(a.valid, b.valid)


def test_ray_tasks_write_the_same_records_as_local_workers(cube_plan, local_records, ray_instance, tmp_path):
    cube, plan = cube_plan
    summary = run_plan(object_spec(cube), plan, tmp_path / "pushes", shard_size=4, progress=False,
                       executor=Executor("ray", num_cpus=2))
    assert summary.simulated_pushes == len(plan)
    _same(load_records(tmp_path / "pushes"), local_records)


@pytest.mark.parametrize("kind", ["local", "ray"])
def test_figures_drawn_as_tasks_are_those_drawn_in_one_process_byte_for_byte(kind, request, tmp_path):
    """An experiment's figures spread over its executor (forked workers on the local one, Ray tasks on Ray) are the
    files one process draws, in the same order; here from the committed paper runs' records."""
    import json
    from types import SimpleNamespace

    from pushtorch.experiments.figures import make_figures
    from pushtorch.experiments.tasks import spread_calls

    if kind == "ray":
        request.getfixturevalue("ray_instance")
    paper = ROOT / "docs" / "results" / "paper"
    records = json.loads((paper / "friction_biasing" / "results.json").read_text())["records"]
    serial = make_figures(tmp_path / "serial", records, {})
    ctx = SimpleNamespace(executor=Executor(kind, num_cpus=2), workers=2, run_dir=tmp_path)
    spread = make_figures(tmp_path / "spread", records, {},
                          lambda draw, calls: spread_calls(ctx, draw, calls, "figures"))
    assert len(serial) == 3 and [p.name for p in spread] == [p.name for p in serial]
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(serial, spread, strict=True))


def _ray_task_pids() -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if b"ray::run_shard_task" in (entry / "cmdline").read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds Ray's workers in /proc")
def test_a_killed_ray_worker_is_retried_and_no_shard_is_lost_or_doubled(cube_plan, local_records, ray_instance,
                                                                        tmp_path):
    cube, plan = cube_plan
    result = {}

    def run():
        result["summary"] = run_plan(object_spec(cube), plan, tmp_path / "pushes", shard_size=1, progress=False,
                                     executor=Executor("ray", max_retries=3))

    thread = threading.Thread(target=run)
    thread.start()
    killed, deadline = None, time.monotonic() + 120
    while killed is None and thread.is_alive() and time.monotonic() < deadline:
        pids = _ray_task_pids()
        if pids:
            os.kill(pids[0], signal.SIGKILL)
            killed = pids[0]
        time.sleep(0.05)
    thread.join(timeout=300)
    assert killed is not None, "no Ray worker was caught running a shard"
    assert "summary" in result  # the run finished: the killed task ran again
    _same(load_records(tmp_path / "pushes"), local_records)


@pytest.mark.slow  # 10-14 s of submitit processes; test_remote_tasks_as_a_submitit_array keeps an array in make test
def test_a_submitit_array_of_four_tasks_writes_the_same_records(cube_plan, local_records, tmp_path):
    pytest.importorskip("submitit")
    cube, plan = cube_plan
    run_plan(object_spec(cube), plan, tmp_path / "pushes", shard_size=4, progress=False,
             executor=Executor("slurm", cluster="local", tasks=4))
    assert len(list((tmp_path / "pushes" / ".submitit").glob("*_result.pkl"))) == 4  # four array tasks ran
    _same(load_records(tmp_path / "pushes"), local_records)


def test_executor_without_its_extra_is_a_clear_error_before_any_file(cube_plan, monkeypatch, tmp_path):
    cube, plan = cube_plan
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(MissingDependencyError, match=r'pip install "pushtorch\[ray\]"'):
        run_plan(object_spec(cube), plan, tmp_path / "pushes", executor=Executor("ray"))
    assert not (tmp_path / "pushes").exists()


def test_an_unreachable_ray_address_is_one_line_and_leaves_no_run_folder(tmp_path):
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch.apps.simulate", "executor=ray", "executor.address=127.0.0.1:9",
         "samples_per_action=1", "progress=false", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("pushtorch-simulate: executor.address='127.0.0.1:9'") and "Traceback" not in result.stderr
    assert not run_dir.exists()


def test_executor_configs_are_checked():
    assert executor_from_config(None) == Executor()
    with pytest.raises(InvalidParameterError, match="executor.kind"):
        executor_from_config({"kind": "kubernetes"})
    with pytest.raises(InvalidParameterError, match="unknown executor keys"):
        executor_from_config({"kind": "ray", "adress": "auto"})
    with pytest.raises(InvalidParameterError, match="executor.timeout_min"):
        Executor("slurm", timeout_min=0)


def _without_slurm() -> dict:
    """This environment with a ``PATH`` of folders that hold no ``sbatch`` (CI's machines have none)."""
    import shutil

    folders = [f for f in os.environ.get("PATH", "").split(os.pathsep)
               if f and not shutil.which("sbatch", path=f)]
    return dict(os.environ, PATH=os.pathsep.join([str(Path(sys.executable).parent), *folders]),
                PYTHONPATH=str(ROOT))


@pytest.mark.parametrize("app", ["pushtorch.apps.simulate", "pushtorch"])
def test_slurm_asked_for_without_slurm_is_one_line_exit_2_and_no_run_folder(tmp_path, app):
    """submitit would fall back to local processes without a word: a user on a login node would run there."""
    run_dir = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", app, "executor=slurm", f"hydra.run.dir={run_dir}"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=120, env=_without_slurm())
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "sbatch is not on this machine's PATH" in lines[0], result.stderr
    assert "executor.cluster=local" in lines[0]
    assert not run_dir.exists()


def test_an_unknown_slurm_partition_is_refused_and_a_local_array_needs_no_slurm(tmp_path, monkeypatch):
    from pushtorch.sim.executors import slurm_problem

    for name, body in (("sbatch", "exit 0"), ("sinfo", "printf 'cpu*\\ngpu\\n'")):
        script = tmp_path / name  # stand-ins for Slurm's commands: only what they print is read
        script.write_text(f"#!/bin/sh\n{body}\n")
        script.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert "is not a Slurm partition here; sinfo lists cpu, gpu" in slurm_problem(Executor("slurm", partition="x"))
    assert slurm_problem(Executor("slurm", partition="gpu")) is None
    assert slurm_problem(Executor("slurm")) is None
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    assert "sbatch" in slurm_problem(Executor("slurm"))
    assert slurm_problem(Executor("slurm", cluster="local")) is None
    with pytest.raises(InvalidParameterError, match="sbatch"):
        from pushtorch.sim.executors import SlurmPool

        SlurmPool(None, None, Executor("slurm"))


def test_remote_tasks_return_in_call_order_and_say_where_they_ran(ray_instance, tmp_path):
    from pushtorch.experiments.context import stable_seed  # a pure function of its arguments
    from pushtorch.sim.executors import run_remote_tasks, task_host

    done = []
    results = run_remote_tasks(Executor("ray"), stable_seed, [(0, k) for k in range(5)], tmp_path,
                               on_done=lambda index, _: done.append(index))
    assert results == [stable_seed(0, k) for k in range(5)] and sorted(done) == [0, 1, 2, 3, 4]
    hosts = run_remote_tasks(Executor("ray"), task_host, [(), ()], tmp_path)
    assert all("/ray-node-" in host for host in hosts)  # a Ray task names its node
    with pytest.raises(InvalidParameterError, match="task_memory_mb=100000000: no node"):  # never a wait forever
        run_remote_tasks(Executor("ray", task_memory_mb=10**8), stable_seed, [(1,)], tmp_path)


def test_remote_tasks_as_a_submitit_array(tmp_path):
    pytest.importorskip("submitit")
    from pushtorch.experiments.context import stable_seed
    from pushtorch.sim.executors import run_remote_tasks

    assert run_remote_tasks(Executor("slurm", cluster="local"), stable_seed, [(3,), (4,)], tmp_path) == [
        stable_seed(3), stable_seed(4)]
    assert len(list(tmp_path.glob("*_result.pkl"))) == 2  # two array tasks ran, their job files in the folder
    with pytest.raises(InvalidParameterError, match="runs no remote tasks"):
        run_remote_tasks(Executor(), stable_seed, [(1,)], tmp_path)
