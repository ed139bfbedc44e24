"""Baselines the paper's predictor is measured against (paper, §Pose Estimation Accuracy; issue 15, item 3).

Each prediction baseline sees what the method sees — the single-shot cloud, the push condition the model
chose, the training pushes — unless it is labelled an oracle:

* centroid (pose): :func:`pushtorch.models.position.centroid_pose`, the approach of the authors' earlier work;
* no motion: the object stays where it was estimated to be;
* mean motion: the training pushes' average object motion, taken in the robot's start frame and applied
  from the predicted robot start pose to the estimated initial pose;
* nearest push: the one training push whose manipulator contact frame best matches the test's, by the
  model's own contact kernel ``K^c`` over ``(u, r, g)``, replayed from the estimated pose
  (:func:`nearest_push_prediction`);
* physics from the cloud: pybullet pushing a body reconstructed from the observed cloud — the visible
  surface's convex hull swept down to the ground (:func:`cloud_body`) — with the training prior's mean
  mass and friction (:func:`physics_from_cloud_prediction`);
* physics ensemble: physics from the cloud as a *density*: the push rolled out N times on the reconstructed
  body with friction and mass drawn from the model's training prior, a kernel density of the outcomes with
  the model's motion bandwidth (:func:`physics_ensemble_prediction`); scored on likelihood and coverage;
* oracle physics: pybullet pushing the *true* mesh from the *true* initial pose with the prior's mean mass
  and friction (:func:`oracle_physics_prediction`). It knows what the method cannot (the hidden geometry
  and the exact pose), so reports label it an oracle and leave it out of "beats the baselines" claims;
* physics from the cloud, online: the equal-information peer of a model conditioned on observed pushes
  (:func:`fit_cloud_physics`): each observed push is rolled out on the body its own cloud reconstructs, for
  every ``(μ, m)`` of a grid over the training prior's uniform parameters (:func:`physics_grid`), and the pair
  whose rollouts best reproduce the observed displacements (:func:`displacement_error`) predicts, as physics
  from the cloud does.
"""

from __future__ import annotations

import math

import torch

from pushtorch import se3
from pushtorch.errors import ModelError
from pushtorch.models.motion import MotionModel, contact_log_weights
from pushtorch.models.position import centroid_pose
from pushtorch.objects import ObjectModel
from pushtorch.sim.bodies import cloud_body, rollout_ensemble

__all__ = [
    "centroid_pose",
    "cloud_body",
    "displacement_error",
    "fit_cloud_physics",
    "physics_grid",
    "mean_motion_prediction",
    "nearest_push_prediction",
    "no_motion_prediction",
    "oracle_physics_prediction",
    "physics_from_cloud_prediction",
    "replay_motion",
]


def no_motion_prediction(initial_estimate: se3.Pose) -> se3.Pose:
    """The final pose predicted by a model that expects nothing to move."""
    return initial_estimate


def replay_motion(motion: se3.Pose, robot_start: se3.Pose, initial_estimate: se3.Pose) -> se3.Pose:
    """``R0 ∘ M ∘ R0⁻¹ ∘ B0'``: a motion ``M`` of the robot's start frame (as
    :func:`pushtorch.models.motion.local_motions` expresses it) replayed from the start ``R0`` on the object
    at ``B0'``; batch dims broadcast."""
    world_motion = se3.compose(robot_start, se3.compose(motion, se3.inverse(robot_start)))
    return se3.compose(world_motion, initial_estimate)


def mean_motion_prediction(motion: MotionModel, robot_start: se3.Pose, initial_estimate: se3.Pose) -> se3.Pose:
    """``B1 = R0 ∘ M̄ ∘ R0⁻¹ ∘ B0'``: the average training motion (robot frame) applied to this push."""
    return replay_motion(motion.mean_motion, robot_start, initial_estimate)


