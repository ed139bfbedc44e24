"""Benchmark of the residual model's prediction against pushtorch's and a 100-rollout physics ensemble, on the
same cloud and robot start (the residual model: pushtorch.models.residual, docs/method.md "The residual model").

A cube model is trained on ``--pushes`` simulated pybullet pushes per action at the quickstart's model size
(``conf/model/quick.yaml``; cached in ``--cache``), and its residual model against pybullet (the simulator
against itself on the cloud's body: the cost is what is measured, not the accuracy). For each of ``--conditions``
test conditions (the cube at a random yaw in [−45°, 45°], the actions in turn) pushtorch predicts first; its
robot start is then given to the residual model (``--ensemble`` rollouts) and to ``physics_ensemble`` at 100
rollouts, each timed on its own after one warm-up of each.

It also prints what one pybullet rollout and its world cost (ensembles of 1 and 4 of each condition's cloud body).
With ``--pool k`` (default 2) the same conditions are predicted again with every ensemble's rollouts split over
``k`` worker processes (:class:`pushtorch.sim.bodies.RolloutPool`), on a line of their own.

One line times a planner's ``--candidates`` candidate starts of one cloud (16; the robot start shifted across the
face), through ``predict_candidates`` (one pose estimate for all, docs/usage.md) and through ``predict_many``
with the starts (a pose query each).

Two lines time the residual model's other point predictions (docs/method.md, "The point prediction"): a model
whose point is learned, predicted through ``pushtorch.prediction.predict`` (pushtorch's prediction, then the
rollouts from its push condition), and one whose point is the shifted mode, from pushtorch's robot start.

The last line is exactly ``residual_p50_s=<..> pushtorch_p50_s=<..> ensemble100_p50_s=<..> ensemble=<N>``; the
line before it gives the host's CPU and the ratio residual / pushtorch (the gate: at most 3).

    .venv/bin/python tools/bench_residual.py [--conditions 12] [--ensemble 4] [--pushes 60] [--pool 2]
        [--candidates 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch.evaluation.baselines import physics_ensemble_prediction
from pushtorch.models.residual import DEFAULT_ENSEMBLE, train_residual_model
from pushtorch.models.residual_file import load_residual_model
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.prediction.residual import predict_residual
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.settings import SimSettings

QUICK = Path(__file__).resolve().parent.parent / "conf" / "model" / "quick.yaml"


def quick_settings() -> ModelSettings:
    """The quickstart's model settings (conf/model/default.yaml with conf/model/quick.yaml's changes)."""
    import yaml

    root = Path(__file__).resolve().parent.parent / "conf" / "model"
    base = yaml.safe_load((root / "default.yaml").read_text())["settings"]
    quick = (yaml.safe_load(QUICK.read_text()) or {}).get("settings") or {}
    return ModelSettings.from_mapping({**base, **quick})


def residual_model(pushes: int, folder: Path, ensemble: int):
    """The cached residual model of the cube, or one trained now (its push model on ``pushes`` per action)."""
    path = folder / f"cube_{pushes}_residual.npz"
    if path.exists():
        return load_residual_model(path)
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), pushes, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    records_folder = folder / f"pushes_cube_{pushes}"
    run_plan(object_spec(cube), plan, records_folder, workers=2, progress=False)
    records = load_records(records_folder)
    model = train_push_model(cube, records, quick_settings(), generator=torch.Generator().manual_seed(0))
    started = time.perf_counter()
    residual = train_residual_model(model, cube, records, SimSettings(), ensemble)
    print(f"residual trained on {int(records.valid.sum())} pushes in {time.perf_counter() - started:.0f} s")
    residual.save(path)
    return residual


def time_peers(residual, cloud, action, prediction, i: int) -> tuple[float, float]:
    """Seconds of a residual prediction and of a 100-rollout physics ensemble from ``prediction``'s robot start."""
    start = prediction.condition.robot_start
    started = time.perf_counter()
    predict_residual(residual, cloud, action, i, robot_start=start)
    residual_s = time.perf_counter() - started
    started = time.perf_counter()
    physics_ensemble_prediction(cloud.points, prediction.condition.object_pose, start, action,
                                Normal(0.3, 0.05), Normal(0.5, 0.025), 100, torch.Generator().manual_seed(i))
    return residual_s, time.perf_counter() - started


def rollout_cost(conditions) -> tuple[float, float]:
    """The p50 seconds of one rollout and of building its world: ensembles of 1 and 4 of each condition's cloud
    body from its robot start, ``t1 = world + rollout`` and ``t4 = world + 4 rollouts``."""
    from pushtorch.sim.bodies import cloud_body, rollout_ensemble

    per_rollout, world = [], []
    for cloud, action, prediction in conditions[1:]:
        body, start = cloud_body(cloud.points, prediction.condition.object_pose)
        spent = []
        for n in (1, 4):
            started = time.perf_counter()
            rollout_ensemble(body, start, prediction.condition.robot_start, action, torch.full((n,), 0.3),
                             torch.full((n,), 0.5))
            spent.append(time.perf_counter() - started)
        per_rollout.append((spent[1] - spent[0]) / 3)
        world.append(spent[0] - per_rollout[-1])
    return statistics.median(per_rollout), statistics.median(world)


