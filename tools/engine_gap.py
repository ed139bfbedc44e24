"""The gap between the two engines: the same pushes in pybullet and in MuJoCo, how far apart they end.

Paper, Experimental Setup (the world) and Future Work (transfer beyond the training simulator). Every catalogue
object is pushed from the same placements (the spread protocol: ±0.1 m lateral, ±5° heading), with the same
mass and friction (each push's own draw from the paper's default priors, N(0.5, 0.025) kg and N(0.3, 0.05)),
under each action, once in each engine. Printed per object and action: the mean distance between the two
engines' final positions (cm, ± std over pushes), the mean yaw difference (deg) and, for scale, the mean
distance the object travelled in pybullet. This is the reality gap the physics peers face in the MuJoCo world
(``world=mujoco``: truth in MuJoCo, ``physics_from_cloud`` in pybullet).

    .venv/bin/python tools/engine_gap.py [--pushes 10] [--seed 0] [--objects cube,cylinder]

The last line is ``engine_gap_cm=<mean over objects and actions> straight_cm=<...> turning_cm=<...>``.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import replace

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch import se3
from pushtorch.objects import CATALOGUE, load_object
from pushtorch.sim import Normal, Placement, SimSettings, make_actions, object_spec, plan_training_pushes
from pushtorch.sim.runner import simulate_plan


def gap(name: str, pushes: int, seed: int) -> list[dict]:
    """Per action: the pushes' final-position differences (cm), yaw differences (deg) and pybullet travel (cm)."""
    obj = load_object(name)
    actions = make_actions(3)
    plan = plan_training_pushes(obj, actions, pushes, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=seed,
                                placement=Placement(lateral_jitter=0.1, yaw_jitter_deg=5.0))
    settings = SimSettings()
    finals = {e: simulate_plan(object_spec(obj), plan, replace(settings, engine=e)) for e in ("pybullet", "mujoco")}
    bullet, mujoco = finals["pybullet"], finals["mujoco"]
    valid = ~(bullet.tipped | bullet.left_ground | mujoco.tipped | mujoco.left_ground)
    apart = 100 * (bullet.object_final.p[:, :2] - mujoco.object_final.p[:, :2]).norm(dim=-1)
    turn = se3.yaw_of(bullet.object_final.q) - se3.yaw_of(mujoco.object_final.q)
    turn = torch.rad2deg(torch.atan2(torch.sin(turn), torch.cos(turn)).abs())
    if obj.symmetry.continuous_z:
        turn = torch.zeros_like(turn)  # a cylinder's yaw is not observable
    travel = 100 * (bullet.object_final.p[:, :2] - bullet.object_initial.p[:, :2]).norm(dim=-1)
    rows = []
    for a in range(actions.shape[0]):
        keep = (plan.action_index == a) & valid
        rows.append({"object": name, "action_deg_s": round(math.degrees(float(actions[a, 1])), 1),
                     "gap_cm": float(apart[keep].mean()), "gap_std_cm": float(apart[keep].std()),
                     "yaw_deg": float(turn[keep].mean()), "travel_cm": float(travel[keep].mean()),
                     "valid": int(keep.sum()), "pushes": int((plan.action_index == a).sum())})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pushes", type=int, default=10, help="pushes per object and action (default 10)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--objects", default=",".join(CATALOGUE), help="comma-separated catalogue objects")
    args = parser.parse_args()
    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); {args.pushes} pushes per object and action, "
          f"seed {args.seed}")
    started = time.perf_counter()
    rows = [row for name in args.objects.split(",") if name for row in gap(name, args.pushes, args.seed)]
    print("| object | action (°/s) | pybullet vs MuJoCo final position (cm) | yaw (°) | travel in pybullet (cm) |"
          " valid |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['object']} | {r['action_deg_s']:+.0f} | {r['gap_cm']:.2f} ± {r['gap_std_cm']:.2f} |"
              f" {r['yaw_deg']:.1f} | {r['travel_cm']:.1f} | {r['valid']}/{r['pushes']} |")
    straight = [r["gap_cm"] for r in rows if r["action_deg_s"] == 0]
    turning = [r["gap_cm"] for r in rows if r["action_deg_s"] != 0]
    mean = sum(r["gap_cm"] for r in rows) / len(rows)
    print(f"{time.perf_counter() - started:.0f} s")
    print(f"engine_gap_cm={mean:.2f} straight_cm={sum(straight) / len(straight):.2f} "
          f"turning_cm={sum(turning) / len(turning):.2f}")


if __name__ == "__main__":
    main()