def nearest_push_prediction(motion: MotionModel, manipulator_frame, robot_start: se3.Pose,
                            initial_estimate: se3.Pose, contact_bandwidth, contact_patch) -> se3.Pose:
    """The training push whose manipulator contact best matches this push's, replayed (module docstring).

    Args:
        motion: the action's motion model (its manipulator kernels: one per training push and feature).
        manipulator_frame: the push condition's manipulator contact frame (world).
        robot_start, initial_estimate: the push condition's robot start and estimated object pose ``B0'``.
        contact_bandwidth: the model's contact-frame kernel (:func:`pushtorch.prediction.contact_bandwidth`).
        contact_patch: ``(3,)`` the push condition's contact patch on the bumper
            (``PushCondition.contact_patch``).

    Returns:
        ``R0 ∘ m_j ∘ R0⁻¹ ∘ B0'`` for the kernel ``j`` of largest ``K^c`` (the first on ties).
    """
    log_w = contact_log_weights(manipulator_frame, motion.manipulator, robot_start, contact_bandwidth, contact_patch)
    best = int(log_w.reshape(-1, len(motion.manipulator)).amax(0).argmax())
    chosen = motion.manipulator.m.take(best)
    return replay_motion(se3.Pose.unchecked(chosen.p.to(robot_start.p), chosen.q.to(robot_start.q)), robot_start,
                         initial_estimate)


def _simulate_once(obj: ObjectModel, robot_start: se3.Pose, start: se3.Pose, action: torch.Tensor, mass: float,
                   ground_friction: float, settings=None) -> se3.Pose:
    from pushtorch.sim.runner import simulate_pushes

    records = simulate_pushes(obj, robot_start, start, action, mass, ground_friction, settings=settings)
    final = records.object_final
    return se3.Pose.unchecked(final.p[0].float(), final.q[0].float())


def physics_from_cloud_prediction(points: torch.Tensor, initial_estimate: se3.Pose, robot_start: se3.Pose,
                                  action: torch.Tensor, mass: float,
                                  ground_friction: float, settings=None) -> tuple[se3.Pose, se3.Pose]:
    """Simulate the push once on the body :func:`cloud_body` reconstructs from the observed ``points``, in the
    engine of ``settings`` (a :class:`~pushtorch.sim.settings.SimSettings`; the experiments' ``physics.engine``).

    Returns:
        ``(start, final)``: the reconstructed body's pose before and after the push (score the displacement
        between them).
    """
    body, start = cloud_body(points, initial_estimate)
    return start.to(torch.float32), _simulate_once(body, robot_start, start, action, mass, ground_friction, settings)


def physics_ensemble_prediction(points: torch.Tensor, initial_estimate: se3.Pose, robot_start: se3.Pose,
                                action: torch.Tensor, friction_prior, mass_prior, count: int,
                                generator: torch.Generator, settings=None) -> tuple[se3.Pose, se3.Pose]:
    """Physics from the cloud as a density: the push rolled out ``count`` times on the body :func:`cloud_body`
    reconstructs, ground friction and mass drawn from the priors (the model's training prior; anything with
    ``.sample(shape, generator)``), in the engine of ``settings``.

    Returns:
        ``(start, finals)``: the reconstructed body's pose before the push ``()`` and after each rollout
        ``(count,)``; :func:`pushtorch.evaluation.likelihood.ensemble_density` makes them a density.

    Raises:
        InvalidParameterError: ``count`` < 1. ModelError: a cloud that spans no volume.
    """
    from pushtorch.errors import InvalidParameterError

    if isinstance(count, bool) or int(count) != count or count < 1:
        raise InvalidParameterError(f"a physics ensemble needs at least one rollout, got {count!r}")
    n = int(count)
    body, start = cloud_body(points, initial_estimate)
    friction = torch.as_tensor(friction_prior.sample((n,), generator), dtype=torch.float64).reshape(n)
    mass = torch.as_tensor(mass_prior.sample((n,), generator), dtype=torch.float64).reshape(n)
    final = rollout_ensemble(body, start, robot_start, action, friction, mass, settings).object_final
    return start.to(torch.float32), se3.Pose.unchecked(final.p.float(), final.q.float())


