"""Push conditions (paper, Fig. pipeline, prediction; §Query Density, §Model Selection): the robot's start
and manipulator contact frame, the environment contacts and the object's estimated initial pose.

*Push condition generation* (:func:`generate_push_condition`, :func:`push_conditions` for several clouds):
each model does its part in one call. The manipulator contact model's query density gives the robot's start
pose (:meth:`~pushtorch.models.contact.ManipulatorContactModel.robot_query`, annealed on the ground plane) and
the manipulator contact frame; the action's motion model places the environment contacts
(:meth:`~pushtorch.models.motion.MotionModel.environment_frames`); the position model's query density
estimates the object's initial pose (:meth:`~pushtorch.models.position.PositionModel.pose_query`,
:func:`estimate_pose`, usable on its own). The annealed start is then cleared of the observed cloud
(:mod:`pushtorch.models.clearance`). Prediction (:mod:`pushtorch.prediction`) and the evidence of observed
pushes (:mod:`pushtorch.models.evidence`) build their conditions here.

A caller may also give the robot's start: the robot query is skipped and the manipulator contact frame is
the observed feature that touches the bumper at that start (:func:`manipulator_frame_at`); the rest is
unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealSchedule
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.kde import Evaluation, KernelBandwidth
from pushtorch.models.clearance import (
    GIVEN_START_OVERLAP,
    MAX_BACKOFF,
    check_start,
    clear_robot_start,
    clearance_points,
    overlap_message,
)
from pushtorch.models.contact import bumper_contact_patch, bumper_contacts
from pushtorch.models.frames import ContactFrames
from pushtorch.models.position import PositionModel, verify_pose_candidates
from pushtorch.models.query import (
    QueryResult,
    feature_distance_heuristic,
    heuristic_descriptors,
    optimise_query_densities,
    optimise_query_density,
)
from pushtorch.models.settings import ModelSettings, as_generator
from pushtorch.perception import PointCloud
from pushtorch.robot import backoff_distance, bumper_mesh

if TYPE_CHECKING:
    from pushtorch.models.model import PushModel

__all__ = [
    "PushCondition",
    "anneal_schedule",
    "candidate_conditions",
    "contact_bandwidth",
    "estimate_pose",
    "features_for",
    "generate_push_condition",
    "given_start_frame",
    "manipulator_frame_at",
    "manipulator_frames_at",
    "motion_bandwidth",
    "push_conditions",
    "query_bandwidth",
]

log = logging.getLogger(__name__)



@dataclass
class PushCondition:
    """Where the push starts: the paper's "push condition" for one cloud and model.

    ``robot_start`` clears the observed cloud by :data:`START_CLEARANCE`: it is the robot query's annealed
    pose backed off along the approach by ``backoff`` metres when that pose overlapped the cloud. A back-off
    beyond :data:`MAX_BACKOFF` makes the condition invalid (:attr:`valid`, :meth:`check_start`).
    """

    robot_start: se3.Pose  # () base pose on the ground
    manipulator_frame: ContactFrames  # (1,)
    environment_frames: ContactFrames  # (E,)
    object_pose: se3.Pose  # () estimated initial pose B0'
    robot_query: QueryResult | None  # None: the caller gave the start (no robot query was annealed)
    pose_query: QueryResult
    features: SurfaceFeatures = field(repr=False)  # the cloud's surface features
    model: PushModel = field(repr=False)
    #: metres the annealed start (``robot_query.pose``) was moved back along the approach to clear the
    #: observed cloud by START_CLEARANCE (:func:`clear_robot_start`); 0.0 when it already cleared.
    backoff: float = 0.0

    @property
    def valid(self) -> bool:
        """False when the annealed start overlapped the observed object so deeply that clearing it took more
        than :data:`MAX_BACKOFF`: the push starts from where the model would not have put the robot (the
        start itself is still collision-free). Score or report such conditions apart."""
        return self.backoff <= MAX_BACKOFF

    def check_start(self) -> PushCondition:
        """This condition, if :attr:`valid`.

        Raises:
            ModelError: the model's start overlapped the observed object beyond :data:`MAX_BACKOFF` of
                back-off (the message names the overlap).
        """
        if not self.valid:
            raise ModelError(overlap_message(self.backoff, self.model.name))
        return self

    @cached_property
    def contact_patch(self) -> torch.Tensor:
        """``(3,)`` where and how the object sits on the bumper at :attr:`robot_start`: the lateral extent (m,
        robot frame) and heading (rad) of the observed surface the bumper meets first
        (:func:`pushtorch.models.contact.bumper_contact_patch`), compared with the training pushes' patches."""
        points = se3.apply(se3.inverse(self.robot_start), self.features.p)
        return bumper_contact_patch(points, self.model.settings.contact_cutoff)

    @cached_property
    def feature_distance(self) -> torch.Tensor:
        """``H_r`` of the model's manipulator contact model on this cloud (computed on first use; the
        value :meth:`ModelLibrary.feature_distances` selects by)."""
        return feature_distance_heuristic(heuristic_descriptors(self.features), self.model.contact.frames.r,
                                          Evaluation.FAST)


