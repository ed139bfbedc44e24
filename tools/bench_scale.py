"""Scale-out benchmark: the same plan with the local process pool and with Ray, at 1 and 2 CPUs; training memory.

Paper, Experimental Setup (the simulated pushes; the paper protocol simulates 189,000). For each executor the
same cube plan (the paper's training pushes) is simulated into a fresh folder with 1 and with 2 CPUs (local:
``workers``; Ray: a local instance's ``num_cpus``, started once without its dashboard before any timing, and
warmed up). Each timed run simulates ``--pushes`` pushes (sized so a run lasts about a minute here). The
records of all four runs are compared bit for bit. Then the peak memory (max RSS) of training the default model
on 100,000 pushes is measured in a fresh process: the records are one 3,000-push run's arrays tiled 34 times
(each copy's push indices shifted, every value otherwise repeated), loaded as training loads them
(``trajectories=False``).

    .venv/bin/python tools/bench_scale.py [--pushes 3000] [--train-pushes 100000] [--skip-train]

The last line is ``local_pps=<..> ray_pps=<..> local_scaling=<..> ray_scaling=<..> identical=<0|1>
train_peak_mb_100k=<..>`` (pushes/s at 2 CPUs; scaling = 2-CPU over 1-CPU throughput).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch.objects import load_object
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.executors import Executor


def _plan(pushes: int, seed: int = 0):
    cube = load_object("cube")
    return cube, plan_training_pushes(cube, make_actions(3), max(1, pushes // 3), Normal(0.5, 0.025),
                                      Normal(0.3, 0.05), seed=seed)


def _timed(kind: str, cpus: int, pushes: int, folder: Path) -> float:
    cube, plan = _plan(pushes)
    executor = Executor("ray", num_cpus=cpus) if kind == "ray" else None
    started = time.perf_counter()
    run_plan(object_spec(cube), plan, folder, workers=cpus, shard_size=25, progress=False, executor=executor)
    return len(plan) / (time.perf_counter() - started)


def _train_peak(pushes: int, base: Path) -> float:
    """Max RSS (MB) of a fresh process that loads ``pushes`` tiled records and trains the default model."""
    script = f"""
import resource, torch
from dataclasses import replace
from pushtorch.objects import load_object
from pushtorch.sim import load_records
from pushtorch.sim.records import PushRecords
from pushtorch.models.training import train_push_model
one = load_records({str(base)!r}, trajectories=False)
copies = -(-{pushes} // len(one))
records = PushRecords.cat([replace(one, index=one.index + k * len(one)) for k in range(copies)])
records = records.take(torch.arange({pushes}))
train_push_model(load_object("cube"), records, generator=0)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=1800)
    if result.returncode != 0:
        raise SystemExit(f"training on {pushes} pushes failed: {result.stderr[-2000:]}")
    return float(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pushes", type=int, default=3000, help="pushes per timed run (default 3000)")
    parser.add_argument("--train-pushes", type=int, default=100_000)
    parser.add_argument("--skip-train", action="store_true", help="leave out the training-memory measurement")
    args = parser.parse_args()
    import ray

    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); {args.pushes} pushes per timed run")
    rate: dict[tuple[str, int], float] = {}
    with tempfile.TemporaryDirectory(prefix="pushtorch-scale-") as tmp:
        root = Path(tmp)
        for cpus in (1, 2):
            rate[("local", cpus)] = _timed("local", cpus, args.pushes, root / f"local{cpus}")
            print(f"local, {cpus} CPU: {rate[('local', cpus)]:.1f} pushes/s", flush=True)
        for cpus in (1, 2):
            ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
            _timed("ray", cpus, 30, root / f"warm{cpus}")  # workers started and their worlds built
            rate[("ray", cpus)] = _timed("ray", cpus, args.pushes, root / f"ray{cpus}")
            ray.shutdown()
            print(f"ray, {cpus} CPU: {rate[('ray', cpus)]:.1f} pushes/s", flush=True)
        reference = load_records(root / "local1")
        identical = all(
            torch.equal(load_records(root / name).object_final.p, reference.object_final.p)
            and torch.equal(load_records(root / name).object_trajectory.q, reference.object_trajectory.q)
            for name in ("local2", "ray1", "ray2"))
        peak = float("nan")
        if not args.skip_train:
            cube, plan = _plan(3000, seed=1)
            run_plan(object_spec(cube), plan, root / "base", progress=False)
            started = time.perf_counter()
            peak = _train_peak(args.train_pushes, root / "base")
            print(f"training the default model on {args.train_pushes} pushes: peak {peak:.0f} MB,"
                  f" {time.perf_counter() - started:.0f} s", flush=True)
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"this process's peak: {own:.0f} MB")
    local_scaling = rate[("local", 2)] / rate[("local", 1)]
    ray_scaling = rate[("ray", 2)] / rate[("ray", 1)]
    print(f"local_pps={rate[('local', 2)]:.1f} ray_pps={rate[('ray', 2)]:.1f} local_scaling={local_scaling:.2f} "
          f"ray_scaling={ray_scaling:.2f} identical={int(identical)} train_peak_mb_100k={peak:.0f}")


if __name__ == "__main__":
    main()
