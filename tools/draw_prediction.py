"""Draw one prediction from a real run: the README's picture (docs/images/prediction.png).

Trains a cube model on ``--pushes`` simulated pushes per action (as the README's library example does; the
pushes are cached under ``--cache``), captures a single depth-camera view of the thin prism (an object the
model never saw), predicts a push for each of the three actions and runs the same pushes in pybullet from
the robot starts the model chose (mass 0.5 kg, ground friction 0.3, the training priors' means). The figure
is a top view: the prism's outline and observed cloud at the start, the robot's start and path, samples of
each predicted final-pose density (positions, and a few of them as faint outlines), its mode (dashed) and
the true final pose (solid). The density is over the final pose given the *estimated* start, so its
samples are drawn moved by the estimate's error, from the true start (the displacement sense of
docs/method.md). The last line printed is, per action, ``action=<j> linear_error_cm=<mode vs truth>
log_prob=<density at the truth, displacement sense>``. About 20 s on 2 cores.

    .venv/bin/python tools/draw_prediction.py [--out docs/images/prediction.png] [--pushes 100] [--samples 600]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.lines import Line2D
from scipy.spatial import ConvexHull

import pushtorch
from pushtorch import Normal, make_actions

ROOT = Path(__file__).resolve().parents[1]


def footprint(obj, pose: pushtorch.Pose) -> np.ndarray:
    """The object's outline seen from above at ``pose``: the convex hull of its vertices in x, y, closed."""
    vertices = torch.as_tensor(np.asarray(obj.mesh.vertices), dtype=pose.p.dtype)
    xy = pose.apply(vertices)[:, :2].numpy()
    hull = xy[ConvexHull(xy).vertices]
    return np.vstack([hull, hull[:1]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "prediction.png")
    parser.add_argument("--cache", type=Path, default=ROOT / "runs" / "draw_prediction")
    parser.add_argument("--pushes", type=int, default=100, help="training pushes per action (default 100)")
    parser.add_argument("--samples", type=int, default=600, help="density samples drawn per action (default 600)")
    args = parser.parse_args()

    cube = pushtorch.load_object("cube")
    plan = pushtorch.plan_training_pushes(cube, make_actions(3), args.pushes, Normal(0.5, 0.025),
                                          Normal(0.3, 0.05), seed=0)
    pushes = args.cache / f"cube_{args.pushes}"
    pushtorch.run_plan(pushtorch.object_spec(cube), plan, pushes)
    model = pushtorch.train_push_model(cube, pushtorch.load_records(pushes))

    prism = pushtorch.load_object("prism_thin")
    start = prism.resting_pose(yaw=0.3)
    cloud = pushtorch.capture_partial_cloud(prism, start)

    fig, ax = plt.subplots(figsize=(9.6, 4.8), dpi=110)
    outline = footprint(prism, start)
    points = cloud.points[:, :2].numpy()
    ax.scatter(points[:, 0], points[:, 1], s=1.5, color="0.35", alpha=0.5, lw=0, zorder=2)
    ax.plot(outline[:, 0], outline[:, 1], color="0.2", lw=1.2, zorder=3)
    ax.annotate("thin prism at the start:\noutline, observed cloud", xy=outline[1], xytext=(-0.33, -0.3),
                fontsize=7, color="0.2", arrowprops={"arrowstyle": "-", "color": "0.5", "lw": 0.6})
    handles, summary = [], []
    for index, colour in zip(range(len(model.actions)), ("tab:blue", "tab:orange", "tab:red"), strict=True):
        action = model.actions[index]
        prediction = pushtorch.predict(model, cloud, action)
        estimate, mode = prediction.condition.object_pose, prediction.final_pose
        robot_start = prediction.condition.robot_start
        truth = pushtorch.simulate_pushes(prism, robot_start, start, action, mass=0.5, ground_friction=0.3)
        final = truth.object_final.take(0).to(mode.p.dtype)
        samples = pushtorch.Pose.from_vector(prediction.density.sample((args.samples,)))
        # the density is over the final pose given the *estimated* start B̂0: its motions (X ∘ B̂0⁻¹) are drawn
        # from the true start B0, where the true object would end if it moved as predicted (displacement sense)
        to_truth = estimate.inverse().compose(start)
        samples, mode = samples.compose(to_truth), mode.compose(to_truth)
        moved = final.compose(start.inverse()).compose(estimate)  # the true motion applied to the estimate
        log_prob = float(prediction.density.log_prob(moved.vector()))
        error_cm = float((mode.p - final.p).norm()) * 100
        summary.append(f"action={index} linear_error_cm={error_cm:.2f} log_prob={log_prob:.2f}")

        robot_path = truth.robot_trajectory.take(0).p[:, :2].numpy()
        ax.plot(robot_path[:, 0], robot_path[:, 1], ":", color=colour, lw=1.2, alpha=0.8)
        rs = robot_start.p[:2].numpy()
        yaw = float(2 * torch.atan2(robot_start.q[3], robot_start.q[0]))
        ax.annotate("", xy=(rs[0] + 0.05 * np.cos(yaw), rs[1] + 0.05 * np.sin(yaw)), xytext=rs,
                    arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 1.4})
        ax.plot(*rs, "o", color=colour, ms=4)
        xy = samples.p[:, :2].numpy()
        ax.scatter(xy[:, 0], xy[:, 1], s=3, color=colour, alpha=0.3, lw=0)
        for i in range(0, args.samples, max(1, args.samples // 12)):
            ring = footprint(prism, samples.take(i))
            ax.plot(ring[:, 0], ring[:, 1], color=colour, lw=0.4, alpha=0.25)
        ring = footprint(prism, mode)
        ax.plot(ring[:, 0], ring[:, 1], "--", color=colour, lw=1.6)
        ring = footprint(prism, final)
        ax.plot(ring[:, 0], ring[:, 1], "-", color=colour, lw=2.0)
        turn = float(torch.rad2deg(action[1]))
        where = "truth inside the density" if np.isfinite(log_prob) else "truth outside its support"
        error = f"{error_cm:.1f}" if error_cm >= 1 else f"{error_cm:.2f}"
        handles.append(Line2D([], [], color=colour, lw=6, alpha=0.5,
                              label=f"turning {turn:+.0f} °/s: mode {error} cm from the truth,\n{where}"))

    styles = [Line2D([], [], color="0.3", ls=":", lw=1.2, label="robot start chosen by the model, its path"),
              Line2D([], [], color="0.3", marker="o", ls="", ms=3, alpha=0.5, label="samples of the predicted density"),
              Line2D([], [], color="0.3", ls="--", lw=1.6, label="predicted final pose (the density's mode)"),
              Line2D([], [], color="0.3", ls="-", lw=2.0, label="true final pose (the same push in pybullet)")]
    ax.legend(handles=styles + handles, fontsize=7.5, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"A cube model ({args.pushes} training pushes per action) predicts three pushes of a thin prism "
                 "it never saw,\nfrom one depth camera's partial view (top view; pushes at 0.1 m/s for 4 s)",
                 fontsize=9, loc="left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, bbox_inches="tight", pad_inches=0.08)
    print(f"wrote {args.out}")
    print(" ".join(summary))


if __name__ == "__main__":
    main()