def query_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    """The query densities' kernel: :attr:`ModelSettings.query_bandwidth`."""
    return settings.query_bandwidth


def contact_bandwidth(settings: ModelSettings, with_robot_position: bool = True) -> KernelBandwidth:
    """The contact-frame kernel: :attr:`ModelSettings.contact_bandwidth` (the motion model's, with the frame's
    position and patch) or :attr:`ModelSettings.environment_contact_bandwidth` (without)."""
    return settings.contact_bandwidth if with_robot_position else settings.environment_contact_bandwidth


def motion_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    """The motion kernels' bandwidth: :attr:`ModelSettings.motion_bandwidth`."""
    return settings.motion_bandwidth


def anneal_schedule(settings: ModelSettings, planar: bool, method: Evaluation) -> AnnealSchedule:
    """The paper's schedule for the dense reference; the fast path's shorter one (then polished)."""
    steps = settings.fast_anneal_steps if method is Evaluation.FAST else settings.anneal_steps
    return AnnealSchedule(steps=steps, planar=planar)


def features_for(cloud: PointCloud | SurfaceFeatures, settings: ModelSettings,
                 position: PositionModel) -> SurfaceFeatures:
    """The cloud's surface features in the dtype of ``position`` (a model's position model) on its device (a
    float64 cloud is cast before its features are computed, so it predicts exactly as the same cloud in float32).
    Features are computed on the CPU (open3d's neighbourhoods and normals) and then moved."""
    dtype, device = position.frames.r.dtype, position.frames.r.device
    if isinstance(cloud, SurfaceFeatures):
        features = cloud if cloud.p.dtype == dtype else cloud.to(dtype)
    else:
        if isinstance(cloud, PointCloud):
            if cloud.points.dtype != dtype or cloud.points.device.type != "cpu":
                origins = None if cloud.view_origins is None else cloud.view_origins.to("cpu", dtype)
                cloud = PointCloud(cloud.points.to("cpu", dtype), origins)
        else:
            cloud = PointCloud(cloud)  # validates an array or tensor (shape, NaN, empty)
            cloud = PointCloud(cloud.points.to("cpu", dtype))
        features = compute_surface_features(cloud, radius=settings.feature_radius)
    return features if features.p.device == device else features.to(device)


def estimate_pose(
    position: PositionModel,
    cloud: PointCloud | SurfaceFeatures,
    settings: ModelSettings | None = None,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: Evaluation | str = Evaluation.FAST,
) -> QueryResult:
    """Estimate an object's pose from a (partial) cloud with a position model (paper, Object Position Model).

    Returns the best pose (full SE(3)) with its log density and the annealing record: the annealing's
    candidates (hypotheses of the query density) verified by their surface fit to the cloud
    (:func:`pushtorch.models.position.verify_pose_candidates`).
    ``method``: :attr:`Evaluation.FAST` (default: pruned, fused densities) or :attr:`Evaluation.DENSE` (the
    reference), or its string; the same law, another random stream.

    Raises:
        InvalidParameterError: an unknown method.
    """
    method = Evaluation.of(method)
    settings = settings or ModelSettings()
    generator = as_generator(generator)
    features = features_for(cloud, settings, position)
    density = position.pose_query(features, settings, generator, method)
    polish = settings.polish_steps if method is Evaluation.FAST else 0
    result = optimise_query_density(
        density, settings.anneal_candidates, anneal_schedule(settings, False, method), generator, record_history,
        method, polish,
    )
    return _verified_pose(result, position, features, generator)


