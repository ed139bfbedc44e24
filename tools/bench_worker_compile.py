"""What a forked task worker pays for the fast path: compiled in the parent on its own threads, compiled in the
parent on one thread (as the workers run), or not compiled at all.

An experiment compiles the fast path once in its parent process and forks its task workers after
(:func:`pushtorch.experiments.tasks.warm_up`); each worker runs on one torch thread. Inductor's guards hold the
thread count, so code compiled on the parent's two threads does not serve a one-thread worker, which compiles it
again on its first prediction. This benchmark trains (once, cached under ``--cache``) a cube model at the
quickstart's prediction sizes, then for each mode starts a fresh process that declares a long run, predicts a cube
(and a second time keeping its annealing history, as the workers that log examples do) on the chosen threads,
and forks one one-thread worker that times its first prediction, one with history and a third plain one:

* ``parent2``: compiled, the parent warmed up on two threads (the code before the fix);
* ``parent1``: compiled, the parent warmed up on one thread (``warm_up`` today);
* ``eager``: ``PUSHTORCH_COMPILE=0``.

Each line: ``mode warm_s=<parent's warm-up> worker_first_s=<..> worker_history_s=<..> worker_again_s=<..>``; the
last line puts the three modes' ``worker_first_s`` side by side. Times depend on the host; compare the modes of
one run.

    .venv/bin/python tools/bench_worker_compile.py [--cache runs/bench_worker_compile]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Runs in the fresh process: prints one JSON line of timings.
_CHILD = r"""
import json, multiprocessing as mp, sys, time
import torch
import pushtorch
from pushtorch.kde import declare_long_run

declare_long_run()
model = pushtorch.load_model(sys.argv[1])
cube = pushtorch.load_object("cube")
cloud = pushtorch.capture_partial_cloud(cube, cube.resting_pose(yaw=0.3), voxel_size=model.settings.voxel_size)


def once(history=False):
    start = time.perf_counter()
    pushtorch.predict(model, cloud, model.actions[0], record_history=history)
    return time.perf_counter() - start


torch.set_num_threads(int(sys.argv[2]))
start = time.perf_counter()
once()
once(history=True)
warm = time.perf_counter() - start


def worker(_):
    torch.set_num_threads(1)
    return once(), once(history=True), once()


with mp.get_context("fork").Pool(1) as pool:
    first, history, again = pool.map(worker, [0])[0]
print(json.dumps({"warm_s": warm, "worker_first_s": first, "worker_history_s": history, "worker_again_s": again}))
"""


def _model(cache: Path) -> Path:
    path = cache / "cube.npz"
    if path.is_file():
        return path
    import torch

    import pushtorch
    from pushtorch.models.settings import ModelSettings

    cube = pushtorch.load_object("cube")
    plan = pushtorch.plan_training_pushes(cube, pushtorch.make_actions(3), 20, pushtorch.Normal(0.5, 0.025),
                                          pushtorch.Normal(0.3, 0.05), seed=0)
    pushtorch.run_plan(pushtorch.object_spec(cube), plan, cache / "pushes", progress=False)
    settings = ModelSettings(query_kernels=1000, anneal_candidates=200, anneal_steps=50)  # the quickstart's
    model = pushtorch.train_push_model(cube, pushtorch.load_records(cache / "pushes"), settings,
                                       generator=torch.Generator().manual_seed(0))
    model.save(path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=ROOT / "runs" / "bench_worker_compile")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    model = _model(args.cache)
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), "unknown") if Path("/proc/cpuinfo").is_file() else "unknown"
    print(f"cpu: {cpu} ({os.cpu_count()} cores)")
    first = {}
    for mode, threads, compile_mode in (("parent2", 2, "1"), ("parent1", 1, "1"), ("eager", 2, "0")):
        env = {**os.environ, "PUSHTORCH_COMPILE": compile_mode}
        done = subprocess.run([sys.executable, "-c", _CHILD, str(model), str(threads)], env=env, cwd=ROOT,
                              capture_output=True, text=True, timeout=900)
        if done.returncode != 0:
            raise SystemExit(f"{mode}: {done.stderr[-2000:]}")
        t = json.loads(done.stdout.strip().splitlines()[-1])
        first[mode] = t["worker_first_s"]
        print(f"{mode} " + " ".join(f"{k}={v:.2f}" for k, v in t.items()))
    print(" ".join(f"{mode}_worker_first_s={v:.2f}" for mode, v in first.items()))


if __name__ == "__main__":
    main()
