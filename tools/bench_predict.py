"""Benchmark of prediction at the paper's sizes: the dense reference against the fast path, same conditions.

A cube model is trained on 500 simulated pushes per action (3 actions, mass N(0.5, 0.025), ground friction
N(0.3, 0.05)), so the motion models hold the paper's 5,000 environment and 500 manipulator kernels; the
predictor runs at the paper's settings (3,000 query kernels, 500 annealing candidates × 100 steps,
5 environment contacts). The model is cached (default ``runs/bench_predict/``) and reused.

Test conditions are the cube at the origin with a random yaw in [−45°, 45°] and the actions in turn. For
each condition the dense reference (``method="dense"``: the paper's 100 annealing steps, every query
against every kernel, the 25,500 motion kernels of the five environment experts and the manipulator
expert included) and the fast path (``method="fast"``: pruned, fused densities, 30 annealing steps
then a 3-step mean-shift polish of every candidate) predict from the same precomputed surface features
with the same seed; each prediction is timed on its own and scored
by H_acc against pybullet run from that prediction's own robot start pose (as the paper's protocol). The
fast path is compiled and warmed up on one extra condition first (compilation time reported apart), and
the batched fast path (``predict_many(batch_size=…)``) is timed on all conditions at once.

For scale, the line before the last times one annealing step evaluated the way the issue measured its
34 s per prediction (eager ``cdist`` + ``exp``, every candidate against every motion kernel, nothing
pruned or fused), which the dense reference's chunked matmul evaluation beats several times over.

The last line is exactly ``p50_s=<fast> ratio=<dense/fast> hacc_fast=<..> hacc_dense=<..>``: the median
latency of one fast prediction from surface features, the ratio of the dense median to it, and the mean
H_acc of each path.

    .venv/bin/python tools/bench_predict.py [--conditions 160] [--threads 0] [--batch-size 32]

About 20 minutes with the default 160 conditions on 2 cores (the dense reference takes ~5.5 s each);
single predictions' H_acc spreads ~0.1 from the annealing's randomness, so fewer conditions cannot
tell the two paths' means apart. Set ``PUSHTORCH_COMPILE=0`` to measure the fast path uncompiled.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import time
from pathlib import Path

import torch

from pushtorch import metrics, se3
from pushtorch.errors import RecordFormatError
from pushtorch.features import compute_surface_features
from pushtorch.kde import fast_path_compiled
from pushtorch.models.library import PushModel, load_model, train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.predict import predict, predict_many
from pushtorch.sim.plan import plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions
from pushtorch.sim.records import load_records
from pushtorch.sim.runner import run_plan, simulate_pushes
from pushtorch.sim.world import object_spec

MASS, FRICTION = 0.5, 0.3  # the training priors' means: the test pushes' physics


def paper_size_model(object_name: str, pushes: int, folder: Path) -> PushModel:
    """Load the cached model, or simulate ``pushes`` per action, train and cache it."""
    path = folder / f"{object_name}_{pushes}.npz"
    if path.exists():
        try:
            return load_model(path)
        except RecordFormatError as exc:  # e.g. saved by an older pushtorch: retrain from the cached pushes
            print(f"retraining: {exc}")
    obj = load_object(object_name)
    plan = plan_training_pushes(obj, make_actions(3), pushes, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    records_folder = folder / f"pushes_{object_name}_{pushes}"
    started = time.perf_counter()
    run_plan(object_spec(obj), plan, records_folder, workers=2, progress=False)
    print(f"simulated {3 * pushes} training pushes in {time.perf_counter() - started:.0f} s")
    model = train_push_model(obj, load_records(records_folder), generator=torch.Generator().manual_seed(0))
    model.save(path)
    return model


def hacc(obj, prediction, truth0: se3.Pose, action: torch.Tensor) -> float:
    """H_acc of a prediction against pybullet pushed from the prediction's own robot start pose."""
    outcome = simulate_pushes(obj, prediction.condition.robot_start, truth0, action, MASS, FRICTION)
    truth1 = se3.Pose(outcome.object_final.p[0].float(), outcome.object_final.q[0].float())
    return float(metrics.accuracy(prediction.final_pose, truth1, obj).hacc)