def _verified_pose(result: QueryResult, position: PositionModel, features: SurfaceFeatures,
                   generator: torch.Generator | None) -> QueryResult:
    """The annealed candidate whose surface best fits the cloud (docs/method.md, pose verification)."""
    candidates = result.anneal.candidates
    best = verify_pose_candidates(position, features.p, candidates, result.anneal.log_prob, generator)
    return replace(result, pose=candidates.take(best), log_prob=result.anneal.log_prob[best])


def manipulator_frame_at(features: SurfaceFeatures, robot_start: se3.Pose, cutoff: float = 0.01,
                         drop_off: float = 100.0, clearance: torch.Tensor | None = None) -> ContactFrames:
    """The manipulator contact frame ``(1,)`` for a robot start the caller chose (paper, Manipulator Contact
    Model, as training takes it at a push's start): of the observed features within ``cutoff`` of the bumper
    and facing it, the one with the largest weight ``exp(−λ_c d²)`` (the training law draws by that weight;
    a prediction takes its mode), related to the start as ``u = v⁻¹ ∘ R0``. ``clearance``: the cloud's
    :func:`~pushtorch.models.clearance.clearance_points` on the CPU, when the caller places many starts on it.
    Many starts at once: :func:`manipulator_frames_at`.

    Raises:
        InvalidPoseError: ``robot_start`` is not one pose, or its bumper or chassis sits more than
            :data:`GIVEN_START_OVERLAP` inside the observed object (:func:`clearance_points`).
        ModelError: no observed feature lies within ``cutoff`` of the bumper facing it (the start does not
            touch the object where the camera saw it).
    """
    [frame], [error] = manipulator_frames_at(features, [check_start(robot_start)], cutoff, drop_off, clearance)
    if error is not None:
        raise error
    return frame


def manipulator_frames_at(features: SurfaceFeatures, robot_starts: list[se3.Pose], cutoff: float = 0.01,
                          drop_off: float = 100.0, clearance: torch.Tensor | None = None
                          ) -> tuple[list[ContactFrames | None], list[InvalidPoseError | ModelError | None]]:
    """:func:`manipulator_frame_at` for many starts on one cloud in one batched computation (a planner's
    candidates): the starts' overlaps with the cloud in one call, the features in every start's frame against
    the bumper in one closest-point query. Returns each start's frame ``(1,)`` or None, and None or the error
    :func:`manipulator_frame_at` raises for it (a start that overlaps the object, or touches nothing)."""
    count = len(robot_starts)
    dtype = features.p.dtype
    starts = se3.Pose.unchecked(torch.stack([s.p.detach().cpu().to(dtype).reshape(3) for s in robot_starts]),
                                torch.stack([s.q.detach().cpu().to(dtype).reshape(4) for s in robot_starts]))
    clearance = clearance_points(features).cpu() if clearance is None else clearance  # the cloud's, shareable
    inside = backoff_distance(starts, clearance, 0.0)  # (C,)
    to_start = se3.inverse(starts).unsqueeze(-1)  # (C, 1)
    points = se3.apply(to_start, features.p.cpu())  # (C, P, 3)
    normals = se3.apply(se3.Pose.unchecked(torch.zeros_like(to_start.p), to_start.q), features.normal.cpu())
    dist, touching = bumper_contacts(bumper_mesh(se3.identity()), points.reshape(-1, 3), normals.reshape(-1, 3),
                                     cutoff)
    dist, touching = dist.reshape(count, -1), touching.reshape(count, -1)
    weight = torch.where(touching, torch.exp(-drop_off * dist**2), torch.zeros_like(dist))
    best = weight.argmax(-1)  # (C,)
    device = features.p.device
    v = se3.Pose.unchecked(features.p[best.to(device)], features.q[best.to(device)])  # (C,)
    u = se3.relative(v, se3.Pose.unchecked(starts.p.to(device), starts.q.to(device)))
    r, w = features.r[best.to(device)], weight.gather(-1, best.unsqueeze(-1)).squeeze(-1).to(device)
    frames: list[ContactFrames | None] = []
    errors: list[InvalidPoseError | ModelError | None] = []
    for i, (overlap, touches) in enumerate(zip(inside.tolist(), touching.any(-1).tolist(), strict=True)):
        if overlap > GIVEN_START_OVERLAP:
            frames.append(None)
            errors.append(InvalidPoseError(
                f"the given robot start overlaps the observed object: its bumper or chassis must reverse "
                f"{overlap:.3f} m along its approach to clear the cloud (at most "
                f"{GIVEN_START_OVERLAP * 1000:g} mm allowed); place the bumper in front of the side the camera saw"))
        elif not touches:
            frames.append(None)
            errors.append(ModelError(
                f"the given robot start touches none of the {points.shape[1]} observed surface features: none lies "
                f"within {cutoff} m of the bumper and faces it (place the bumper against the side the camera saw)"))
        else:
            frames.append(ContactFrames(v.take(i).unsqueeze(0), r[i : i + 1], u.take(i).unsqueeze(0), w[i : i + 1]))
            errors.append(None)
    return frames, errors


