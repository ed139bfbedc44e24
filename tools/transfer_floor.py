"""How well can *any* model trained on one object predict another? The transfer floor of issue 17.

pushtorch learns motions from pushes of a training object (the cube for the cube and the prisms, the
cylinder for the cylinders and the hybrid) and moves the test object by them, expressed in the robot's
start frame (docs/method.md, "Motion frames"). Its best possible answer is therefore the training
object's own motion from the *same* placement: the bumper's centre line the same distance from the face's
centre, the same heading to the face, the same action and physics. This tool simulates exactly that pair
of pushes (test object and training object, both in pybullet) and scores:

* ``floor``: the training object's motion from the same placement, moved to the test object's true start
  (what a perfect model of the training object predicts; it sees the true placement, so it is an oracle);
* ``mean``: the mean over the placements of the training object's motions, per action (what the
  ``mean_motion`` baseline predicts when it is trained on these placements);
* ``best``: for each test push, the training push of the same action (any placement) whose motion lands
  nearest the truth. This oracle *picks with the truth*: it shows how far the training motions reach, not
  what a model can reach, and it falls as ``--placements`` grows (more pushes to pick from).

With ``--models CUBE.npz CYLINDER.npz`` (trained models, e.g. from a run folder's ``models/``) it also predicts
every test push with pushtorch from the same start (``predict(..., robot_start=)``; the model of the training
object, H_r's choice between the two for held-out shapes) and prints its scores beside them: a
model at the floor has learnt all the training object can teach.

All are scored as the experiments score a prediction: the displacement applied to the true start pose,
H_acc with the test object's own dimensions and symmetries, and the raw linear error. If ``floor / mean``
is above issue 17's 0.85 on an object, a model that knew the training object perfectly would still miss
that target there: the test object itself moves differently (a thinner body slides farther along the
bumper while it turns). For held-out shapes (``--held-out N``) the floor takes the better of the two
training objects per shape, as adaptive model selection at best would.

With ``--shapes N`` it also measures the **many-shape floor**: the same pushes of ``N`` generated training shapes
(``shapes:mixed:N``, seeds below the held-out set's), and per test object the one shape whose own motion from the
same placement lands nearest the truth on average (an oracle pick among the shapes, as the floor's pick of the
better training object). Below the single-object floor, the pooled kernels hold motions closer to the test
object's than the paper's training objects do; above it, no choice among those shapes can beat the floor. With
``--shape-model POOLED.npz`` (a pooled model, e.g. ``runs/<run>/models/shapes_*.npz``) pushtorch_shapes predicts
the same pushes.

``turn rad`` is how far the test object turns in the robot's start frame under the −10 °/s action (mean over
the placements): the robot turns −0.70 rad in the 4 s, so an object sticking to the bumper turns about that much,
and a round object, rolling along the bumper, turns the other way.

The placements are issue 17's ``placement_spread`` set by default (bumper centre line ±0.1 m, heading ±5°,
2 mm short); ``--lateral 0.03 --yaw-deg 2`` is close to where the contact model puts the robot.

    .venv/bin/python tools/transfer_floor.py [--placements 16] [--lateral 0.1] [--yaw-deg 5]
        [--friction 0.3] [--mass 0.5] [--held-out 9] [--models CUBE.npz CYLINDER.npz] [--shapes 40]
    [--shape-model POOLED.npz]

The last line is exactly ``objects=<n> floor_over_085=<count> worst_floor_ratio=<r>``, followed with ``--shapes`` by
`` shapes_floor_below_floor=<k>/<n>`` (on the catalogue objects and held-out shapes scored).
"""

from __future__ import annotations

import argparse
import math
import time
from importlib.resources import files