def time_candidates(residual, condition, count: int) -> tuple[float, float]:
    """Seconds for ``count`` candidate starts of one cloud (the condition's robot start shifted across the face, its
    action) through ``predict_candidates`` and through ``predict_many`` with the starts, after one warm-up each."""
    from pushtorch import se3
    from pushtorch.prediction import predict_candidates, predict_many

    cloud, action, prediction = condition
    shifts = torch.linspace(-0.02, 0.02, count).tolist()
    starts = [se3.compose(prediction.condition.robot_start, se3.from_xy_yaw(0.0, dy, 0.0)) for dy in shifts]
    predict_candidates(residual, cloud, starts[:1], action, seed=0)
    predict_many(residual, [cloud], action, seed=0, robot_starts=starts[:1])
    started = time.perf_counter()
    predict_candidates(residual, cloud, starts, action, seed=0)
    middle = time.perf_counter()
    predict_many(residual, [cloud] * count, action, seed=0, robot_starts=starts)
    return middle - started, time.perf_counter() - middle


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--conditions", type=int, default=12)
    parser.add_argument("--ensemble", type=int, default=DEFAULT_ENSEMBLE,
                        help="the residual model's rollouts per prediction")
    parser.add_argument("--pushes", type=int, default=60, help="training pushes per action")
    parser.add_argument("--cache", default="runs/bench_residual")
    parser.add_argument("--candidates", type=int, default=16, help="a planner's candidate starts of one cloud")
    parser.add_argument("--pool", type=int, default=2,
                        help="also time the residual and the ensemble with their rollouts split over this many "
                             "worker processes (pushtorch.sim.bodies.RolloutPool; 0: not)")
    args = parser.parse_args()
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    residual = residual_model(args.pushes, folder, args.ensemble)
    if residual.ensemble != args.ensemble:
        from pushtorch.models.residual import with_ensemble

        residual = with_ensemble(residual, args.ensemble)
    model, cube = residual.model, load_object("cube")
    yaws = torch.empty(args.conditions + 1).uniform_(-math.pi / 4, math.pi / 4,
                                                      generator=torch.Generator().manual_seed(1))
    learned = dataclasses.replace(residual, point="learned")
    shifted = dataclasses.replace(residual, point="shifted")
    times = {"residual": [], "pushtorch": [], "ensemble100": [], "learned": [], "shifted": []}
    conditions = []
    for i, yaw in enumerate(yaws.tolist()):
        pose = cube.resting_pose(yaw=yaw)
        cloud = capture_partial_cloud(cube, pose, voxel_size=model.settings.voxel_size)
        action = model.actions[i % len(model.actions)]
        started = time.perf_counter()
        prediction = predict(model, cloud, action, i)
        pushtorch_s = time.perf_counter() - started
        residual_s, ensemble_s = time_peers(residual, cloud, action, prediction, i)
        started = time.perf_counter()  # a model whose point is learned, through predict: its push model first
        predict(learned, cloud, action, i)
        learned_s = time.perf_counter() - started
        started = time.perf_counter()  # a model whose point is the corrected kernels' shifted mode
        predict_residual(shifted, cloud, action, i, robot_start=prediction.condition.robot_start)
        times["shifted"].append(time.perf_counter() - started)
        conditions.append((cloud, action, prediction))
        if i == 0:
            continue  # the warm-up
        times["learned"].append(learned_s)
        times["pushtorch"].append(pushtorch_s)
        times["residual"].append(residual_s)
        times["ensemble100"].append(ensemble_s)
        print(f"condition {i}: pushtorch {pushtorch_s:.2f} s, residual {residual_s:.2f} s, "
              f"ensemble100 {ensemble_s:.2f} s", flush=True)
    times["shifted"] = times["shifted"][1:]  # after the warm-up, as the others
    p50 = {k: statistics.median(v) for k, v in times.items()}
    rollout_s, world_s = rollout_cost(conditions)
    print(f"one pybullet rollout of a 4 s push: {rollout_s:.3f} s; building its world: {world_s:.3f} s")
    if args.pool:
        from pushtorch.sim.bodies import RolloutPool

        pooled = {"residual": [], "ensemble100": []}
        with RolloutPool(args.pool):
            for i, (cloud, action, prediction) in enumerate(conditions):
                residual_s, ensemble_s = time_peers(residual, cloud, action, prediction, i)
                if i:  # the first warms the workers up
                    pooled["residual"].append(residual_s)
                    pooled["ensemble100"].append(ensemble_s)
        print(f"rollouts over {args.pool} worker processes: residual_p50_s="
              f"{statistics.median(pooled['residual']):.3f} ensemble100_p50_s="
              f"{statistics.median(pooled['ensemble100']):.3f} (here, one after another: {p50['residual']:.3f}, "
              f"{p50['ensemble100']:.3f})")
    candidates_s, many_s = time_candidates(residual, conditions[1], args.candidates)
    print(f"a planner's {args.candidates} candidate starts of one cloud: predict_candidates {candidates_s:.2f} s "
          f"(one pose estimate), predict_many with the starts {many_s:.2f} s ({many_s / candidates_s:.2f} ×)")
    print(f"a model whose point is learned, through predict (its push model's prediction, then the residual's "
          f"from that push condition): p50 {p50['learned']:.3f} s, {p50['learned'] / p50['pushtorch']:.2f} × pushtorch")
    print(f"a model whose point is the corrected kernels' shifted mode, from the same robot start: p50 "
          f"{p50['shifted']:.3f} s, {p50['shifted'] / p50['pushtorch']:.2f} × pushtorch")
    print(f"cpu: {cpu_name()}; torch threads {torch.get_num_threads()}; residual / pushtorch "
          f"{p50['residual'] / p50['pushtorch']:.2f}")
    print(f"residual_p50_s={p50['residual']:.3f} pushtorch_p50_s={p50['pushtorch']:.3f} "
          f"ensemble100_p50_s={p50['ensemble100']:.3f} ensemble={residual.ensemble}")


if __name__ == "__main__":
    main()