def given_start_frame(start: se3.Pose | None, features: SurfaceFeatures, model: PushModel) -> ContactFrames | None:
    """The manipulator frame of a start the caller gave (None for none), read before any annealing so that
    a start touching nothing or sitting inside the object is refused first."""
    if start is None:
        return None
    return manipulator_frame_at(features, start, model.settings.contact_cutoff, model.settings.contact_drop_off)


def _given_start_condition(start: se3.Pose, frame: ContactFrames, environment: ContactFrames, pose: QueryResult,
                           features: SurfaceFeatures, model: PushModel) -> PushCondition:
    """The push condition of a start the caller gave: used as it is (no back-off; the caller owns it)."""
    start = se3.Pose.unchecked(start.p.to(features.p), start.q.to(features.p))
    return PushCondition(start, frame, environment, pose.pose, None, pose, features, model, 0.0)


def _condition(robot: QueryResult, environment: ContactFrames, pose: QueryResult, features: SurfaceFeatures,
               model: PushModel) -> PushCondition:
    """The push condition, its annealed robot start cleared of the cloud (an invalid one logged)."""
    start, backoff = clear_robot_start(robot.pose, features)
    condition = PushCondition(start, robot.nearest_kernel, environment, pose.pose, robot, pose, features, model,
                              backoff)
    if not condition.valid:
        log.warning("%s; the condition is marked invalid (PushCondition.valid)", overlap_message(backoff, model.name))
    return condition


def generate_push_condition(
    model: PushModel,
    cloud: PointCloud | SurfaceFeatures,
    action_index: int = 0,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: Evaluation | str = Evaluation.FAST,
    robot_start: se3.Pose | None = None,
) -> PushCondition:
    """Robot start pose, manipulator and environment contact frames, and initial pose (paper, Query Density).

    ``method``: :attr:`Evaluation.FAST` (default) anneals the robot's (planar) and the object's query
    densities in one batch with pruned, fused densities (:func:`push_conditions`); :attr:`Evaluation.DENSE`
    is the reference, one after the other. The annealed start is then backed off along the approach to clear
    the observed cloud (:func:`~pushtorch.models.clearance.clear_robot_start`; ``PushCondition.backoff``);
    beyond :data:`MAX_BACKOFF` the condition is marked invalid (``PushCondition.valid``) and a warning is
    logged. A given ``robot_start`` is used as it is, with the manipulator frame the cloud shows at it
    (:func:`manipulator_frame_at`).

    Raises:
        InvalidParameterError: an unknown method or action index.
    """
    method = Evaluation.of(method)
    generator = as_generator(generator)
    features = features_for(cloud, model.settings, model.position)
    if not (isinstance(action_index, int) and 0 <= action_index < len(model.motions)):
        raise InvalidParameterError(
            f"action_index must be an int in [0, {len(model.motions)}) for model {model.name!r}, got {action_index!r}"
        )
    if method is Evaluation.FAST:
        return push_conditions(model, [features], [action_index], generator, record_history, [robot_start])[0]
    settings = model.settings
    given_frame = given_start_frame(robot_start, features, model)
    if robot_start is None:
        robot = optimise_query_density(
            model.contact.robot_query(features, settings, generator, method), settings.anneal_candidates,
            anneal_schedule(settings, True, method), generator, record_history,
        )
    environment = model.motions[action_index].environment_frames(features, settings, generator)
    pose = estimate_pose(model.position, features, settings, generator, record_history, method)
    if robot_start is not None:
        return _given_start_condition(robot_start, given_frame, environment, pose, features, model)
    return _condition(robot, environment, pose, features, model)


