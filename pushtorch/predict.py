"""Prediction: partial cloud + action → robot start pose, contact frames, initial pose, final-pose density.

Paper, Fig. pipeline (prediction) and §Query Density / §Motion Model / §Model Selection:

1. *Push condition generation* (:func:`generate_push_condition`): the manipulator contact model's query
   density gives the robot's start pose (annealed on the ground plane) and the manipulator contact frame;
   environment contacts are placed by the environment contact model; the position model's query density
   estimates the object's initial pose (:func:`estimate_pose`, usable on its own).
2. *Prediction* (:func:`predict`): the action's motion model becomes a product of experts over the
   object's final pose (:class:`pushtorch.models.motion.MotionDensity`), optimised by simulated annealing.

With a :class:`~pushtorch.models.library.ModelLibrary`, the model is chosen first by the lowest ``H_r``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.kde import KernelBandwidth
from pushtorch.models.contact import place_environment_contacts
from pushtorch.models.frames import ContactFrames
from pushtorch.models.library import ModelLibrary, ModelSettings, PushModel
from pushtorch.models.motion import MotionDensity, MotionKernels
from pushtorch.models.position import PositionModel
from pushtorch.models.query import QueryResult, build_query_density, optimise_query_density
from pushtorch.perception import PointCloud

__all__ = ["Prediction", "PushCondition", "estimate_pose", "generate_push_condition", "predict", "predict_many"]


@dataclass
class PushCondition:
    """Where the push starts: the paper's "push condition" for one cloud and model."""

    robot_start: se3.Pose  # () base pose on the ground
    manipulator_frame: ContactFrames  # (1,)
    environment_frames: ContactFrames  # (E,)
    object_pose: se3.Pose  # () estimated initial pose B0'
    feature_distance: torch.Tensor  # H_r of the manipulator contact model on this cloud
    robot_query: QueryResult
    pose_query: QueryResult


@dataclass
class Prediction:
    """A predicted push outcome and the density it came from."""

    model_name: str
    action: torch.Tensor  # (2,)
    condition: PushCondition
    final_pose: se3.Pose  # ()
    log_prob: torch.Tensor  # ()
    density: MotionDensity
    candidates: se3.Pose  # (C,) annealed candidates
    candidate_log_prob: torch.Tensor  # (C,)
    anneal: AnnealResult | None = None  # the motion annealing (with per-step history if recorded)


def query_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    c = settings.cutoff_std
    return KernelBandwidth(settings.query_p_std, settings.query_rot_std, cutoff_std=(c, c, c),
                           alpha_t=settings.alpha_t)


def contact_bandwidth(settings: ModelSettings, with_robot_position: bool = True) -> KernelBandwidth:
    """The contact-frame kernel: relation ``u``, embedded curvatures and (for the motion model) the
    frame's position in the robot's start frame."""
    c = settings.cutoff_std
    stds = (settings.descriptor_std,) * 2 + ((settings.contact_robot_std,) * 3 if with_robot_position else ())
    return KernelBandwidth(
        settings.contact_p_std, settings.contact_rot_std, stds,
        cutoff_std=(c, c, settings.descriptor_cutoff_std), alpha_t=settings.alpha_t,
    )


def motion_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    c = settings.cutoff_std
    return KernelBandwidth(settings.motion_p_std, settings.motion_rot_std, cutoff_std=(c, c, c),
                           alpha_t=settings.alpha_t)


def _schedule(settings: ModelSettings, planar: bool) -> AnnealSchedule:
    return AnnealSchedule(steps=settings.anneal_steps, planar=planar)


def _as_features(cloud: PointCloud | SurfaceFeatures, settings: ModelSettings) -> SurfaceFeatures:
    if isinstance(cloud, SurfaceFeatures):
        return cloud
    return compute_surface_features(cloud, radius=settings.feature_radius)


