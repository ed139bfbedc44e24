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

For scale, every ``--straightforward-every``-th condition is also predicted by the dense reference evaluated
the straightforward way the issue sized its ~34 s baseline (``kde.straightforward_evaluation``: ``cdist``
and the quaternion dot of every candidate against every kernel of each density, cut-offs, ``logsumexp``,
at each of the 100 steps; nothing chunked, pruned or fused). It evaluates the same densities with the same
annealing and seed as the dense reference, so their predictions agree up to float rounding (printed).

Under load: the fast path is timed again on every condition while the benchmark keeps two busy background
processes simulating pushes in pybullet (as an experiment's simulation workers would), with the thread
policy of :mod:`pushtorch.parallel` (``share_cores(busy=2)``, set in its own process before anything
compiles). Dynamo's graph count is read around every fast prediction after the warm-up: what grows there
is the recompiles (the dense reference's own first compilations are not counted).

The last line is exactly ``p50_s=<..> p95_s=<..> loaded_p50_s=<..> loaded_max_s=<..> batched_s=<..> peak_mb=<..>
recompiles=<..> ratio=<..> hacc_fast=<..> hacc_dense=<..>``: the median and 95th-percentile latency of one
fast prediction from surface features, the median and the worst under load, the batched time per condition, the peak
resident memory of the process (before any straightforward evaluation), the recompiles after warm-up, the
ratio of the dense reference's median to the fast median, and the mean H_acc of each path; with
straightforward evaluations the line before it gives their ratios.

    .venv/bin/python tools/bench_predict.py [--quick] [--conditions 160] [--straightforward-every 10]
        [--batch-size 32]

``--quick`` (under 15 minutes on 2 cores) predicts 48 conditions and skips the straightforward evaluation.

20–35 minutes with the defaults on 2 cores (the dense reference takes 5.5–11.5 s per condition: latencies
depend on the CPU, which is printed); single predictions' H_acc spreads ~0.1 from the annealing's
randomness, so fewer conditions cannot tell the paths' means apart. Peak memory is read before the
straightforward predictions (they hold whole query × kernel blocks, by design). The benchmark declares a long run
(:func:`pushtorch.kde.declare_long_run`), so the fast path is compiled; set ``PUSHTORCH_COMPILE=0`` to
measure it uncompiled.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from pushtorch import se3
from pushtorch.errors import RecordFormatError
from pushtorch.evaluation import metrics
from pushtorch.features import compute_surface_features
from pushtorch.kde import declare_long_run, fast_path_compiled, straightforward_evaluation
from pushtorch.models.model import PushModel, load_model
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.parallel import share_cores
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict, predict_many
from pushtorch.sim.plan import Placement, plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions
from pushtorch.sim.records import load_records
from pushtorch.sim.runner import run_plan, simulate_pushes
from pushtorch.sim.settings import object_spec

MASS, FRICTION = 0.5, 0.3  # the training priors' means: the test pushes' physics


def paper_size_model(object_name: str, pushes: int, folder: Path, settings: ModelSettings | None = None,
                     placement: Placement | None = None, tag: str = "") -> PushModel:
    """Load the cached model, or simulate ``pushes`` per action (mass N(0.5, 0.025), friction N(0.3, 0.05),
    ``placement``), train it with ``settings`` (default the paper's) and cache it; ``tag`` names the file."""
    path = folder / f"{object_name}_{pushes}{tag}.npz"
    if path.exists():
        try:
            return load_model(path)
        except RecordFormatError as exc:  # e.g. saved by an older pushtorch: retrain from the cached pushes
            print(f"retraining: {exc}")
    obj = load_object(object_name)
    plan = plan_training_pushes(obj, make_actions(3), pushes, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0,
                                placement=placement)
    records_folder = folder / f"pushes_{object_name}_{pushes}{tag}"
    started = time.perf_counter()
    run_plan(object_spec(obj), plan, records_folder, workers=2, progress=False)
    print(f"simulated {3 * pushes} training pushes in {time.perf_counter() - started:.0f} s")
    model = train_push_model(obj, load_records(records_folder), settings, generator=torch.Generator().manual_seed(0))
    model.save(path)
    return model


def cpu_name() -> str:
    """The CPU's model name (Linux), or what the platform module knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


# A simulation worker's load: pybullet pushes of the cube, one after another, until killed.
_BUSY_SIMULATION = """
import math, torch
from pushtorch.objects import load_object
from pushtorch.sim.push import place_robot_against
from pushtorch.sim.runner import simulate_pushes
cube = load_object("cube")
pose = cube.resting_pose()
start = place_robot_against(cube.mesh, pose, gap=0.002)
while True:
    simulate_pushes(cube, start, pose, torch.tensor([0.1, math.radians(10.0)]), 0.5, 0.3)
"""


def start_busy_simulations(count: int) -> list[subprocess.Popen]:
    """``count`` background processes simulating pushes (the loaded measurement), running once this returns."""
    processes = [subprocess.Popen([sys.executable, "-c", _BUSY_SIMULATION], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL) for _ in range(count)]
    time.sleep(3.0)  # imports done, simulating
    if any(p.poll() is not None for p in processes):
        raise SystemExit("a background simulation process died: cannot measure under load")
    return processes


def graphs_compiled() -> int:
    """Dynamo's count of graphs compiled in this process so far."""
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def hacc(obj, prediction, truth0: se3.Pose, action: torch.Tensor) -> float:
    """H_acc of a prediction against pybullet pushed from the prediction's own robot start pose."""
    outcome = simulate_pushes(obj, prediction.condition.robot_start, truth0, action, MASS, FRICTION)
    truth1 = se3.Pose(outcome.object_final.p[0].float(), outcome.object_final.q[0].float())
    return float(metrics.accuracy(prediction.final_pose, truth1, obj).hacc)


def test_conditions(model: PushModel, obj, count: int, seed: int) -> tuple[list, list[float]]:
    """``count + 1`` conditions (true start, surface features, action): the cube at the origin, random yaw."""
    g = torch.Generator().manual_seed(seed)
    conditions, feature_seconds = [], []
    for i in range(count + 1):
        yaw = (float(torch.rand(1, generator=g)) - 0.5) * math.pi / 2
        truth0 = obj.resting_pose(x=0.0, y=0.0, yaw=yaw)
        cloud = capture_partial_cloud(obj, truth0)
        started = time.perf_counter()
        features = compute_surface_features(cloud, radius=model.settings.feature_radius)
        feature_seconds.append(time.perf_counter() - started)
        conditions.append((truth0, features, model.actions[i % len(model.actions)]))
    return conditions, feature_seconds


def warm_up(model: PushModel, condition: tuple, batch: int) -> float:
    """Compile the fast path on one extra condition, single and batched (two batch sizes: a run's last batch
    is usually smaller, and the second size makes the batch dimension dynamic); seconds taken."""
    features, action = condition
    started = time.perf_counter()
    predict(model, features, action, torch.Generator().manual_seed(10_000), method="fast")
    predict(model, features, action, torch.Generator().manual_seed(10_001), method="fast")
    for size in sorted({batch, max(2, batch // 2 + 1)}):
        predict_many(model, [features] * size, action, seed=10_002, method="fast", batch_size=size)
    return time.perf_counter() - started


def measure_loaded(args) -> dict:
    """The fast path under load, in a fresh process (``--loaded``): a process that runs beside simulation
    workers sets its torch threads once, before anything compiles (a later change of the thread count
    invalidates every compiled graph)."""
    command = [sys.executable, __file__, "--loaded", "--conditions", str(args.conditions), "--seed", str(args.seed),
               "--cache", args.cache, "--object", args.object, "--pushes", str(args.pushes),
               "--batch-size", str(args.batch_size)]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise SystemExit(f"the loaded measurement failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def loaded_child(args, model: PushModel, obj) -> None:
    """``--loaded``: this process's share of the cores beside two busy simulation processes, warm-up, then
    every condition timed while they run; prints one JSON line."""
    threads = share_cores(busy=2)
    conditions, _ = test_conditions(model, obj, args.conditions, args.seed)
    warm_up(model, conditions.pop()[1:], min(args.batch_size, len(conditions)))
    graphs = graphs_compiled()
    busy = start_busy_simulations(2)
    try:
        seconds = []
        for i, (_, features, action) in enumerate(conditions):
            started = time.perf_counter()
            predict(model, features, action, torch.Generator().manual_seed(i), method="fast")
            seconds.append(time.perf_counter() - started)
        load = os.getloadavg()[0]
    finally:
        for process in busy:
            process.kill()
            process.wait()
    print(json.dumps({"seconds": seconds, "threads": threads, "load_average": load,
                      "recompiles": graphs_compiled() - graphs}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="cube", help="catalogue object trained and tested (default cube)")
    parser.add_argument("--pushes", type=int, default=500, help="training pushes per action (default 500)")
    parser.add_argument("--conditions", type=int, default=160,
                        help="test conditions (default 160: H_acc varies ~0.1 between single predictions)")
    parser.add_argument("--straightforward-every", type=int, default=10,
                        help="also time the straightforward evaluation on every k-th condition (default 10)")
    parser.add_argument("--batch-size", type=int, default=32,
                        help="conditions per batched fast call (default 32)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the test conditions (default 1)")
    parser.add_argument("--cache", default="runs/bench_predict", help="model cache folder")
    parser.add_argument("--quick", action="store_true",
                        help="48 conditions, no straightforward evaluation (under 15 min on 2 cores)")
    parser.add_argument("--loaded", action="store_true", help=argparse.SUPPRESS)  # measure_loaded's process
    args = parser.parse_args()
    if args.quick:
        args.conditions, args.straightforward_every = 48, 0
    declare_long_run()  # hundreds of predictions: the fast path is measured compiled (PUSHTORCH_COMPILE=0: eager)
    if args.threads:
        torch.set_num_threads(args.threads)
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    model = paper_size_model(args.object, args.pushes, folder)
    obj = load_object(args.object)
    if args.loaded:
        loaded_child(args, model, obj)
        return
    s = model.settings
    print(f"model {args.object}: {len(model.motions[0].environment)} environment / "
          f"{len(model.motions[0].manipulator)} manipulator kernels per action; settings: "
          f"{s.query_kernels} query kernels, {s.anneal_candidates} candidates x {s.anneal_steps} steps, "
          f"{s.environment_contacts} environment contacts")
    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) torch {torch.__version__} threads={torch.get_num_threads()} "
          f"compiled={fast_path_compiled()} "
          f"load_average={os.getloadavg()[0]:.2f}")

    conditions, feature_seconds = test_conditions(model, obj, args.conditions, args.seed)
    warm = warm_up(model, conditions.pop()[1:], min(args.batch_size, len(conditions)))
    print(f"warm-up (compilation) of the fast path, single and batched: {warm:.1f} s, {graphs_compiled()} graphs")
    recompiles = 0  # graphs compiled during fast predictions after the warm-up (the dense reference's own apart)

    seconds = {"dense": [], "fast": []}
    scores = {"dense": [], "fast": []}
    dense_final = []
    for i, (truth0, features, action) in enumerate(conditions):
        line = [f"condition {i:2d} action {action.tolist()}"]
        for method in ("dense", "fast"):
            graphs = graphs_compiled()
            started = time.perf_counter()
            prediction = predict(model, features, action, torch.Generator().manual_seed(i), method=method)
            seconds[method].append(time.perf_counter() - started)
            if method == "fast":
                recompiles += graphs_compiled() - graphs
            scores[method].append(hacc(obj, prediction, truth0, action))
            line.append(f"{method} {seconds[method][-1]:.3f}s hacc {scores[method][-1]:.3f}")
            if method == "dense":
                dense_final.append(prediction.final_pose)
        print(" | ".join(line), flush=True)

    graphs = graphs_compiled()
    started = time.perf_counter()
    batched = predict_many(model, [c[1] for c in conditions], torch.stack([c[2] for c in conditions]),
                           seed=0, method="fast", batch_size=args.batch_size)
    batched_seconds = (time.perf_counter() - started) / len(conditions)
    recompiles += graphs_compiled() - graphs
    batched_scores = [hacc(obj, p, c[0], c[2]) for p, c in zip(batched, conditions, strict=True)]

    loaded = measure_loaded(args)
    loaded_seconds = loaded["seconds"]
    recompiles += loaded["recompiles"]
    print(f"fast under load (2 busy simulation processes, {loaded['threads']} torch thread(s) set before "
          f"compiling, load average {loaded['load_average']:.2f}): median {statistics.median(loaded_seconds):.3f} s, "
          f"max {max(loaded_seconds):.3f} s, {loaded['recompiles']} recompiles")

    p50 = {m: statistics.median(v) for m, v in seconds.items()}
    p95 = statistics.quantiles(seconds["fast"], n=20)[-1] if len(seconds["fast"]) > 1 else seconds["fast"][0]
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
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(f"load_average={os.getloadavg()[0]:.2f} peak_rss={peak_mb:.0f} MB (whole run so far: both paths)")

    summary = (f"p50_s={p50['fast']:.4f} p95_s={p95:.4f} loaded_p50_s={statistics.median(loaded_seconds):.4f} "
               f"loaded_max_s={max(loaded_seconds):.4f} batched_s={batched_seconds:.4f} peak_mb={peak_mb:.0f} "
               f"recompiles={recompiles} "
               f"ratio={p50['dense'] / p50['fast']:.1f} hacc_fast={mean['fast']:.4f} hacc_dense={mean['dense']:.4f}")
    if args.straightforward_every <= 0:
        print(summary)
        return
    subset = range(0, len(conditions), args.straightforward_every)
    plain_seconds, plain_scores, offsets_mm = [], [], []
    for i in subset:
        truth0, features, action = conditions[i]
        started = time.perf_counter()
        with straightforward_evaluation():
            prediction = predict(model, features, action, torch.Generator().manual_seed(i), method="dense")
        plain_seconds.append(time.perf_counter() - started)
        plain_scores.append(hacc(obj, prediction, truth0, action))
        offsets_mm.append(1000 * float((prediction.final_pose.p - dense_final[i].p).norm()))
        print(f"condition {i:2d} straightforward dense {plain_seconds[-1]:.1f}s hacc {plain_scores[-1]:.3f} "
              f"(dense {seconds['dense'][i]:.2f}s hacc {scores['dense'][i]:.3f}, "
              f"final poses {offsets_mm[-1]:.2f} mm apart)", flush=True)
    p50_plain = statistics.median(plain_seconds)
    same = sum(offset < 1.0 for offset in offsets_mm)
    print(f"straightforward dense (cdist + exp, every query against every kernel, {s.anneal_steps} steps) on "
          f"{len(plain_seconds)} of the conditions: median {p50_plain:.2f} s, mean H_acc "
          f"{statistics.fmean(plain_scores):.4f} (the dense reference on the same: "
          f"{statistics.fmean(scores['dense'][i] for i in subset):.4f}; final poses within 1 mm on {same} of "
          f"{len(offsets_mm)}, median {statistics.median(offsets_mm):.3f} mm apart)")
    print(f"ratios: straightforward / fast {p50_plain / p50['fast']:.1f}, straightforward / dense "
          f"{p50_plain / p50['dense']:.2f}")
    print(summary)


if __name__ == "__main__":
    main()