import torch
import yaml
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch import se3
from pushtorch.evaluation.baselines import replay_motion
from pushtorch.evaluation.metrics import accuracy, displaced
from pushtorch.experiments.common import observe
from pushtorch.experiments.report import PAPER_LINEAR_CM
from pushtorch.models.library import ModelLibrary
from pushtorch.models.model import PushModel, load_model
from pushtorch.models.motion import local_motions
from pushtorch.objects import ObjectModel, load_object
from pushtorch.objects.shapes import held_out_shapes, training_shapes
from pushtorch.prediction import predict_many
from pushtorch.sim import SimSettings, make_actions, place_robot_against
from pushtorch.sim.runner import simulate_pushes

#: The paper's transfer pairs (test object: training object), read from the friction-biasing experiment.
TRAINING_OBJECT_OF = yaml.safe_load((files("pushtorch.conf") / "experiment" / "friction_biasing.yaml")
                                    .read_text())["experiment"]["training_object_of"]
ACTIONS = make_actions(3, dtype=torch.float64)  # the paper's three actions: −10, 0, +10 °/s at 0.1 m/s


def placements(count: int, lateral: float, yaw_deg: float, seed: int = 0) -> torch.Tensor:
    """``(count, 2)`` uniform (heading offset rad, lateral offset m) pairs, the same for every object."""
    generator = torch.Generator().manual_seed(seed)
    u = torch.rand(count, 2, generator=generator, dtype=torch.float64) * 2 - 1
    return torch.stack([u[:, 0] * math.radians(yaw_deg), u[:, 1] * lateral], dim=-1)


def robot_frame_motions(obj: ObjectModel, offsets: torch.Tensor, friction: float, mass: float,
                        settings: SimSettings) -> tuple[se3.Pose, se3.Pose, se3.Pose, se3.Pose]:
    """Simulate ``obj`` from every placement and action: the robot starts ``(P,)``, the object's true start
    and final poses ``(P, A)`` and its motion in the robot's start frame ``R0⁻¹ ∘ B1 ∘ B0⁻¹ ∘ R0``."""
    pose = obj.resting_pose()
    starts = [place_robot_against(obj.mesh, pose, float(h), float(s), 0.002) for h, s in offsets]
    robot = se3.Pose(torch.stack([s.p for s in starts]).double(), torch.stack([s.q for s in starts]).double())
    P, A = len(starts), len(ACTIONS)
    robot_pa = se3.Pose(robot.p[:, None].expand(P, A, 3), robot.q[:, None].expand(P, A, 4))
    initial = se3.Pose(pose.p.double().expand(P, A, 3), pose.q.double().expand(P, A, 4))
    records = simulate_pushes(obj, robot_pa, initial, ACTIONS.expand(P, A, 2), mass, friction, settings=settings)
    final = se3.Pose(records.object_final.p.reshape(P, A, 3), records.object_final.q.reshape(P, A, 4))
    return robot, initial, final, local_motions(robot_pa, se3.compose(final, se3.inverse(initial)))


def score(test: ObjectModel, robot: se3.Pose, initial: se3.Pose, truth_final: se3.Pose,
          motion: se3.Pose) -> tuple[torch.Tensor, torch.Tensor]:
    """H_acc and linear error (cm) ``(P, A)`` of robot-frame motions ``(P, A)`` moved to the test object's
    starts ``(P, A)`` (broadcast: motions ``(P, 1, A)`` against starts ``(1, P, A)`` give ``(P, P, A)``)."""
    shape = torch.broadcast_shapes(initial.batch_shape, motion.batch_shape)
    robot_pa = se3.Pose(robot.p[..., None, :].expand(*shape, 3), robot.q[..., None, :].expand(*shape, 4))
    estimate = replay_motion(motion.expand(*shape), robot_pa, initial.expand(*shape))
    acc = accuracy(estimate.reshape(-1), truth_final.expand(*shape).reshape(-1), test)
    return acc.hacc.double().reshape(shape), acc.linear_cm.double().reshape(shape)


