"""Where a fast prediction's time goes at the paper's sizes (issue 18): a cProfile of warm predictions.

Uses tools/bench_predict.py's cached cube model (500 pushes per action; trained on first use) and its
conditions; compiles and warms up the fast path first (as in a long run), then profiles ``--predictions``
single predictions (or, with ``--batch-size``, the same conditions through ``predict_many`` in batches)
and prints where each prediction's time goes: the stages of a prediction (query densities, their annealing,
pose verification, environment contacts, the motion density, its annealing) with the time each takes
including what it calls, the own time of compiled kernels, other built-ins and Python, the count of calls
into compiled code and into torch operators, and the functions with the most time.

    .venv/bin/python tools/profile_predict.py [--predictions 10] [--batch-size 1] [--top 25] [--sort cumulative]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import time
from pathlib import Path

import torch
from bench_predict import cpu_name, paper_size_model, test_conditions, warm_up

from pushtorch.kde import declare_long_run
from pushtorch.objects import load_object
from pushtorch.prediction import predict, predict_many

#: A prediction's stages, in the order they run: (label, file, function). None of them calls another, so
#: their inclusive times add up; what is left of a prediction is dispatch and bookkeeping between them.
STAGES = (
    ("query densities: kernel draws (robot, pose)", os.path.join("models", "query.py"), "build_query_density"),
    ("query annealing: steps, polish (robot, pose)", os.path.join("models", "query.py"), "optimise_query_densities"),
    ("pose verification", os.path.join("models", "push_condition.py"), "_verified_pose"),
    ("environment contact frames", os.path.join("models", "motion.py"), "environment_frames"),
    ("robot start clearance", os.path.join("models", "clearance.py"), "clear_robot_start"),
    ("motion density: contact weights, experts", os.path.join("prediction", "forward.py"), "_motion_density"),
    ("motion annealing: steps, polish", os.path.join("models", "experts.py"), "anneal_motion_densities"),
)
#: Parts of the two annealing stages, listed under them (callees included; they overlap the stages).
ANNEALING_PARTS = (
    ("leaf-block index of the query densities", os.path.join("kde", "fast_index.py"), "__init__"),
    ("proposal draws (vMF, normal, uniform)", "anneal.py", "_draw_fast_proposals"),
    ("mean-shift polish", "anneal.py", "polish_candidates"),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predictions", type=int, default=10, help="profiled predictions (default 10)")
    parser.add_argument("--top", type=int, default=25, help="functions listed (default 25)")
    parser.add_argument("--cache", default="runs/bench_predict", help="model cache folder")
    parser.add_argument("--sort", default="tottime", choices=("tottime", "cumulative"),
                        help="list by own time (default) or by time including callees")
    parser.add_argument("--batch-size", type=int, default=1,
                        help="profile predict_many with this many conditions per batch (default 1: predict)")
    args = parser.parse_args()
    declare_long_run()
    model = paper_size_model("cube", 500, Path(args.cache))
    obj = load_object("cube")
    conditions, _ = test_conditions(model, obj, args.predictions, seed=1)
    warm_up(model, conditions.pop()[1:], max(args.batch_size, 4))
    clouds = [features for _, features, _ in conditions]
    actions = torch.stack([action for _, _, action in conditions])
    if args.batch_size > 1:  # this run's batch sizes compiled before the profile (the last batch may be smaller)
        predict_many(model, clouds, actions, seed=0, batch_size=args.batch_size)
    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) threads={torch.get_num_threads()} "
          f"load_average={os.getloadavg()[0]:.2f} batch_size={args.batch_size}")
    profiler = cProfile.Profile()
    started = time.perf_counter()
    profiler.enable()
    if args.batch_size > 1:
        predict_many(model, clouds, actions, seed=0, batch_size=args.batch_size)
    else:
        for i, (features, action) in enumerate(zip(clouds, actions, strict=True)):
            predict(model, features, action, torch.Generator().manual_seed(i), method="fast")
    profiler.disable()
    seconds = (time.perf_counter() - started) / len(conditions)
    stats = pstats.Stats(profiler)
    compiled = sum(calls for (file, _, name), (_, calls, *_rest) in stats.stats.items()
                   if name == "call" and file.endswith(os.path.join("kde", "fused.py")))
    operators = sum(calls for (file, _, name), (_, calls, *_rest) in stats.stats.items()
                    if file == "~" and "torch" in name)
    print(f"{seconds:.3f} s per prediction under the profiler; per prediction {compiled / len(conditions):.0f} calls "
          f"into fused (compiled) functions, {operators / len(conditions):.0f} calls of torch built-ins")
    kernel_s, builtin_s, python_s = split_own_time(stats)
    n = len(conditions)
    print(f"own time per prediction: compiled kernels {kernel_s / n * 1e3:.1f} ms, other built-ins (eager torch "
          f"ops, C calls) {builtin_s / n * 1e3:.1f} ms, Python (glue, guards, set-up) {python_s / n * 1e3:.1f} ms")
    print_stages(stats, seconds, n)
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats(args.sort).print_stats(args.top)
    print(text.getvalue())


def print_stages(stats: pstats.Stats, seconds: float, n: int) -> None:
    """The time of each of :data:`STAGES` (and :data:`ANNEALING_PARTS`) per prediction, callees included, and
    its share of the whole. A stage the profile never entered is an error: a renamed function must not
    read as a stage that costs nothing."""
    def inclusive(file_end: str, name: str) -> float:
        found = [total for (file, _, fn), (_, _, _, total, _) in stats.stats.items()
                 if fn == name and file.endswith(os.path.join("pushtorch", file_end))]
        if not found:
            raise SystemExit(f"profile_predict: no call of {name} in pushtorch/{file_end} (renamed? update STAGES)")
        return sum(found) / n

    def line(label: str, part: float) -> str:
        return f"  {label:50s} {part * 1e3:6.1f} ms  {part / seconds:5.1%}"

    print("stage (per prediction, callees included)")
    times = [inclusive(file_end, name) for _, file_end, name in STAGES]
    for (label, _, _), part in zip(STAGES, times, strict=True):
        print(line(label, part))
    print(line("rest (dispatch, results, bookkeeping)", seconds - sum(times)))
    print("of the two annealings")
    for label, file_end, name in ANNEALING_PARTS:
        print(line(label, inclusive(file_end, name)))


def split_own_time(stats: pstats.Stats) -> tuple[float, float, float]:
    """Own (not cumulative) time in Inductor's generated kernels, in other built-ins, and in Python frames.

    A prediction's floor is the first: the arithmetic at the paper's sizes. The other two are what fusing
    and batching can still remove."""
    kernel = builtin = python = 0.0
    for (file, _, name), (_, _, own, *_rest) in stats.stats.items():
        if file == "~" and name.endswith(".kernel>"):
            kernel += own
        elif file == "~":
            builtin += own
        else:
            python += own
    return kernel, builtin, python


if __name__ == "__main__":
    main()
