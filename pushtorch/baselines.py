"""Baselines the paper's predictor is measured against (paper, §Pose Estimation Accuracy; issue 5's tables).

* centroid (pose): :func:`pushtorch.models.position.centroid_pose`, the approach of the authors'
  earlier work;
* no motion: the object stays where it was estimated to be;
* mean motion: the training pushes' average object motion, taken in the robot's start frame and
  applied from the predicted robot start pose to the estimated initial pose;
* nominal physics: pybullet with the training prior's mean mass and friction, pushing the object's
  mesh from the estimated initial pose — what most users would try first. It is given the true mesh
  (a real user of a novel object would not have it), which makes it an optimistic baseline.
"""

from __future__ import annotations

import torch

from pushtorch import se3
from pushtorch.models.motion import MotionModel
from pushtorch.models.position import centroid_pose
from pushtorch.objects import ObjectModel

__all__ = ["centroid_pose", "mean_motion_prediction", "no_motion_prediction", "nominal_physics_prediction"]


def no_motion_prediction(initial_estimate: se3.Pose) -> se3.Pose:
    """The final pose predicted by a model that expects nothing to move."""
    return initial_estimate


def mean_motion_prediction(motion: MotionModel, robot_start: se3.Pose, initial_estimate: se3.Pose) -> se3.Pose:
    """``B1 = R0 ∘ M̄ ∘ R0⁻¹ ∘ B0'``: the average training motion (robot frame) applied to this push."""
    world_motion = se3.compose(robot_start, se3.compose(motion.mean_motion, se3.inverse(robot_start)))
    return se3.compose(world_motion, initial_estimate)


def nominal_physics_prediction(
    obj: ObjectModel,
    robot_start: se3.Pose,
    initial_estimate: se3.Pose,
    action: torch.Tensor,
    mass: float,
    ground_friction: float,
) -> se3.Pose:
    """Simulate the push once with nominal parameters from the estimated pose (see the module docstring).

    The estimate is first set upright on the ground (a physics engine cannot start a tilted object
    half inside the floor).
    """
    from pushtorch.sim.runner import simulate_pushes

    upright = obj.resting_pose(
        float(initial_estimate.p[0]), float(initial_estimate.p[1]), float(se3.yaw_of(initial_estimate.q))
    )
    records = simulate_pushes(obj, robot_start, upright, action, mass, ground_friction)
    final = records.object_final
    return se3.Pose(final.p[0].to(initial_estimate.p.dtype), final.q[0].to(initial_estimate.q.dtype))