def pushtorch_scores(test: ObjectModel, model: PushModel | ModelLibrary, robot: se3.Pose, initial: se3.Pose,
                     truth_final: se3.Pose) -> tuple[float, float]:
    """Mean H_acc and linear error (cm) of pushtorch's predictions from the given starts ``(P,)`` of every
    action, from the test object's single-shot cloud, scored on the displacement from the true start."""
    first = model.models[0] if isinstance(model, ModelLibrary) else model
    _, features = observe(test, se3.Pose(initial.p[0, 0].float(), initial.q[0, 0].float()), first.settings)
    P, A = initial.batch_shape
    actions = ACTIONS.float().repeat(P, 1)
    starts = [se3.Pose(robot.p[i].float(), robot.q[i].float()) for i in range(P) for _ in range(A)]
    predictions = predict_many(model, [features] * (P * A), actions, seed=0, robot_starts=starts)
    estimate = se3.Pose.stack([p.condition.object_pose for p in predictions]).to(torch.float64)
    final = se3.Pose.stack([p.final_pose for p in predictions]).to(torch.float64)
    moved = displaced(estimate, final, initial.reshape(P * A))
    acc = accuracy(moved, truth_final.reshape(P * A), test)
    return float(acc.hacc.double().mean()), float(acc.linear_cm.double().mean())


