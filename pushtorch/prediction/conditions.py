"""Push conditions (paper, Fig. pipeline, prediction; §Query Density, §Model Selection): the robot's start
and manipulator contact frame, the environment contacts and the object's estimated initial pose, for every
method.

1. *Push condition generation* (:func:`generate_push_condition`): the manipulator contact model's query
   density gives the robot's start pose (annealed on the ground plane) and the manipulator contact frame;
   environment contacts are placed by the environment contact model; the position model's query density
   estimates the object's initial pose (:func:`estimate_pose`, usable on its own).
2. *Prediction* (:func:`predict`): the action's motion model becomes a product of experts over the
   object's final pose (:class:`pushtorch.models.motion.MotionDensity`), optimised by simulated annealing.

A caller may also give the robot's start (``predict(..., robot_start=...)``): step 1 then skips the robot
query and takes as manipulator contact frame the observed feature that touches the bumper at that start
(:func:`manipulator_frame_at`); the rest is unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import cached_property

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealSchedule
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.kde import KernelBandwidth
from pushtorch.models.contact import bumper_contact_patch, bumper_contacts, place_environment_contacts
from pushtorch.models.frames import ContactFrames
from pushtorch.models.library import ModelSettings, PushModel, as_generator
from pushtorch.models.motion import MotionKernels
from pushtorch.models.position import PositionModel, verify_pose_candidates
from pushtorch.models.query import (
    QueryDensity,
    QueryResult,
    build_query_density,
    feature_distance_heuristic,
    heuristic_descriptors,
    optimise_query_densities,
    optimise_query_density,
)
from pushtorch.perception import PointCloud
from pushtorch.prediction.clearance import (
    GIVEN_START_OVERLAP,
    MAX_BACKOFF,
    _check_start,
    _overlap_message,
    clear_robot_start,
    clearance_points,
)
from pushtorch.robot import backoff_distance, bumper_mesh

__all__ = [
    "PushCondition",
    "contact_bandwidth",
    "estimate_pose",
    "generate_push_condition",
    "manipulator_frame_at",
    "motion_bandwidth",
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
            raise ModelError(_overlap_message(self.backoff, self.model.name))
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
        return feature_distance_heuristic(heuristic_descriptors(self.features), self.model.contact.frames.r, "fast")


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


def _schedule(settings: ModelSettings, planar: bool, method: str) -> AnnealSchedule:
    """The paper's schedule for the dense reference; the fast path's shorter one (then polished)."""
    steps = settings.fast_anneal_steps if method == "fast" else settings.anneal_steps
    return AnnealSchedule(steps=steps, planar=planar)


def _polish_steps(settings: ModelSettings, method: str) -> int:
    return settings.polish_steps if method == "fast" else 0


def _as_features(cloud: PointCloud | SurfaceFeatures, settings: ModelSettings,
                 model: PushModel | PositionModel) -> SurfaceFeatures:
    """The cloud's surface features in the ``model``'s dtype on its device (a float64 cloud is cast
    before its features are computed, so it predicts exactly as the same cloud in float32). Features are
    computed on the CPU (open3d's neighbourhoods and normals) and then moved."""
    frames = (model.position if isinstance(model, PushModel) else model).frames.r
    dtype, device = frames.dtype, frames.device
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
    method: str = "fast",
) -> QueryResult:
    """Estimate an object's pose from a (partial) cloud with a position model (paper, Object Position Model).

    Returns the best pose (full SE(3)) with its log density and the annealing record: the annealing's
    candidates (hypotheses of the query density) verified by their surface fit to the cloud
    (:func:`pushtorch.models.position.verify_pose_candidates`).
    ``method``: ``"fast"`` (default: pruned, fused densities) or ``"dense"`` (the reference); the
    same law, another random stream.
    """
    _check_method(method)
    settings = settings or ModelSettings()
    generator = as_generator(generator)
    features = _as_features(cloud, settings, position)
    density = _pose_density(position, features, settings, generator, method)
    result = optimise_query_density(
        density, settings.anneal_candidates, _schedule(settings, False, method), generator, record_history,
        method, _polish_steps(settings, method),
    )
    return _verified_pose(result, position, features, generator)