def straightforward_step_seconds(n_candidates: int, n_kernels: int, p_std: float, rot_std: float) -> float:
    """One annealing step evaluated the way the issue measured its 34 s (eager cdist + exp, nothing
    pruned or fused): every candidate against every motion kernel, median of 3. For scale only; the dense
    reference above is the comparison the ratio uses."""
    g = torch.Generator().manual_seed(0)
    x, mu = torch.randn(n_candidates, 3, generator=g), torch.randn(n_kernels, 3, generator=g)
    q = torch.nn.functional.normalize(torch.randn(n_candidates, 4, generator=g), dim=-1)
    mu_q = torch.nn.functional.normalize(torch.randn(n_kernels, 4, generator=g), dim=-1)
    log_w = torch.randn(n_kernels, generator=g)
    times = []
    for _ in range(3):
        started = time.perf_counter()
        distance = torch.cdist(x, mu)
        angle = 2 * torch.arccos((q @ mu_q.T).abs().clamp(max=1.0))
        kernel = torch.exp(log_w - 0.5 * (distance / p_std) ** 2 - 0.5 * (angle / rot_std) ** 2)
        kernel.sum(-1).log()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="cube", help="catalogue object trained and tested (default cube)")
    parser.add_argument("--pushes", type=int, default=500, help="training pushes per action (default 500)")
    parser.add_argument("--conditions", type=int, default=160,
                        help="test conditions (default 160: H_acc varies ~0.1 between single predictions)")
    parser.add_argument("--batch-size", type=int, default=32,
                        help="conditions per batched fast call (default 32)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the test conditions (default 1)")
    parser.add_argument("--cache", default="runs/bench_predict", help="model cache folder")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    model = paper_size_model(args.object, args.pushes, folder)
    obj = load_object(args.object)
    s = model.settings
    print(f"model {args.object}: {len(model.motions[0].environment)} environment / "
          f"{len(model.motions[0].manipulator)} manipulator kernels per action; settings: "
          f"{s.query_kernels} query kernels, {s.anneal_candidates} candidates x {s.anneal_steps} steps, "
          f"{s.environment_contacts} environment contacts")
    print(f"torch {torch.__version__} threads={torch.get_num_threads()} compiled={fast_path_compiled()} "
          f"load_average={os.getloadavg()[0]:.2f}")

    g = torch.Generator().manual_seed(args.seed)
    conditions = []
    feature_seconds = []
    for i in range(args.conditions + 1):
        yaw = (float(torch.rand(1, generator=g)) - 0.5) * math.pi / 2
        truth0 = obj.resting_pose(x=0.0, y=0.0, yaw=yaw)
        cloud = capture_partial_cloud(obj, truth0)
        started = time.perf_counter()
        features = compute_surface_features(cloud, radius=s.feature_radius)
        feature_seconds.append(time.perf_counter() - started)
        conditions.append((truth0, features, model.actions[i % len(model.actions)]))

    warm_truth, warm_features, warm_action = conditions.pop()
    started = time.perf_counter()
    predict(model, warm_features, warm_action, torch.Generator().manual_seed(10_000), method="fast")
    predict(model, warm_features, warm_action, torch.Generator().manual_seed(10_001), method="fast")
    batch = min(args.batch_size, len(conditions))
    predict_many(model, [warm_features] * batch, warm_action, seed=10_002, method="fast", batch_size=batch)
    warm = time.perf_counter() - started
    print(f"warm-up (compilation) of the fast path, single and batched: {warm:.1f} s")

    seconds = {"dense": [], "fast": []}
    scores = {"dense": [], "fast": []}
    for i, (truth0, features, action) in enumerate(conditions):
        line = [f"condition {i:2d} action {action.tolist()}"]
        for method in ("dense", "fast"):
            started = time.perf_counter()
            prediction = predict(model, features, action, torch.Generator().manual_seed(i), method=method)
            seconds[method].append(time.perf_counter() - started)
            scores[method].append(hacc(obj, prediction, truth0, action))
            line.append(f"{method} {seconds[method][-1]:.3f}s hacc {scores[method][-1]:.3f}")
        print(" | ".join(line), flush=True)

    started = time.perf_counter()
    batched = predict_many(model, [c[1] for c in conditions], torch.stack([c[2] for c in conditions]),
                           seed=0, method="fast", batch_size=args.batch_size)
    batched_seconds = (time.perf_counter() - started) / len(conditions)
    batched_scores = [hacc(obj, p, c[0], c[2]) for p, c in zip(batched, conditions, strict=True)]

    p50 = {m: statistics.median(v) for m, v in seconds.items()}
    mean = {m: statistics.fmean(v) for m, v in scores.items()}
    difference = [f - d for f, d in zip(scores["fast"], scores["dense"], strict=True)]
    spread = statistics.stdev(difference) / math.sqrt(len(difference)) if len(difference) > 1 else math.nan
    print(f"surface features (not in the timings above): median {statistics.median(feature_seconds):.3f} s")
    print(f"dense: median {p50['dense']:.3f} s, mean H_acc {mean['dense']:.4f}")
    print(f"fast:  median {p50['fast']:.3f} s, mean H_acc {mean['fast']:.4f}")
    print(f"H_acc fast − dense over {len(difference)} conditions: {statistics.fmean(difference):+.4f} "
          f"± {spread:.4f} (standard error; each path's own annealing noise dominates it)")
    print(f"fast batched ({args.batch_size} conditions per call): {batched_seconds:.3f} s per condition, "
          f"mean H_acc {statistics.fmean(batched_scores):.4f}")
    n_kernels = s.environment_contacts * s.environment_kernels + s.manipulator_kernels
    step = straightforward_step_seconds(s.anneal_candidates, n_kernels, s.motion_p_std, s.motion_rot_std)
    print(f"for scale, one straightforward step (eager cdist + exp, {s.anneal_candidates} x {n_kernels}): "
          f"{step:.3f} s, x {s.anneal_steps} steps = {step * s.anneal_steps:.1f} s per prediction, "
          f"{step * s.anneal_steps / p50['fast']:.0f}x the fast median")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(f"load_average={os.getloadavg()[0]:.2f} peak_rss={peak_mb:.0f} MB (whole run, both paths)")
    print(f"p50_s={p50['fast']:.4f} ratio={p50['dense'] / p50['fast']:.1f} "
          f"hacc_fast={mean['fast']:.4f} hacc_dense={mean['dense']:.4f}")


if __name__ == "__main__":
    main()