def transfer_scores(test: ObjectModel, trainers: list[ObjectModel], offsets: torch.Tensor, friction: float,
                    mass: float, settings: SimSettings, cache: dict,
                    model: PushModel | ModelLibrary | None = None) -> dict:
    """Floor, mean-motion and best-push scores (H_acc, cm) of ``test`` against its better training object (by
    the floor's H_acc), and pushtorch's with ``model`` (a library chooses by H_r, whatever the floor chose)."""
    robot, initial, truth_final, own = robot_frame_motions(test, offsets, friction, mass, settings)
    # how far the object turns in the robot's start frame under the first (−10 °/s) action: the robot turns
    # −0.70 rad; an object that sticks to the bumper turns with it, a round one spins the other way
    turn = float(se3.yaw_of(own.q[:, 0]).mean())
    chosen = None
    for trainer in trainers:
        if trainer.name not in cache:
            cache[trainer.name] = robot_frame_motions(trainer, offsets, friction, mass, settings)[3]
        motion = cache[trainer.name]
        floor = score(test, robot, initial, truth_final, motion)
        mean = se3.mean_pose(motion, dim=0)  # per action, over the placements
        P, A = motion.batch_shape
        mean_motion = se3.Pose(mean.p[None].expand(P, A, 3), mean.q[None].expand(P, A, 4))
        # every training push (rows) against every test push (columns) of the same action
        every = score(test, se3.Pose(robot.p[None], robot.q[None]), initial.unsqueeze(0), truth_final.unsqueeze(0),
                      motion.unsqueeze(1))
        nearest = every[0].argmin(dim=0, keepdim=True)
        result = {"trainer": trainer.name,
                  "floor": tuple(float(x.mean()) for x in floor),
                  "mean": tuple(float(x.mean()) for x in score(test, robot, initial, truth_final, mean_motion)),
                  "best": tuple(float(x.gather(0, nearest).mean()) for x in every)}
        if chosen is None or result["floor"][0] < chosen["floor"][0]:
            chosen = result
    if model is not None:
        chosen["pushtorch"] = pushtorch_scores(test, model, robot, initial, truth_final)
    chosen["turn"] = turn
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=16, help="placements per object (× 3 actions)")
    parser.add_argument("--lateral", type=float, default=0.1, help="m, uniform ± bumper centre-line offset")
    parser.add_argument("--yaw-deg", type=float, default=5.0, help="deg, uniform ± heading offset")
    parser.add_argument("--friction", type=float, default=0.3, help="ground friction of every push")
    parser.add_argument("--mass", type=float, default=0.5, help="kg, every object's mass")
    parser.add_argument("--held-out", type=int, default=0, help="also this many held-out random shapes")
    parser.add_argument("--models", nargs=2, metavar=("CUBE", "CYLINDER"),
                        help="model files trained on the cube and the cylinder: also score pushtorch")
    parser.add_argument("--shapes", type=int, default=0, help="also the many-shape floor over this many shapes")
    parser.add_argument("--shape-model", help="a pooled model file: also score pushtorch_shapes")
    args = parser.parse_args()
    shapes = training_shapes(f"shapes:mixed:{args.shapes}") if args.shapes else []
    shape_model = load_model(args.shape_model) if args.shape_model else None
    models = {}
    if args.models:
        models = dict(zip(("cube", "cylinder"), (load_model(path) for path in args.models), strict=True))
        models["either"] = ModelLibrary([models["cube"], models["cylinder"]])

    started = time.perf_counter()
    settings = SimSettings()
    offsets = placements(args.placements, args.lateral, args.yaw_deg)
    print(f"cpu: {cpu_name()}; {args.placements} placements x {len(ACTIONS)} actions per object, "
          f"lateral ±{args.lateral} m, heading ±{args.yaw_deg}°, friction {args.friction}, mass {args.mass} kg")
    cache: dict = {}
    tests = [(name, [load_object(TRAINING_OBJECT_OF[name])], load_object(name), models.get(TRAINING_OBJECT_OF[name]))
             for name in TRAINING_OBJECT_OF]
    both = [load_object("cube"), load_object("cylinder")]
    tests += [(shape.name, both, shape, models.get("either")) for shape in held_out_shapes(args.held_out)]
    print("H_acc (and linear cm) of the displacement; ratios to the mean motion's H_acc")
    columns = ("mean", "floor", "best", *(("pushtorch",) if models else ()),
               *(("shapes_floor",) if shapes else ()), *(("pushtorch_shapes",) if shape_model else ()))
    print(f"{'object':<18} {'trained on':<9} " + " ".join(f"{c:>13}" for c in columns)
          + f" {'floor/mean':>10} {'best/mean':>9}" + (f" {'pushtorch/mean':>14}" if models else "")
          + f" {'paper cm':>8} {'turn rad':>8}" + (f" {'nearest shape':>16}" if shapes else ""))
    ratios, below = [], []
    for name, trainers, test, model in tests:
        result = transfer_scores(test, trainers, offsets, args.friction, args.mass, settings, cache, model)
        nearest = ""
        if shapes:
            many = transfer_scores(test, shapes, offsets, args.friction, args.mass, settings, cache, shape_model)
            result["shapes_floor"] = many["floor"]
            if shape_model is not None:
                result["pushtorch_shapes"] = many["pushtorch"]
            below.append(many["floor"][0] < result["floor"][0])
            nearest = f" {many['trainer']:>16}"
        mean_h = max(result["mean"][0], 1e-12)
        ratios.append(result["floor"][0] / mean_h)
        paper = PAPER_LINEAR_CM.get(name)
        cells = " ".join(f"{h:>6.3f} ({cm:>4.1f})" for h, cm in (result[k] for k in columns))
        ours = f" {result['pushtorch'][0] / mean_h:>14.2f}" if models else ""
        print(f"{name:<18} {result['trainer']:<9} {cells} {ratios[-1]:>10.2f} "
              f"{result['best'][0] / mean_h:>9.2f}{ours} {'' if paper is None else f'{paper:.2f}':>8} "
              f"{result['turn']:>8.2f}{nearest}",
              flush=True)
    print(f"{time.perf_counter() - started:.0f} s")
    last = f"objects={len(ratios)} floor_over_085={sum(r > 0.85 for r in ratios)} worst_floor_ratio={max(ratios):.2f}"
    if shapes:
        last += f" shapes_floor_below_floor={sum(below)}/{len(below)}"
    print(last)


if __name__ == "__main__":
    main()
