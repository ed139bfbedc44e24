"""How much a prediction's normaliser varies with its importance sampler's seed, by sample count: the number behind
``pushtorch.prediction.PLANNER_NORMALISER_SAMPLES`` and ``pushtorch.distribution.NORMALISER_SAMPLES``.

Paper, §Motion Model: the product of experts is used through its arg-max; scoring a goal under it needs its
normalising constant, estimated by importance sampling (``pushtorch.kde.normaliser.log_normaliser``). The model and
candidates are ``tools/bench_plan.py``'s (a paper-size cube model, its cached file in ``runs/bench_plan/``; run that
benchmark once first): four candidates' densities, each normaliser estimated with eight seeds per sample count.

    .venv/bin/python tools/normaliser_spread.py [--model runs/bench_plan/cube_100.npz]

Prints, per sample count, each candidate's standard deviation of log Z between seeds and the median seconds of one
estimate.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from bench_plan import candidates  # tools/ is on sys.path when a tool runs as a script
from bench_predict import cpu_name

from pushtorch import se3
from pushtorch.kde import PoseKDE
from pushtorch.kde.normaliser import log_normaliser
from pushtorch.models.model import load_model
from pushtorch.models.push_condition import features_for
from pushtorch.prediction import predict_candidates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="runs/bench_plan/cube_100.npz")
    args = parser.parse_args()
    print(f"CPU: {cpu_name()}")
    model = load_model(args.model)
    cloud, starts, actions = candidates(8, "cpu")
    features = features_for(cloud, model.settings, model.position)
    density = predict_candidates(model, features, starts, model.actions[torch.tensor(actions)], seed=0).density
    for samples in (64, 256, 1024):
        spreads, times = [], []
        for b in range(4):
            counted = density.exponent[:, b] > 0
            kept = torch.isfinite(density.log_weights[counted, b]).any(0)
            e = int(counted.sum())
            means = se3.Pose.unchecked(density.means.p[b, kept].expand(e, -1, 3),
                                       density.means.q[b, kept].expand(e, -1, 4))
            kde = PoseKDE(means, density.bandwidth, density.log_weights[counted, b][:, kept],
                          trial_rounds=density.trial_rounds[b].expand(e, 3))
            values = []
            for seed in range(8):
                started = time.perf_counter()
                values.append(float(log_normaliser(kde, torch.Generator().manual_seed(seed), samples,
                                                   density.normaliser_centres.take(b), density.exponent[counted, b])))
                times.append(time.perf_counter() - started)
            spreads.append(statistics.stdev(values))
        print(f"samples {samples}: std of log Z between seeds per candidate {[round(s, 4) for s in spreads]}; "
              f"{statistics.median(times):.3f} s an estimate")


if __name__ == "__main__":
    main()
