"""What "the same seed gives the same result" covers: records, models and predictions across worker counts,
torch thread counts and compile modes, each compared bit for bit (README, "Reliability").

Simulates a small real cube run with 1 and with 2 workers, trains a model on each, then predicts the same
conditions in fresh processes under 1 and 2 torch threads, compiled and eager (``PUSHTORCH_COMPILE=0``).
Prints, per comparison, whether the outputs are identical and, where not, the largest difference.

    .venv/bin/python tools/determinism_check.py [--pushes-per-action 40] [--conditions 8]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

_PREDICT = r"""
import json, sys, torch
from pushtorch.models.model import load_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict_many
model = load_model(sys.argv[1])
obj = load_object("cube")
clouds = [capture_partial_cloud(obj, obj.resting_pose(0.0, 0.0, 0.3 * k), generator=torch.Generator().manual_seed(k))
          for k in range(int(sys.argv[2]))]
out = predict_many(model, clouds, model.actions[0], generator=7)
print(json.dumps([p.final_pose.p.tolist() + p.final_pose.q.tolist() for p in out]))
"""


def _simulate_and_train(folder: Path, workers: int, per_action: int) -> tuple[Path, Path]:
    from pushtorch.models.settings import ModelSettings
    from pushtorch.models.training import train_push_model
    from pushtorch.objects import load_object
    from pushtorch.sim.plan import plan_training_pushes
    from pushtorch.sim.priors import Uniform
    from pushtorch.sim.push import make_actions
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import object_spec

    obj = load_object("cube")
    plan = plan_training_pushes(obj, make_actions(3, (-10.0, 10.0), 0.1), per_action, Uniform(0.1, 1.0),
                                Uniform(0.15, 0.35), seed=3)
    run_plan(object_spec(obj), plan, folder / "pushes", workers=workers, shard_size=20, progress=False)
    records = load_records(folder / "pushes")
    settings = ModelSettings(query_kernels=400, anneal_candidates=60, anneal_steps=20, environment_kernels=400,
                             manipulator_kernels=60, environment_samples=20, voxel_size=0.008, feature_radius=0.02)
    model = train_push_model(obj, records, settings, generator=0)
    return folder / "pushes", model.save(folder / "model.npz")


def _shards_identical(a: Path, b: Path) -> bool:
    import numpy as np
    import torch

    from pushtorch.sim.records import load_records

    ra, rb = load_records(a, dtype=torch.float64), load_records(b, dtype=torch.float64)
    return all(np.array_equal(x.numpy(), y.numpy()) for x, y in
               ((ra.object_final.p, rb.object_final.p), (ra.object_final.q, rb.object_final.q),
                (ra.object_trajectory.p, rb.object_trajectory.p)))


def _models_identical(a: Path, b: Path) -> bool:
    import numpy as np

    with np.load(a) as x, np.load(b) as y:
        return sorted(x.files) == sorted(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)


def _predict(model: Path, conditions: int, threads: int, compiled: bool) -> list[list[float]]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PUSHTORCH_COMPILE": "1" if compiled else "0"}
    code = f"import torch; torch.set_num_threads({threads})\n" + _PREDICT
    result = subprocess.run([sys.executable, "-c", code, str(model), str(conditions)], env=env, check=True,
                            capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pushes-per-action", type=int, default=40)
    parser.add_argument("--conditions", type=int, default=8)
    args = parser.parse_args()
    print(f"CPU: {cpu_name()} ({os.cpu_count()} cores), python {platform.python_version()}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="pushtorch-determinism-") as tmp:
        one, two = Path(tmp, "workers1"), Path(tmp, "workers2")
        records1, model1 = _simulate_and_train(one, 1, args.pushes_per_action)
        records2, model2 = _simulate_and_train(two, 2, args.pushes_per_action)
        print(f"records, 1 vs 2 simulation workers: identical={_shards_identical(records1, records2)}")
        print(f"models trained on them (same seed): identical={_models_identical(model1, model2)}")
        reference = _predict(model1, args.conditions, 1, True)
        for threads, compiled in ((1, True), (2, True), (1, False), (2, False)):
            other = _predict(model1, args.conditions, threads, compiled)
            gap = max(abs(a - b) for ra, rb in zip(reference, other, strict=True) for a, b in zip(ra, rb, strict=True))
            label = f"{threads} thread{'s' if threads > 1 else ''}, {'compiled' if compiled else 'eager'}"
            print(f"predictions, {label} vs 1 thread compiled: identical={gap == 0.0} max_abs_diff={gap:.3g}")
    print(f"wall {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