def estimate_pose(
    position: PositionModel,
    cloud: PointCloud | SurfaceFeatures,
    settings: ModelSettings | None = None,
    generator: torch.Generator | None = None,
    record_history: bool = False,
) -> QueryResult:
    """Estimate an object's pose from a (partial) cloud with a position model (paper, Object Position Model).

    Returns the annealed best pose (full SE(3)) with its log density and the annealing record.
    """
    settings = settings or ModelSettings()
    features = _as_features(cloud, settings)
    std = torch.full((2,), settings.descriptor_std)
    density = build_query_density(
        position.frames, features, settings.query_kernels, std, query_bandwidth(settings),
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, generator=generator,
    )
    return optimise_query_density(
        density, settings.anneal_candidates, _schedule(settings, planar=False), generator, record_history
    )


def _subsample(kernels: MotionKernels, count: int, generator: torch.Generator | None) -> MotionKernels:
    if len(kernels) <= count:
        return kernels
    return kernels.take(torch.randperm(len(kernels), generator=generator)[:count])


def generate_push_condition(
    model: PushModel,
    cloud: PointCloud | SurfaceFeatures,
    action_index: int = 0,
    generator: torch.Generator | None = None,
    record_history: bool = False,
) -> PushCondition:
    """Robot start pose, manipulator and environment contact frames, and initial pose (paper, Query Density)."""
    settings = model.settings
    features = _as_features(cloud, settings)
    std = torch.full((2,), settings.descriptor_std)
    robot_density = build_query_density(
        model.contact.frames, features, settings.query_kernels, std, query_bandwidth(settings),
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, project_planar=True,
        heuristic=True, generator=generator,
    )
    robot = optimise_query_density(
        robot_density, settings.anneal_candidates, _schedule(settings, planar=True), generator, record_history
    )
    motion = model.motions[action_index]
    env_kernels = _subsample(motion.environment, settings.environment_kernels, generator)
    environment = place_environment_contacts(
        features, env_kernels.r, env_kernels.u, contact_bandwidth(settings, with_robot_position=False),
        settings.environment_contacts, settings.environment_samples, generator,
    )
    pose = estimate_pose(model.position, features, settings, generator, record_history)
    return PushCondition(robot.pose, robot.nearest_kernel, environment, pose.pose,
                         robot_density.feature_distance, robot, pose)


def predict(
    model: PushModel | ModelLibrary,
    cloud: PointCloud | SurfaceFeatures,
    action,
    generator: torch.Generator | None = None,
    record_history: bool = False,
) -> Prediction:
    """Predict where the object in ``cloud`` ends up after ``action`` (paper, Motion Model, Eq. poe).

    Args:
        model: a trained model, or a library to select from by ``H_r``.
        cloud: the object's single-shot cloud (or its surface features), world frame.
        action: ``(2,)`` (ẋ m/s, θ̇ rad/s), one of the model's actions.
        generator: seeded generator: the same seed gives the same prediction.
    """
    features = _as_features(cloud, model.models[0].settings if isinstance(model, ModelLibrary) else model.settings)
    if isinstance(model, ModelLibrary):
        model, _ = model.select(features)
    settings = model.settings
    a = model.action_index(action)
    condition = generate_push_condition(model, features, a, generator, record_history)
    motion = model.motions[a]
    density = MotionDensity(
        type(motion)(
            motion.action,
            _subsample(motion.manipulator, settings.manipulator_kernels, generator),
            _subsample(motion.environment, settings.environment_kernels, generator),
            motion.mean_motion,
        ),
        condition.manipulator_frame,
        condition.environment_frames,
        condition.object_pose,
        condition.robot_start,
        contact_bandwidth(settings),
        motion_bandwidth(settings),
    )
    result = density.predict(settings.anneal_candidates, _schedule(settings, planar=False), generator,
                             record_history)
    return Prediction(model.name, motion.action, condition, result.final_pose, result.log_prob, density,
                      result.anneal.candidates, result.anneal.log_prob, result.anneal)


def predict_many(
    model: PushModel | ModelLibrary,
    clouds: list[PointCloud | SurfaceFeatures],
    actions,
    seed: int = 0,
) -> list[Prediction]:
    """Predict several conditions (one cloud and action each), each with its own seeded generator."""
    actions = torch.as_tensor(actions).reshape(-1, 2)
    if len(actions) == 1:
        actions = actions.expand(len(clouds), 2)
    out = []
    for i, (cloud, action) in enumerate(zip(clouds, actions, strict=True)):
        out.append(predict(model, cloud, action, torch.Generator().manual_seed(seed + i)))
    return out
