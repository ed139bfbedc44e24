"""The fused annealing steps against the generic loop, measured in one process (issue 18 item 1).

A prediction anneals two problems on the fast path: the robot's and the object's query densities
(a :class:`~pushtorch.kde.PoseKDE` on pruned leaf blocks) and the motion model's product of experts (a
:class:`~pushtorch.kde.SharedKernelProduct`). Given the density itself, :func:`pushtorch.anneal.anneal`
runs each step as fused calls; given its bound ``log_prob``, the generic loop (proposal, evaluation
and Metropolis test as separate calls). This tool intercepts the annealing of warm, compiled cube
predictions at the paper's sizes (tools/bench_predict.py's cached model and conditions), runs both
ways from the same generator state, alternating, and prints the medians and their ratio. One run
compares both on the same host and load, which separate runs on this machine kind cannot (their
p50 varies by 30 % between runs).

    .venv/bin/python tools/bench_fused_steps.py [--predictions 24]

Last line: ``query_generic_ms=<..> query_fused_ms=<..> motion_generic_ms=<..> motion_fused_ms=<..>
query_speedup=<..> motion_speedup=<..>``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from functools import partial
from pathlib import Path

import torch
from bench_predict import cpu_name, paper_size_model, test_conditions, warm_up

import pushtorch.anneal
import pushtorch.models.motion
import pushtorch.models.query
from pushtorch.kde import PoseKDE, declare_long_run
from pushtorch.objects import load_object
from pushtorch.prediction import predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predictions", type=int, default=24, help="predictions measured (default 24)")
    parser.add_argument("--cache", default="runs/bench_predict", help="model cache folder")
    args = parser.parse_args()
    declare_long_run()
    times: dict[str, list[float]] = {f"{kind}_{way}": []
                                     for kind in ("query", "motion") for way in ("generic", "fused")}
    anneal = pushtorch.anneal.anneal

    def both_ways(target, init, schedule, generator, **options):
        kind = "query" if isinstance(target, PoseKDE) else "motion"
        generic = partial(target.log_prob, method="fast") if kind == "query" else target.log_prob
        start = generator.get_state()
        for way, fn in (("generic", generic), ("fused", target)) * 2:
            generator.set_state(start)
            started = time.perf_counter()
            result = anneal(fn, init, schedule, generator, **options)
            times[f"{kind}_{way}"].append(time.perf_counter() - started)
        return result  # the fused result, as a prediction would have it

    pushtorch.models.query.anneal = pushtorch.models.motion.anneal = both_ways
    model = paper_size_model("cube", 500, Path(args.cache))
    conditions, _ = test_conditions(model, load_object("cube"), args.predictions + 1, seed=1)
    warm_up(model, conditions.pop()[1:], 4)
    for values in times.values():
        values.clear()
    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) threads={torch.get_num_threads()} "
          f"load_average={os.getloadavg()[0]:.2f}")
    for i, (_, features, action) in enumerate(conditions):
        predict(model, features, action, torch.Generator().manual_seed(i), method="fast")
    ms = {name: 1e3 * statistics.median(values) for name, values in times.items()}
    print(" ".join(f"{name}_ms={value:.1f}" for name, value in ms.items())
          + f" query_speedup={ms['query_generic'] / ms['query_fused']:.2f}"
          f" motion_speedup={ms['motion_generic'] / ms['motion_fused']:.2f}")


if __name__ == "__main__":
    main()
