"""The residual model's ensemble size chosen by held-out likelihood on generated training shapes (never a test
object or a held-out shape): pushtorch.models.residual.DEFAULT_ENSEMBLE and docs/method.md "The residual model".

``--shapes`` generated training shapes (``shapes:mixed:<n>``, seeds below the held-out set's) are pushed
``--pushes`` times per action in pybullet under the experiments' training prior (mass N(0.5, 0.025), friction
N(0.3, 0.05)), one model is pooled over them and its residual model taken against pybullet on their clouds'
bodies. Each shape is held out in turn (``ResidualModel.without_shape``) and ``--held-out`` of its own pushes
are predicted from their robot starts at every ensemble size of ``--sizes``, the rollouts drawn anew for each
size; the same pushes and starts are predicted by the pooled push model for the time a pushtorch prediction
takes here. Per size it prints the mean negative log-likelihood of the held-out outcomes (displacement sense)
with its standard error, the p50 time of a prediction and its ratio to pushtorch's.

The rule: among the sizes whose p50 is within 3 × pushtorch's (the speed gate of tools/bench_residual.py, which
measures both on one cloud and start), the largest whose held-out nll is within 2 paired standard errors of the
lowest: more rollouts estimate the same density more closely, so a smaller ensemble must win clearly. The last
line is exactly ``chosen=<N> sizes=<a,b,..> nll=<..,..> ratio=<..,..>``.

    .venv/bin/python tools/residual_ensemble.py [--shapes 6] [--pushes 10] [--held-out 4] [--sizes 1,2,4,8]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script
from bench_residual import quick_settings

from pushtorch import se3
from pushtorch.evaluation.likelihood import nll
from pushtorch.models.pooled import train_pooled_model
from pushtorch.models.residual import train_residual_model, with_ensemble
from pushtorch.objects.shapes import resolve_training_objects
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.prediction.residual import predict_residual
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.settings import SimSettings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shapes", type=int, default=6)
    parser.add_argument("--pushes", type=int, default=10, help="training pushes per action and shape")
    parser.add_argument("--held-out", type=int, default=4, help="held-out pushes predicted per shape")
    parser.add_argument("--sizes", default="1,2,4,8")
    parser.add_argument("--cache", default="runs/residual_ensemble")
    args = parser.parse_args()
    sizes = [int(v) for v in args.sizes.split(",")]
    folder = Path(args.cache)
    shapes = resolve_training_objects([f"shapes:mixed:{args.shapes}"])
    records = []
    for k, shape in enumerate(shapes):
        out = folder / f"pushes_{shape.name}_{args.pushes}"
        if not (out / "manifest.json").exists():
            plan = plan_training_pushes(shape, make_actions(3), args.pushes, Normal(0.5, 0.025), Normal(0.3, 0.05),
                                        seed=k)
            run_plan(object_spec(shape), plan, out, workers=2, progress=False)
        records.append(load_records(out))
    settings = quick_settings()
    model = train_pooled_model(shapes, records, settings, generator=torch.Generator().manual_seed(0))
    started = time.perf_counter()
    residual = train_residual_model(model, shapes, records, SimSettings())
    print(f"residual of {len(shapes)} shapes trained in {time.perf_counter() - started:.0f} s")
    scores = {n: [] for n in sizes}
    times = {n: [] for n in ["pushtorch", *sizes]}
    generator = torch.Generator().manual_seed(0)
    for s, (shape, shape_records) in enumerate(zip(shapes, records, strict=True)):
        held = residual.without_shape(s)
        valid = shape_records.take(shape_records.valid)
        for i in torch.randperm(len(valid), generator=generator)[:args.held_out].tolist():
            push = valid.take(torch.tensor([i]))
            start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
            robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
            truth = se3.Pose.unchecked(push.object_final.p.float(), push.object_final.q.float())
            cloud = capture_partial_cloud(shape, start, voxel_size=settings.voxel_size)
            action = push.action[0].float()
            began = time.perf_counter()
            predict(held.model, cloud, action, i, robot_start=robot)
            times["pushtorch"].append(time.perf_counter() - began)
            for n in sizes:
                began = time.perf_counter()
                prediction = predict_residual(with_ensemble(held, n), cloud, action, 1000 * s + i, robot_start=robot)
                times[n].append(time.perf_counter() - began)
                scores[n].append(float(nll(prediction.density, truth, start, prediction.start, shape.symmetry)[0]))
    pushtorch_s = statistics.median(times["pushtorch"][1:] or times["pushtorch"])
    print(f"cpu: {cpu_name()}; {len(scores[sizes[0]])} held-out pushes of {len(shapes)} shapes; pushtorch p50 "
          f"{pushtorch_s:.3f} s")
    rows = []
    for n in sizes:
        values = torch.tensor(scores[n], dtype=torch.float64)
        p50 = statistics.median(times[n][1:] or times[n])
        rows.append((n, float(values.mean()), float(values.std() / math.sqrt(len(values))), p50, p50 / pushtorch_s))
        print(f"ensemble {n}: held-out nll {rows[-1][1]:.2f} ± {rows[-1][2]:.2f}, p50 {p50:.3f} s "
              f"({rows[-1][4]:.2f} × pushtorch)")
    within = [r for r in rows if r[4] <= 3.0] or rows[:1]
    best = min(within, key=lambda r: r[1])[0]
    chosen = best
    for n, *_ in within:  # the largest size within 2 paired SE of the best: more rollouts, the same density closer
        diff = torch.tensor(scores[n], dtype=torch.float64) - torch.tensor(scores[best], dtype=torch.float64)
        se = float(diff.std() / math.sqrt(len(diff))) if len(diff) > 1 else 0.0
        print(f"ensemble {n} - ensemble {best}: {float(diff.mean()):+.2f} nats (paired SE {se:.2f})")
        if n > chosen and float(diff.mean()) <= 2 * se:
            chosen = n
    print(f"chosen={chosen} sizes={','.join(str(r[0]) for r in rows)} nll={','.join(f'{r[1]:.2f}' for r in rows)} "
          f"ratio={','.join(f'{r[4]:.2f}' for r in rows)}")


if __name__ == "__main__":
    main()