def push_conditions(
    model: PushModel,
    features: list[SurfaceFeatures],
    action_indices: list[int],
    generator: torch.Generator | None,
    record_history: bool = False,
    starts: list[se3.Pose | None] | None = None,
) -> list[PushCondition]:
    """Push conditions of several clouds' features (:func:`features_for`) on the fast path: every robot and
    pose query density annealed in one batch (a cloud whose start is given, ``starts[i]``, has no robot
    query; its manipulator frame is :func:`given_start_frame`)."""
    settings = model.settings
    starts = starts if starts is not None else [None] * len(features)
    given_frames = [given_start_frame(start, f, model) for f, start in zip(features, starts, strict=True)]
    robot_densities, pose_densities = [], []
    for f, start in zip(features, starts, strict=True):
        if start is None:
            robot_densities.append(model.contact.robot_query(f, settings, generator, Evaluation.FAST))
        pose_densities.append(model.position.pose_query(f, settings, generator, Evaluation.FAST))
    n_robot = len(robot_densities)
    results = optimise_query_densities(
        robot_densities + pose_densities, settings.anneal_candidates,
        anneal_schedule(settings, False, Evaluation.FAST), [True] * n_robot + [False] * len(features), generator,
        record_history, settings.polish_steps,
    )
    robots = iter(results[:n_robot])
    conditions = []
    for f, a, start, frame, pose_result in zip(features, action_indices, starts, given_frames, results[n_robot:],
                                               strict=True):
        pose = _verified_pose(pose_result, model.position, f, generator)
        environment = model.motions[a].environment_frames(f, settings, generator)
        if start is None:
            conditions.append(_condition(next(robots), environment, pose, f, model))
        else:
            conditions.append(_given_start_condition(start, frame, environment, pose, f, model))
    return conditions


def candidate_conditions(model: PushModel, features: SurfaceFeatures, starts: list[se3.Pose],
                         action_indices: list[int], generator: torch.Generator | None,
                         record_history: bool = False) -> tuple[list[PushCondition | None], list[str | None]]:
    """Push conditions of many given robot starts on one cloud (a planner's candidates, fast path): what depends
    on the cloud alone is computed once, the pose estimate (annealed and verified) and each action's environment
    frames (from a stream of the action's own), and each start gets its manipulator frame. A start that touches
    nothing the camera saw, or sits inside the object, gives None and the reason, not an error for the whole call.

    Raises:
        InvalidPoseError: a start that is not one finite pose (bad input, not a bad candidate).
    """
    settings = model.settings
    starts = [check_start(start) for start in starts]
    frames, errors = manipulator_frames_at(features, starts, settings.contact_cutoff, settings.contact_drop_off)
    reasons = [None if error is None else str(error) for error in errors]
    density = model.position.pose_query(features, settings, generator, Evaluation.FAST)
    [result] = optimise_query_densities([density], settings.anneal_candidates,
                                        anneal_schedule(settings, False, Evaluation.FAST), [False], generator,
                                        record_history, settings.polish_steps)
    pose = _verified_pose(result, model.position, features, generator)
    # each action's environment frames from a stream of its own, so that neither the candidates' order nor which
    # other actions they hold changes them
    base = None if generator is None else int(torch.randint(0, 2**62, (1,), generator=generator))
    environments = {a: model.motions[a].environment_frames(
        features, settings, None if base is None else torch.Generator(generator.device).manual_seed(base + a))
        for a in sorted(set(action_indices))}
    conditions = [None if frame is None else _given_start_condition(start, frame, environments[a], pose, features,
                                                                     model)
                  for start, frame, a in zip(starts, frames, action_indices, strict=True)]
    return conditions, reasons