def _verified_pose(result: QueryResult, position: PositionModel, features: SurfaceFeatures,
                   generator: torch.Generator | None) -> QueryResult:
    """The annealed candidate whose surface best fits the cloud (docs/method.md, pose verification)."""
    candidates = result.anneal.candidates
    best = verify_pose_candidates(position, features.p, candidates, result.anneal.log_prob, generator)
    return replace(result, pose=candidates.take(best), log_prob=result.anneal.log_prob[best])


def _check_method(method: str) -> None:
    if method not in ("dense", "fast"):
        raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}")


def _pose_density(position: PositionModel, features: SurfaceFeatures, settings: ModelSettings,
                  generator: torch.Generator | None, method: str) -> QueryDensity:
    std = torch.full((2,), settings.descriptor_std)
    return build_query_density(
        position.frames, features, settings.query_kernels, std, settings.query_bandwidth,
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, generator=generator,
        method=method,
    )


def _robot_density(model: PushModel, features: SurfaceFeatures, generator: torch.Generator | None,
                   method: str) -> QueryDensity:
    settings = model.settings
    std = torch.full((2,), settings.descriptor_std)
    return build_query_density(
        model.contact.frames, features, settings.query_kernels, std, settings.query_bandwidth,
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, project_planar=True,
        generator=generator, method=method,
    )


def _subsample(kernels: MotionKernels, count: int, generator: torch.Generator | None) -> MotionKernels:
    if len(kernels) <= count:
        return kernels
    return kernels.take(torch.randperm(len(kernels), generator=generator)[:count])


def manipulator_frame_at(features: SurfaceFeatures, robot_start: se3.Pose, cutoff: float = 0.01,
                         drop_off: float = 100.0) -> ContactFrames:
    """The manipulator contact frame ``(1,)`` for a robot start the caller chose (paper, Manipulator Contact
    Model, as training takes it at a push's start): of the observed features within ``cutoff`` of the bumper
    and facing it, the one with the largest weight ``exp(−λ_c d²)`` (the training law draws by that weight;
    a prediction takes its mode), related to the start as ``u = v⁻¹ ∘ R0``.

    Raises:
        InvalidPoseError: ``robot_start`` is not one pose, or its bumper or chassis sits more than
            :data:`GIVEN_START_OVERLAP` inside the observed object (:func:`clearance_points`).
        ModelError: no observed feature lies within ``cutoff`` of the bumper facing it (the start does not
            touch the object where the camera saw it).
    """
    robot_start = _check_start(robot_start)
    robot_start = se3.Pose.unchecked(robot_start.p.detach().cpu().to(features.p.dtype),
                           robot_start.q.detach().cpu().to(features.p.dtype))
    inside = float(backoff_distance(robot_start, clearance_points(features).cpu(), 0.0))
    if inside > GIVEN_START_OVERLAP:
        raise InvalidPoseError(
            f"the given robot start overlaps the observed object: its bumper or chassis must reverse {inside:.3f} m "
            f"along its approach to clear the cloud (at most {GIVEN_START_OVERLAP * 1000:g} mm allowed); place the "
            "bumper in front of the side the camera saw"
        )
    points = se3.apply(se3.inverse(robot_start), features.p.cpu())
    normals = se3.apply(se3.Pose.unchecked(torch.zeros(3, dtype=points.dtype),
                                           se3.inverse(robot_start).q), features.normal.cpu())
    dist, touching = bumper_contacts(bumper_mesh(se3.identity()), points, normals, cutoff)
    if not bool(touching.any()):
        raise ModelError(
            f"the given robot start touches none of the {len(points)} observed surface features: none lies within "
            f"{cutoff} m of the bumper and faces it (place the bumper against the side the camera saw)"
        )
    weight = torch.where(touching, torch.exp(-drop_off * dist**2), torch.zeros_like(dist))
    best = int(weight.argmax())
    device = features.p.device
    v = se3.Pose.unchecked(features.p[best : best + 1], features.q[best : best + 1])
    u = se3.relative(v, se3.Pose.unchecked(robot_start.p.to(device).unsqueeze(0),
                                           robot_start.q.to(device).unsqueeze(0)))
    return ContactFrames(v, features.r[best : best + 1], u, weight[best : best + 1].to(device))


