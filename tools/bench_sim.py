"""Benchmark of the push simulator: pushes per second with one worker and with all cores.

Runs the paper's training pushes (3 actions, mass N(0.5, 0.025), ground friction N(0.3, 0.05), 4 s at
0.1 m/s) through the parallel runner, shards and all, into a temporary folder. Each pool is started and
warmed up before its timed run, so the figures are the steady-state throughput of the workers (pool
start-up is reported separately). The last line is exactly ``pushes_per_s=<all cores> scaling=<ratio>``.

    .venv/bin/python tools/bench_sim.py [--object cube] [--pushes 300] [--workers 0] [--shard-size 10]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from pushtorch.objects import load_object
from pushtorch.sim import (
    Normal,
    PushPool,
    SimSettings,
    default_workers,
    make_actions,
    object_spec,
    plan_training_pushes,
)


def measure(model, workers: int, pushes: int, shard_size: int, folder: Path,
            settings: SimSettings | None = None) -> tuple[float, float, float]:
    """(pushes per second, seconds, pool start-up seconds) of one timed run with ``workers`` processes."""
    spec = object_spec(model)
    actions = make_actions(3)
    per_action = max(1, pushes // actions.shape[0])
    plan = plan_training_pushes(model, actions, per_action, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    warm = plan_training_pushes(model, actions[:1], workers, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=1)
    started = time.perf_counter()
    with PushPool(spec, settings or SimSettings(), workers) as pool:
        pool.run(warm, folder / f"warm-{workers}", shard_size=1, progress=False)
        startup = time.perf_counter() - started
        summary = pool.run(plan, folder / f"run-{workers}", shard_size=shard_size, progress=False)
    return summary.pushes_per_second, summary.seconds, startup


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="cube", help="catalogue object (default cube)")
    parser.add_argument("--pushes", type=int, default=300, help="pushes per timed run (default 300)")
    parser.add_argument("--workers", type=int, default=0, help="worker processes for 'all cores' (0: all)")
    parser.add_argument("--shard-size", type=int, default=10, help="pushes per shard/task (default 10)")
    args = parser.parse_args()
    model = load_object(args.object)
    cores = args.workers or default_workers()
    with tempfile.TemporaryDirectory(prefix="pushtorch-bench-") as tmp:
        one, one_s, one_up = measure(model, 1, args.pushes, args.shard_size, Path(tmp))
        print(f"workers=1 object={args.object} pushes={args.pushes} seconds={one_s:.2f} startup={one_up:.2f} "
              f"pushes_per_s={one:.1f}")
        if cores > 1:
            all_, all_s, all_up = measure(model, cores, args.pushes, args.shard_size, Path(tmp))
        else:
            all_, all_s, all_up = one, one_s, one_up
        print(f"workers={cores} object={args.object} pushes={args.pushes} seconds={all_s:.2f} "
              f"startup={all_up:.2f} pushes_per_s={all_:.1f}")
    print(f"pushes_per_s={all_:.1f} scaling={all_ / one:.2f}")


if __name__ == "__main__":
    main()