def oracle_physics_prediction(obj: ObjectModel, robot_start: se3.Pose, truth_initial: se3.Pose,
                              action: torch.Tensor, mass: float, ground_friction: float,
                              settings=None) -> se3.Pose:
    """An oracle: the true mesh pushed from the true initial pose, once, with the prior's mean parameters, in the
    engine of ``settings`` (an oracle of the object and its pose, not of the world's engine)."""
    return _simulate_once(obj, robot_start, truth_initial, action, mass, ground_friction, settings)


#: The lever arm (m) that weighs a heading error against a position error in :func:`displacement_error`.
ROTATION_LEVER = 0.1


def displacement_error(start: se3.Pose, moved: se3.Pose, observed: se3.Pose) -> torch.Tensor:
    """How far a simulated world motion (``start`` → ``moved``, ``(...)``) is from an observed one (``observed``,
    the world motion ``W = B1 ∘ B0⁻¹``): the distance between where each carries the body's centre plus the
    heading difference times :data:`ROTATION_LEVER` (m), ``(...)``."""
    centre = start.p.double()
    simulated = se3.compose(moved, se3.inverse(start))
    obs = se3.Pose.unchecked(observed.p.double().expand_as(centre), observed.q.double().expand_as(start.q.double()))
    sim = se3.Pose.unchecked(simulated.p.double(), simulated.q.double())
    gap = (se3.apply(sim, centre) - se3.apply(obs, centre)).norm(dim=-1)
    turn = se3.yaw_of(sim.q) - se3.yaw_of(obs.q)
    turn = torch.atan2(torch.sin(turn), torch.cos(turn)).abs()
    return gap + ROTATION_LEVER * turn


def physics_grid(friction_prior, mass_prior, count: int) -> torch.Tensor:
    """``(G, 2)`` float64 ``(μ, m)``: ``count`` quantiles of each uniform prior (masses spaced in log) and the mean
    of each other one (a general prior's narrow or fixed second parameter), their product."""
    def axis(prior, log: bool) -> torch.Tensor:
        if type(prior).__name__ != "Uniform":
            return torch.tensor([prior.mean], dtype=torch.float64)
        u = (torch.arange(count, dtype=torch.float64) + 0.5) / count
        if log:
            return torch.exp(math.log(prior.low) + (math.log(prior.high) - math.log(prior.low)) * u)
        return prior.low + (prior.high - prior.low) * u

    return torch.cartesian_prod(axis(friction_prior, False), axis(mass_prior, True)).reshape(-1, 2)


def fit_cloud_physics(observations, grid: torch.Tensor, settings=None) -> torch.Tensor:
    """``(K, G)`` float64 the displacement error (m, :func:`displacement_error`) of every observed push ``(K)``
    rolled out on the body its own cloud reconstructs (:func:`cloud_body`, from its observed initial pose and
    robot start) under every ``(μ, m)`` of ``grid (G, 2)``. The peer's fit after ``k`` pushes is
    ``grid[errors[:k].pow(2).sum(0).argmin()]``. ``settings``: the engine the peer rolls out in.

    Raises:
        ModelError: an observation without its robot start, or a cloud that spans no volume.
    """
    rows = []
    for o in observations:
        if o.robot_start is None:
            raise ModelError("physics from the cloud needs each observed push's robot start")
        points = o.cloud.points if hasattr(o.cloud, "points") else o.cloud.p
        body, start = cloud_body(points, o.initial_pose)
        records = rollout_ensemble(body, start, o.robot_start, o.action, grid[:, 0], grid[:, 1], settings)
        initial = se3.Pose.unchecked(start.p.reshape(1, 3).expand(grid.shape[0], 3),
                                     start.q.reshape(1, 4).expand(grid.shape[0], 4))
        rows.append(displacement_error(initial, records.object_final, o.displacement))
    return torch.stack(rows) if rows else torch.zeros(0, grid.shape[0], dtype=torch.float64)
