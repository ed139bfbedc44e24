"""Where a fast prediction's time goes at the paper's sizes (issue 18): a cProfile of warm predictions.

Uses tools/bench_predict.py's cached cube model (500 pushes per action; trained on first use) and its
conditions; compiles and warms up the fast path first (as in a long run), then profiles ``--predictions``
single predictions and prints the functions with the most time of their own, and the count of calls into
compiled code and into torch operators per prediction.

    .venv/bin/python tools/profile_predict.py [--predictions 10] [--top 25] [--sort cumulative]
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
from pushtorch.predict import predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predictions", type=int, default=10, help="profiled predictions (default 10)")
    parser.add_argument("--top", type=int, default=25, help="functions listed (default 25)")
    parser.add_argument("--cache", default="runs/bench_predict", help="model cache folder")
    parser.add_argument("--sort", default="tottime", choices=("tottime", "cumulative"),
                        help="list by own time (default) or by time including callees")
    args = parser.parse_args()
    declare_long_run()
    model = paper_size_model("cube", 500, Path(args.cache))
    obj = load_object("cube")
    conditions, _ = test_conditions(model, obj, args.predictions, seed=1)
    warm_up(model, conditions.pop()[1:], 4)
    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) threads={torch.get_num_threads()} "
          f"load_average={os.getloadavg()[0]:.2f}")
    profiler = cProfile.Profile()
    started = time.perf_counter()
    profiler.enable()
    for i, (_, features, action) in enumerate(conditions):
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
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats(args.sort).print_stats(args.top)
    print(text.getvalue())


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
