"""Physics check of the simulated world (issue 16): does mass matter, do mirrored pushes mirror, how fast is it.

Prints, for the chosen ``sim.robot`` drive (default: the library's default):

* the mass effect: final displacement of a 0.1 kg cube minus that of a 5 kg cube, ground friction 0.4, under
  the straight 4 s push (the issue's X) and under the paper's turning actions (±10 °/s);
* the friction effect (what online inference of the physics, issue 19, has to work with): final
  displacement of a 0.5 kg cube at ground friction 0.1 minus that at 0.9, straight and turning;
* the mirror asymmetry: for the cube, cylinder, thin prism and hybrid, centred and pushed with −10 and +10 °/s
  (mass 0.5 kg, friction 0.3), the distance between one final position and the mirror image of the other
  (and the yaw mismatch), each push in a fresh world;
* the simulation throughput on all cores, as tools/bench_sim.py measures it.

The last line is exactly ``mass_effect_cm=<X> mirror_mm=<Y> pushes_per_s=<Z>`` (targets on a 2-core
machine: X >= 5, Y <= 5, Z >= 40). ``--engine mujoco`` checks the MuJoCo world instead and also times
pybullet in the same run, printing the ratio of the two throughputs (target: MuJoCo >= 0.7 x pybullet).

    .venv/bin/python tools/physics_check.py [--engine pybullet|mujoco] [--robot p3dx|ideal] [--pushes 300]
                                            [--wheel-friction MU]

``--wheel-friction`` replaces the documented tyre friction (0.5) to show what a slipping drive would do; it
is not a setting any experiment uses.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script
from bench_sim import measure

from pushtorch import se3
from pushtorch.objects import load_object
from pushtorch.sim import SimSettings, default_workers, place_robot_against
from pushtorch.sim.drive import DriveSettings
from pushtorch.sim.runner import simulate_pushes
from pushtorch.sim.settings import ENGINES

MIRROR_OBJECTS = ("cube", "cylinder", "prism_thin", "hybrid")


def _push(name: str, settings: SimSettings, yaw_rate_deg: float, mass: float, friction: float) -> se3.Pose:
    """The final pose of ``name`` pushed from the training placement (a fresh world per call)."""
    obj = load_object(name)
    pose = obj.resting_pose()
    start = place_robot_against(obj.mesh, pose, gap=0.002)
    action = torch.tensor([0.1, math.radians(yaw_rate_deg)])
    records = simulate_pushes(obj, start, pose, action, mass, friction, settings=settings)
    return se3.Pose(records.object_final.p[0], records.object_final.q[0])


def mass_effect_cm(settings: SimSettings, yaw_rate_deg: float) -> float:
    """How much farther (cm) a 0.1 kg cube travels than a 5 kg one, ground friction 0.4."""
    light, heavy = (_push("cube", settings, yaw_rate_deg, m, 0.4) for m in (0.1, 5.0))
    start = load_object("cube").resting_pose().p.double()
    return 100.0 * float((light.p[:2] - start[:2]).norm() - (heavy.p[:2] - start[:2]).norm())


def friction_effect_cm(settings: SimSettings, yaw_rate_deg: float) -> float:
    """How much farther (cm) a 0.5 kg cube travels at ground friction 0.1 than at 0.9."""
    slick, rough = (_push("cube", settings, yaw_rate_deg, 0.5, mu) for mu in (0.1, 0.9))
    start = load_object("cube").resting_pose().p.double()
    return 100.0 * float((slick.p[:2] - start[:2]).norm() - (rough.p[:2] - start[:2]).norm())


def mirror_gap(name: str, settings: SimSettings) -> tuple[float, float]:
    """(mm, deg) between the final pose of the −10 °/s push and the mirror image of the +10 °/s push."""
    right, left = (_push(name, settings, rate, 0.5, 0.3) for rate in (-10.0, 10.0))
    mirrored = torch.stack([left.p[0], -left.p[1]])
    yaw_right, yaw_left = (float(se3.yaw_of(p.q)) for p in (right, left))
    gap = 1000.0 * float((right.p[:2] - mirrored).norm())
    turn = math.degrees(abs(math.remainder(yaw_right + yaw_left, 2 * math.pi)))
    symmetry = load_object(name).symmetry
    if symmetry.continuous_z:
        turn = 0.0  # a cylinder's yaw is not observable
    return gap, turn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--engine", default=SimSettings().engine, choices=ENGINES,
                        help="world.engine (default: the library's)")
    parser.add_argument("--robot", default=SimSettings().robot, help="sim.robot (default: the library's)")
    parser.add_argument("--pushes", type=int, default=300, help="pushes of the throughput run (default 300)")
    parser.add_argument("--wheel-friction", type=float, default=DriveSettings().wheel_friction,
                        help="p3dx tyre-floor friction (default: the documented 0.5)")
    args = parser.parse_args()
    settings = SimSettings(engine=args.engine, robot=args.robot,
                           drive=DriveSettings(wheel_friction=args.wheel_friction))
    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); world.engine={settings.engine} "
          f"sim.robot={settings.robot} "
          f"wheel_friction={settings.drive.wheel_friction}")
    straight = mass_effect_cm(settings, 0.0)
    turning = [mass_effect_cm(settings, rate) for rate in (-10.0, 10.0)]
    print(f"mass effect, 0.1 kg vs 5 kg cube at friction 0.4: straight {straight:.2f} cm; "
          f"turning -10/+10 deg/s {turning[0]:.2f} / {turning[1]:.2f} cm")
    friction = [friction_effect_cm(settings, rate) for rate in (0.0, 10.0)]
    print(f"friction effect, 0.5 kg cube at friction 0.1 vs 0.9: straight {friction[0]:.2f} cm; "
          f"turning +10 deg/s {friction[1]:.2f} cm")
    gaps = {}
    for name in MIRROR_OBJECTS:
        gaps[name] = mirror_gap(name, settings)
        print(f"mirror {name}: {gaps[name][0]:.1f} mm, {gaps[name][1]:.2f} deg")
    with tempfile.TemporaryDirectory(prefix="pushtorch-physics-") as tmp:
        rate, seconds, _ = measure(load_object("cube"), default_workers(), args.pushes, 10, Path(tmp), settings)
    print(f"throughput: {args.pushes} pushes in {seconds:.1f} s on {default_workers()} workers")
    if settings.engine != "pybullet":
        reference = replace(settings, engine="pybullet")
        with tempfile.TemporaryDirectory(prefix="pushtorch-physics-") as tmp:
            pybullet_rate, _, _ = measure(load_object("cube"), default_workers(), args.pushes, 10, Path(tmp),
                                          reference)
        print(f"pybullet in the same run: {pybullet_rate:.1f} pushes/s; {settings.engine}/pybullet ="
              f" {rate / pybullet_rate:.2f}")
    worst = max(g for g, _ in gaps.values())
    print(f"mass_effect_cm={straight:.2f} mirror_mm={worst:.1f} pushes_per_s={rate:.1f}")


if __name__ == "__main__":
    main()
