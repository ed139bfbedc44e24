"""Benchmark of a model pooled over many shapes against the paper's one-object model, and of pushtorch's density
against the physics ensemble's, at the paper's sizes, in one run.

* The one-object model is tools/bench_predict.py's cube model (500 pushes per action, mass N(0.5, 0.025), friction
  N(0.3, 0.05); cached there and reused).
* The pooled model trains on ``--pushes`` pushes in all (default the paper's 24,000) spread over ``--shapes``
  generated shapes (seeds 1…, never the held-out set's), under the same priors, at the paper's settings; its
  widening is switched on (κ = 0.1) so the timing includes the contact-distance it costs. A prediction evaluates
  the same kernel budget (500 manipulator, 5,000 environment kernels, the nearest in contact) as the one-object
  model's: what grows is the search for them.
* What the budget costs: the pooled model also predicts with every kernel it holds (``pooled_all``: budgets
  raised past its kernel counts), timed and scored the same way.
* The physics ensemble rolls ``--ensemble`` pushes (default 100) of the body the cloud reconstructs, friction and
  mass drawn from the training prior (:func:`pushtorch.evaluation.baselines.physics_ensemble_prediction`), from the
  pooled prediction's own robot start, and makes a kernel density of them.

Conditions: the cube at the origin, random yaw, the actions in turn (bench_predict's). Both models predict the
same conditions with the same seeds by the fast path after a warm-up; the ensemble runs after each pooled
prediction. Each density scores the truth (pybullet from that prediction's start, mass 0.5, friction 0.3) by its nll.

    .venv/bin/python tools/bench_shapes.py [--shapes 40] [--pushes 24000] [--conditions 24] [--ensemble 100]

The last line is exactly ``single_p50_s=<..> pooled_p50_s=<..> pooled_ratio=<..> ensemble_p50_s=<..>
ensemble_over_pooled=<..> nll_single=<..> nll_pooled=<..> nll_ensemble=<..> ensemble_better=<k>/<n>
pooled_all_p50_s=<..> nll_pooled_all=<..>``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch
from bench_predict import cpu_name, paper_size_model, test_conditions  # tools/ is on sys.path as a script

from pushtorch import se3
from pushtorch.evaluation.baselines import physics_ensemble_prediction
from pushtorch.evaluation.likelihood import ensemble_density, motion_product_density, nll
from pushtorch.models.model import load_model
from pushtorch.models.pooled import train_pooled_model
from pushtorch.objects import load_object
from pushtorch.objects.shapes import training_shapes
from pushtorch.prediction import predict
from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes
from pushtorch.sim.records import load_records
from pushtorch.sim.runner import run_plan, simulate_pushes

MASS, FRICTION = Normal(0.5, 0.025), Normal(0.3, 0.05)


def pooled_model(count: int, pushes: int, folder: Path):
    """The pooled model of ``count`` shapes sharing ``pushes`` pushes (cached in ``folder``)."""
    path = folder / f"pooled_{count}_{pushes}.npz"
    if path.exists():
        return load_model(path)
    shapes = training_shapes(f"shapes:mixed:{count}")
    per_action = max(1, round(pushes / (3 * count)))
    records, started = [], time.perf_counter()
    for shape in shapes:
        plan = plan_training_pushes(shape, make_actions(3), per_action, MASS, FRICTION, seed=0)
        run_plan(object_spec(shape), plan, folder / f"pushes_{shape.name}_{per_action}", workers=0, progress=False)
        records.append(load_records(folder / f"pushes_{shape.name}_{per_action}", trajectories=False))
    print(f"simulated {sum(len(r) for r in records)} pushes of {count} shapes in {time.perf_counter() - started:.0f} s")
    started = time.perf_counter()
    model = train_pooled_model(shapes, records, generator=torch.Generator().manual_seed(0))
    print(f"trained the pooled model in {time.perf_counter() - started:.0f} s")
    model.save(path)
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=40)
    parser.add_argument("--pushes", type=int, default=24000, help="the pooled model's pushes in all")
    parser.add_argument("--conditions", type=int, default=24)
    parser.add_argument("--ensemble", type=int, default=100, help="physics_ensemble's rollouts")
    parser.add_argument("--cache", default="runs/bench_shapes")
    args = parser.parse_args()
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) torch {torch.__version__}")
    single = paper_size_model("cube", 500, Path("runs/bench_predict"))
    pooled = pooled_model(args.shapes, args.pushes, folder)
    pooled = replace(pooled, settings=replace(pooled.settings, transfer_widening=0.1))
    everything = max(len(k) for m in pooled.motions for k in (m.manipulator, m.environment))
    pooled_all = replace(pooled, settings=replace(pooled.settings, manipulator_kernels=everything,
                                                  environment_kernels=everything))
    models = (("single", single), ("pooled", pooled), ("pooled_all", pooled_all))
    for name, m in models[:2]:
        print(f"{name}: {len(m.motions[0].manipulator)} manipulator / {len(m.motions[0].environment)} environment "
              "kernels per action")
    cube = load_object("cube")
    conditions, _ = test_conditions(single, cube, args.conditions, seed=1)
    for _, m in models:  # warm-up: compile the fast path on the extra condition
        predict(m, conditions[-1][1], conditions[-1][2], torch.Generator().manual_seed(0))
    seconds = {"single": [], "pooled": [], "pooled_all": [], "ensemble": []}
    scores = {"single": [], "pooled": [], "pooled_all": [], "ensemble": []}
    for i, (truth0, features, action) in enumerate(conditions[:-1]):
        for name, m in models:
            started = time.perf_counter()
            prediction = predict(m, features, action, torch.Generator().manual_seed(i))
            seconds[name].append(time.perf_counter() - started)
            made = prediction.condition
            truth = simulate_pushes(cube, made.robot_start, truth0, action, 0.5, 0.3).object_final
            final = se3.Pose.unchecked(truth.p.float(), truth.q.float())
            density = motion_product_density(prediction.motion_density, torch.Generator().manual_seed(i),
                                              prediction.candidates)
            scores[name].append(float(nll(density, final, truth0, made.object_pose, cube.symmetry)[0]))
            if name == "pooled":  # the ensemble rolls out from the pooled prediction's start, against its truth
                condition, pooled_final = made, final
        started = time.perf_counter()
        start, finals = physics_ensemble_prediction(features.p, condition.object_pose, condition.robot_start, action,
                                                    FRICTION, MASS, args.ensemble, torch.Generator().manual_seed(i))
        density = ensemble_density(finals, pooled.settings.motion_p_std, pooled.settings.motion_rot_std)
        seconds["ensemble"].append(time.perf_counter() - started)
        scores["ensemble"].append(float(nll(density, pooled_final, truth0, start, cube.symmetry)[0]))
        print(f"condition {i:2d}: " + " ".join(f"{k} {v[-1]:.3f} s" for k, v in seconds.items())
              + " | nll " + " ".join(f"{v[-1]:.1f}" for v in scores.values()), flush=True)
    p50 = {k: statistics.median(v) for k, v in seconds.items()}
    mean = {k: statistics.fmean(v) for k, v in scores.items()}
    better = sum(e < p for e, p in zip(scores["ensemble"], scores["pooled"], strict=True))
    print(f"single_p50_s={p50['single']:.3f} pooled_p50_s={p50['pooled']:.3f} "
          f"pooled_ratio={p50['pooled'] / p50['single']:.2f} ensemble_p50_s={p50['ensemble']:.3f} "
          f"ensemble_over_pooled={p50['ensemble'] / p50['pooled']:.1f} nll_single={mean['single']:.1f} "
          f"nll_pooled={mean['pooled']:.1f} nll_ensemble={mean['ensemble']:.1f} "
          f"ensemble_better={better}/{len(scores['pooled'])} pooled_all_p50_s={p50['pooled_all']:.3f} "
          f"nll_pooled_all={mean['pooled_all']:.1f}")


if __name__ == "__main__":
    main()
