"""Bodies from observed clouds and their batched rollouts: the physics every cloud-based predictor shares
(beyond the paper, whose predictor is learned alone; its §Conclusions and future work ask for transfer to
shapes unlike the training ones, where a simulator on the observed shape knows what local contact cannot).

* :func:`cloud_body`: the rigid body a single-shot cloud builds (the visible surface's convex hull swept down
  to the ground) and its pose.
* :func:`rollout_ensemble`: one push of that body rolled out for an ensemble of ``(μ, m)``, in one call to the
  configured engine. ``physics_from_cloud``, ``physics_ensemble``
  (:mod:`pushtorch.evaluation.baselines`) and the residual model (:mod:`pushtorch.models.residual`) roll out
  through it, so they are compared like for like.

It sits in ``sim``, below ``models``, so a model can roll out; nothing here learns.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.objects import ObjectModel, Symmetry

__all__ = ["cloud_body", "rollout_ensemble"]


def cloud_body(points: torch.Tensor, initial_estimate: se3.Pose,
               name: str = "cloud_hull") -> tuple[ObjectModel, se3.Pose]:
    """A rigid body reconstructed from an observed cloud, and its pose: the convex hull of the points and of
    their projections onto the ground (z = 0), i.e. the visible surface swept down to the floor.

    The body frame sits at the hull's centre of mass with the estimate's heading (the frame only names the
    body: the displacement a push gives does not depend on it). Hidden parts the camera could not see and
    concavities are filled or missing exactly as the sweep makes them.

    Raises:
        ModelError: the cloud spans no volume (fewer than 4 points off one plane), or has non-finite points.
    """
    world = points.detach().double().cpu().numpy().reshape(-1, 3)
    if not np.isfinite(world).all():
        raise ModelError("the observed cloud has non-finite points: no body to simulate")
    ground = world.copy()
    ground[:, 2] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by a flat hull's zero volume
        try:
            hull = trimesh.convex.convex_hull(np.concatenate([world, ground]))
        except Exception as exc:  # scipy's QhullError on flat or degenerate point sets
            raise ModelError(f"the observed cloud ({len(world)} points) spans no volume to simulate") from exc
        volume = hull.volume
    if not volume > 0:
        raise ModelError(f"the observed cloud ({len(world)} points) spans no volume to simulate")
    centre = np.asarray(hull.center_mass)
    yaw = float(se3.yaw_of(initial_estimate.q.reshape(4)))
    pose = se3.from_xy_yaw(float(centre[0]), float(centre[1]), yaw, z=float(centre[2])).to(torch.float64)
    to_body = np.linalg.inv(se3.to_matrix(pose).numpy())
    body = hull.copy()
    body.apply_transform(to_body)
    identity = Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    return ObjectModel(name, body, identity), pose


def rollout_ensemble(body: ObjectModel, start: se3.Pose, robot_start: se3.Pose, action: torch.Tensor,
                     friction: torch.Tensor, mass: torch.Tensor, settings=None):
    """One push of ``body`` from ``start`` rolled out for every ``(friction[i], mass[i])`` in one call to the
    engine of ``settings`` (a :class:`~pushtorch.sim.settings.SimSettings`; default pybullet's).

    Args:
        start, robot_start: ``()`` the body's and the robot's start poses (world).
        action: ``(2,)`` (ẋ m/s, θ̇ rad/s); friction, mass: ``(N,)``.

    Returns:
        :class:`~pushtorch.sim.records.PushRecords` of the ``N`` rollouts (float64), in order.

    Raises:
        InvalidParameterError: an empty or misshaped ensemble.
    """
    from pushtorch.sim.runner import simulate_pushes

    friction = torch.as_tensor(friction, dtype=torch.float64).reshape(-1)
    mass = torch.as_tensor(mass, dtype=torch.float64).reshape(-1)
    n = int(friction.shape[0])
    if n < 1 or mass.shape[0] != n:
        raise InvalidParameterError(f"an ensemble needs as many masses as frictions, at least one: got "
                                    f"{n} and {int(mass.shape[0])}")
    robot = se3.Pose.unchecked(robot_start.p.double().reshape(1, 3).expand(n, 3),
                               robot_start.q.double().reshape(1, 4).expand(n, 4))
    initial = se3.Pose.unchecked(start.p.double().reshape(1, 3).expand(n, 3),
                                 start.q.double().reshape(1, 4).expand(n, 4))
    act = torch.as_tensor(action, dtype=torch.float64).reshape(1, 2).expand(n, 2)
    return simulate_pushes(body, robot, initial, act, mass, friction, settings=settings)