def _given_start_frame(start: se3.Pose | None, features: SurfaceFeatures, model: PushModel) -> ContactFrames | None:
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
        log.warning("%s; the condition is marked invalid (PushCondition.valid)", _overlap_message(backoff, model.name))
    return condition


def generate_push_condition(
    model: PushModel,
    cloud: PointCloud | SurfaceFeatures,
    action_index: int = 0,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: str = "fast",
    robot_start: se3.Pose | None = None,
) -> PushCondition:
    """Robot start pose, manipulator and environment contact frames, and initial pose (paper, Query Density).

    ``method``: ``"fast"`` (default) anneals the robot's (planar) and the object's query densities in
    one batch with pruned, fused densities; ``"dense"`` is the reference, one after the other. The
    annealed start is then backed off along the approach to clear the observed cloud
    (:func:`clear_robot_start`; ``PushCondition.backoff``); beyond :data:`MAX_BACKOFF` the condition is
    marked invalid (``PushCondition.valid``) and a warning is logged. A given ``robot_start`` is used as it
    is, with the manipulator frame the cloud shows at it (:func:`manipulator_frame_at`).
    """
    _check_method(method)
    generator = as_generator(generator)
    features = _as_features(cloud, model.settings, model)
    if not (isinstance(action_index, int) and 0 <= action_index < len(model.motions)):
        raise InvalidParameterError(
            f"action_index must be an int in [0, {len(model.motions)}) for model {model.name!r}, got {action_index!r}"
        )
    if method == "fast":
        return _push_conditions_fast(model, [features], [action_index], generator, record_history, [robot_start])[0]
    settings = model.settings
    given_frame = _given_start_frame(robot_start, features, model)
    if robot_start is None:
        robot_density = _robot_density(model, features, generator, method)
        robot = optimise_query_density(
            robot_density, settings.anneal_candidates, _schedule(settings, True, method), generator, record_history
        )
    environment = _environment_frames(model, features, action_index, generator)
    pose = estimate_pose(model.position, features, settings, generator, record_history, method)
    if robot_start is not None:
        return _given_start_condition(robot_start, given_frame, environment, pose, features, model)
    return _condition(robot, environment, pose, features, model)


def _environment_frames(model: PushModel, features: SurfaceFeatures, action_index: int,
                        generator: torch.Generator | None) -> ContactFrames:
    settings = model.settings
    motion = model.motions[action_index]
    env_kernels = _subsample(motion.environment, settings.environment_kernels, generator)
    return place_environment_contacts(
        features, env_kernels.r, env_kernels.u, settings.environment_contact_bandwidth,
        settings.environment_contacts, settings.environment_samples, generator,
    )


def _push_conditions_fast(
    model: PushModel,
    features: list[SurfaceFeatures],
    action_indices: list[int],
    generator: torch.Generator | None,
    record_history: bool,
    starts: list[se3.Pose | None] | None = None,
) -> list[PushCondition]:
    """Push conditions of several clouds: every robot and pose query density annealed in one batch (a cloud
    whose start is given, ``starts[i]``, has no robot query)."""
    settings = model.settings
    starts = starts if starts is not None else [None] * len(features)
    given_frames = [_given_start_frame(start, f, model) for f, start in zip(features, starts, strict=True)]
    robot_densities, pose_densities = [], []
    for f, start in zip(features, starts, strict=True):
        if start is None:
            robot_densities.append(_robot_density(model, f, generator, "fast"))
        pose_densities.append(_pose_density(model.position, f, settings, generator, "fast"))
    n_robot = len(robot_densities)
    results = optimise_query_densities(
        robot_densities + pose_densities, settings.anneal_candidates, _schedule(settings, False, "fast"),
        [True] * n_robot + [False] * len(features), generator, record_history, settings.polish_steps,
    )
    robots = iter(results[:n_robot])
    conditions = []
    for f, a, start, frame, pose_result in zip(features, action_indices, starts, given_frames, results[n_robot:],
                                               strict=True):
        pose = _verified_pose(pose_result, model.position, f, generator)
        environment = _environment_frames(model, f, a, generator)
        if start is None:
            conditions.append(_condition(next(robots), environment, pose, f, model))
        else:
            conditions.append(_given_start_condition(start, frame, environment, pose, f, model))
    return conditions
