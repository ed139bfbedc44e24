"""Whether the robot's own odometry tells masses apart better than the object's outcome does (online adaptation,
docs/method.md): the same pushes of one object under two masses, from jittered starts.

For every start and action, the object's final pose and the robot's final pose (its last recorded pose) are
compared between the masses; the separability of each is the mean gap between the masses over the spread the
starts give at one mass (per action, averaged), as the online-adaptation experiment measures it. Prints one line
per signal and ends with ``object_separability=<..> robot_separability=<..> object_gap_cm=<..> robot_gap_cm=<..>``.

    .venv/bin/python tools/odometry_evidence.py --object cube --masses 0.1 5.0 --starts 12
"""

from __future__ import annotations

import argparse
import math

import torch

from pushtorch import se3
from pushtorch.objects import load_object
from pushtorch.sim.push import make_actions, place_robot_against
from pushtorch.sim.runner import simulate_pushes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--object", default="cube")
    parser.add_argument("--masses", type=float, nargs=2, default=(0.1, 5.0))
    parser.add_argument("--friction", type=float, default=0.3)
    parser.add_argument("--starts", type=int, default=12)
    args = parser.parse_args(argv)
    obj, actions = load_object(args.object), make_actions(3)
    g = torch.Generator().manual_seed(0)
    robot, initial, action = [], [], []
    for _ in range(args.starts):
        u = torch.rand(3, generator=g, dtype=torch.float64) * 2 - 1
        pose = obj.resting_pose(0.0, 0.0, float(u[0]) * math.pi / 4)
        start = place_robot_against(obj.mesh, pose, float(se3.yaw_of(pose.q)) + float(u[1]) * math.radians(5),
                                    float(u[2]) * 0.02, 0.005)
        for a in actions:
            robot.append(start)
            initial.append(pose)
            action.append(a)
    robot, initial, action = se3.Pose.stack(robot), se3.Pose.stack(initial), torch.stack(action).double()
    outcomes = {}
    for mass in args.masses:
        rec = simulate_pushes(obj, robot, initial, action, mass, args.friction)
        obj_final = se3.relative(robot, rec.object_final).p[:, :2]  # in the robot's start frame
        robot_final = se3.relative(robot, se3.Pose.unchecked(rec.robot_trajectory.p[:, -1],
                                                              rec.robot_trajectory.q[:, -1])).p[:, :2]
        outcomes[mass] = (obj_final.reshape(args.starts, 3, 2), robot_final.reshape(args.starts, 3, 2))
    light, heavy = (outcomes[m] for m in args.masses)
    summary = {}
    for k, name in enumerate(("object", "robot")):
        x, y = light[k], heavy[k]
        gap = (x.mean(0) - y.mean(0)).norm(dim=-1)
        pooled = ((x.var(0).sum(-1) + y.var(0).sum(-1)) / 2).sqrt()
        paired = (x - y).norm(dim=-1).mean(0)
        summary[name] = (float((gap / pooled.clamp_min(1e-9)).mean()), float(gap.mean() * 100),
                         float(paired.mean() * 100))
        print(f"{name}: separability {summary[name][0]:.2f}, mean gap {summary[name][1]:.2f} cm, paired gap "
              f"{summary[name][2]:.2f} cm, spread {float(pooled.mean() * 100):.2f} cm")
    print(f"object_separability={summary['object'][0]:.3f} robot_separability={summary['robot'][0]:.3f} "
          f"object_gap_cm={summary['object'][2]:.3f} robot_gap_cm={summary['robot'][2]:.3f}")


if __name__ == "__main__":
    main()
