"""Where a residual prediction's point prediction should sit, measured on held-out *training* pushes: the
mixture's highest kernel centre (``"centre"``), the local mode of the same kernels at the model's motion width
(``ModelSettings.motion_bandwidth``, where pushtorch anneals its own mode; the ``shifted`` point,
:func:`pushtorch.prediction.residual.shifted_mode`; ``"motion"``), the held-out push model's own prediction from
the same robot start (``"learned"``), and the higher of the centre and that prediction under an even mixture of
the residual's density and pushtorch's (``"mixture"``).
A diagnosis for docs/method.md ("The residual model"), never a choice on a test object.

For a run folder of the engine gap (``python -m pushtorch experiment=engine_gap``; its training pushes cached),
each training object's residual model is trained again in this process (the run's settings and seeds), and
``--pushes`` of its pushes per action are each held out (``ResidualModel.without_pushes``: its residuals and its
push model's kernels), predicted from the single-shot cloud at the push's start and its robot start, and scored by
H_acc of the displacement under each point. One line per training object, then the last line,
``centre_hacc=<..> motion_hacc=<..> learned_hacc=<..> mixture_hacc=<..> paired_se=<..> pushes=<n>`` (the paired
SE of motion − centre).

    .venv/bin/python tools/residual_mode.py runs/engine_gap_pybullet [--pushes 10]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from omegaconf import OmegaConf

from pushtorch import se3
from pushtorch.evaluation.metrics import accuracy, displaced
from pushtorch.experiments.context import context_from_config, stable_seed
from pushtorch.experiments.training import training_records
from pushtorch.models.residual import train_residual_model
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.prediction.residual import learned_point, narrow_density, predict_residual, shifted_mode


def mixture_mode(pred, own, learned: se3.Pose) -> se3.Pose:
    """Of the residual's point and the push model's (``learned``, in the body's frame), the one where the even
    mixture of the residual's density and the push model's own (``own.density``, over the estimate's frame) is
    higher."""
    double = torch.float64
    to_estimate = se3.compose(se3.inverse(pred.start.to(double)), own.condition.object_pose.to(double))
    best, value = pred.final_pose, -math.inf
    for point in (pred.final_pose, learned):
        there = se3.compose(point.to(double), to_estimate)
        mixed = torch.logaddexp(pred.density.log_prob(point.vector().reshape(1, 7)).double(),
                                own.density.log_prob(there.vector().float().reshape(1, 7)).double())
        if float(mixed.reshape(-1)[0]) > value:
            best, value = point, float(mixed.reshape(-1)[0])
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--pushes", type=int, default=10)
    args = parser.parse_args()
    cfg = OmegaConf.load(args.run / "resolved_config.yaml")
    ctx = context_from_config(cfg, args.run)
    wide = ctx.settings.motion_bandwidth
    rows = []
    for name in ("cube", "cylinder"):
        obj = load_object(name)
        records = training_records(ctx, obj, "paper_default", "paper_default", progress=False)
        key = f"{name}_paper_default_paper_default"
        model = train_push_model(obj, records, ctx.settings, name=key,
                                 generator=torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key)))
        residual = train_residual_model(model, obj, records, ctx.physics, 4)
        valid = records.take(records.valid)
        generator = torch.Generator().manual_seed(0)
        for a, motion in enumerate(model.motions):
            action = motion.action.detach().double()
            pushes = valid.take((valid.action.double() - action).abs().amax(-1) <= 1e-6)
            kept = motion.manipulator.push.unique()
            for p in kept[torch.randperm(len(kept), generator=generator)[:args.pushes]].tolist():
                held = residual.without_pushes(a, torch.tensor([p]))
                push = pushes.take(torch.tensor([p]))
                start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
                robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
                truth = se3.Pose.unchecked(push.object_final.p[0].float(), push.object_final.q[0].float())
                cloud = capture_partial_cloud(obj, start, voxel_size=ctx.settings.voxel_size)
                pred = predict_residual(held, cloud, push.action[0].float(), generator, robot_start=robot)
                own = predict(held.model, cloud, push.action[0].float(), generator, robot_start=robot)
                learned = learned_point((own.condition.object_pose, own.final_pose), pred.start)
                row = []
                shifted = shifted_mode(narrow_density(pred), wide)
                for point in (pred.final_pose, shifted, learned, mixture_mode(pred, own, learned)):
                    row.append(float(accuracy(displaced(pred.start, point, start), truth, obj).hacc))
                rows.append(row)
                print(name, a, p, [round(v, 4) for v in row], flush=True)
        t = torch.tensor(rows[-args.pushes * len(model.motions):], dtype=torch.float64).mean(0).tolist()
        print(f"{name}: centre {t[0]:.4f} motion {t[1]:.4f} learned {t[2]:.4f} mixture {t[3]:.4f}", flush=True)
    t = torch.tensor(rows, dtype=torch.float64)
    diff = t[:, 1] - t[:, 0]
    print(f"centre_hacc={float(t[:, 0].mean()):.4f} motion_hacc={float(t[:, 1].mean()):.4f} "
          f"learned_hacc={float(t[:, 2].mean()):.4f} mixture_hacc={float(t[:, 3].mean()):.4f} "
          f"paired_se={float(diff.std() / math.sqrt(len(diff))):.4f} pushes={len(rows)}")


if __name__ == "__main__":
    main()
