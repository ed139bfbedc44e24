"""Prediction: partial cloud + action → robot start pose, contact frames, initial pose, final-pose density.

Paper, Fig. pipeline (prediction) and §Query Density / §Motion Model / §Model Selection:

1. *Push condition generation* (:func:`generate_push_condition`): the manipulator contact model's query
   density gives the robot's start pose (annealed on the ground plane) and the manipulator contact frame;
   environment contacts are placed by the environment contact model; the position model's query density
   estimates the object's initial pose (:func:`estimate_pose`, usable on its own).
2. *Prediction* (:func:`predict`): the action's motion model becomes a product of experts over the
   object's final pose (:class:`pushtorch.models.motion.MotionDensity`), optimised by simulated annealing.

With a :class:`~pushtorch.models.library.ModelLibrary`, the model is chosen first by the lowest ``H_r``.

A caller may also give the robot's start (``predict(..., robot_start=...)``, issue 17's ``placement_spread``
test set): step 1 then skips the robot query and takes as manipulator contact frame the observed feature
that touches the bumper at that start (:func:`manipulator_frame_at`); the rest is unchanged.

Two implementations of the same method: ``method="fast"`` (default) evaluates the densities only where
the kernels' hard cut-offs let them reach, in fused (compiled when possible) passes, anneals the robot's
and the object's query densities in one batch and, in :func:`predict_many`, many conditions at once;
it anneals for ``ModelSettings.fast_anneal_fraction`` of the steps and then moves every candidate to
its local mode by mean shift (``polish_steps``, :func:`pushtorch.anneal.polish_candidates`).
``method="dense"`` is the reference implementation of the paper (every query against every kernel — the
motion kernels whose contact weight is zero included — one density at a time, the full annealing
schedule). Both optimise the same densities; their random streams differ; ``tools/bench_predict.py``
checks that their accuracy agrees.

Collision-free starts (issue 15): the robot's query density knows nothing of the robot's volume, so an
annealed start can put the bumper or the chassis inside the object, and the physics engine then throws the
object. Every push condition's start is therefore checked against the observed cloud before it is used
(:func:`clear_robot_start`): it is backed off straight along the approach (the robot's −x) until the
bumper and chassis boxes clear the observed surface by :data:`START_CLEARANCE`, by the exact distance
:func:`pushtorch.robot.backoff_distance` gives, and recorded in ``PushCondition.backoff``; no prediction
is made from an overlapping start. A start that needed more than :data:`MAX_BACKOFF` is no longer the
model's choice: its condition is marked invalid (``PushCondition.valid`` False, a warning is logged, and
:meth:`PushCondition.check_start` raises :class:`~pushtorch.errors.ModelError` for callers that refuse
it), while the start it carries is still the collision-free one. The check covers the observed surface only (the
single shot sees the side facing the camera): besides the observed points it takes the space just behind
them, :data:`OCCLUDED_DEPTH` along each point's inward normal, as occupied (:func:`clearance_points`),
which catches a bumper buried wholly behind the visible face; deeper hidden parts of the object are not
checked.
"""

from __future__ import annotations

import logging
import math
import sys
import types
from dataclasses import dataclass, field, replace
from functools import cached_property

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule
from pushtorch.distribution import FinalPoseDistribution
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.kde import KernelBandwidth
from pushtorch.models.contact import bumper_contact_patch, bumper_contacts, place_environment_contacts
from pushtorch.models.frames import ContactFrames
from pushtorch.models.library import ModelLibrary, ModelSettings, PushModel, as_generator, check_action
from pushtorch.models.motion import MotionDensity, MotionKernels, anneal_motion_densities
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
from pushtorch.robot import backed_off, backoff_distance, bumper_mesh

__all__ = [
    "GIVEN_START_OVERLAP",
    "MAX_BACKOFF",
    "OCCLUDED_DEPTH",
    "OCCLUDED_STEP",
    "START_CLEARANCE",
    "Prediction",
    "PushCondition",
    "clear_robot_start",
    "clearance_points",
    "estimate_pose",
    "generate_push_condition",
    "manipulator_frame_at",
    "predict",
    "predict_many",
]

log = logging.getLogger("pushtorch.predict")

#: Clearance (m) the robot's bumper and chassis keep from the observed cloud at a push's start: the 2 mm gap
#: of the training placement (:func:`pushtorch.sim.push.place_robot_against`).
START_CLEARANCE = 0.002
#: Largest back-off (m) along the approach that still counts as the start the model chose: 0.10 m is 1 s of
#: the paper's 0.1 m/s push, a quarter of its 0.4 m travel. A start that needs more sat deep in (or on) the
#: object: its condition is marked invalid (``PushCondition.valid``), though still backed off to a clear start.
MAX_BACKOFF = 0.10
#: Depth (m) behind each observed point, along its inward normal, taken as occupied by the object: deeper
#: than the 1.25 cm slot between the chassis and the bumper, so a bumper buried wholly behind the visible
#: face is caught, and shallower than half the thinnest catalogue object (0.1 m), so a robot flush against a
#: hidden face is not pushed away by it.
OCCLUDED_DEPTH = 0.02
#: Trial rounds the motion model's contact-frame kernel may take (:func:`contact_bandwidth`): 2^-30 scales
#: any distance a float32 holds into reach.
CONTACT_TRIAL_ROUNDS = 30
#: Spacing (m) of the occluded samples: below the bumper's 0.02 m thickness, so it cannot slip between them.
OCCLUDED_STEP = 0.01
#: How far (m) a start the caller gives may sit inside the observed object (the cloud and its occluded layer):
#: a sensor's noise of a few mm on a bumper placed flush. Spread test starts placed 2 mm short on the catalogue
#: and 9 random shapes measured 0 m; a start more than this deep would push from inside the object.
GIVEN_START_OVERLAP = 0.005


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


@dataclass
class Prediction:
    """A predicted push outcome and the density it came from."""

    model_name: str
    action: torch.Tensor  # (2,)
    condition: PushCondition
    final_pose: se3.Pose  # ()
    log_prob: torch.Tensor  # () the product of experts at final_pose, up to its constant (as annealed)
    #: the predicted density over final poses as a torch distribution (normalised; ``mode`` = final_pose)
    density: FinalPoseDistribution
    candidates: se3.Pose  # (C,) annealed candidates
    candidate_log_prob: torch.Tensor  # (C,)
    anneal: AnnealResult | None = None  # the motion annealing (with per-step history if recorded)
    #: the product of experts as the method builds it (kernels, experts, mean shift; unnormalised)
    motion_density: MotionDensity | None = field(default=None, repr=False)


def query_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    c = settings.cutoff_std
    return KernelBandwidth(settings.query_p_std, settings.query_rot_std, cutoff_std=(c, c, c),
                           alpha_t=settings.alpha_t)


def contact_bandwidth(settings: ModelSettings, with_robot_position: bool = True) -> KernelBandwidth:
    """The contact-frame kernel: relation ``u``, embedded curvatures and (for the motion model) the
    frame's position in the robot's start frame and the push's contact patch on the bumper.

    The motion model's kernel may widen by up to :data:`CONTACT_TRIAL_ROUNDS` trial rounds (the lineage's 10
    elsewhere): its patch stds are chosen from the training pushes (5 mm, 0.01 rad at the bounds), and an
    incongruent model's push can meet the object with a patch metres or a radian from every training one
    (measured: 9,600 scaled distances in the quickstart's selection part). Widening then lets the nearest
    training pushes weigh in, as trial rounds are meant to, instead of refusing the prediction.
    """
    c = settings.cutoff_std
    stds = (settings.descriptor_std,) * 2
    rounds = 10
    if with_robot_position:
        stds += (settings.contact_robot_std,) * 3 + (settings.contact_patch_std,) * 2
        stds += (settings.contact_patch_yaw_std,)
        rounds = CONTACT_TRIAL_ROUNDS
    return KernelBandwidth(
        settings.contact_p_std, settings.contact_rot_std, stds,
        cutoff_std=(c, c, settings.descriptor_cutoff_std), alpha_t=settings.alpha_t, max_trial_rounds=rounds,
    )


def motion_bandwidth(settings: ModelSettings) -> KernelBandwidth:
    c = settings.cutoff_std
    return KernelBandwidth(settings.motion_p_std, settings.motion_rot_std, cutoff_std=(c, c, c),
                           alpha_t=settings.alpha_t)


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


def _check_actions(actions, count: int) -> torch.Tensor:
    """``(count, 2)`` float64 actions from one ``(2,)`` (or ``(1, 2)``) action for every condition or
    ``(count, 2)``.

    Raises:
        InvalidParameterError: not numeric, misshaped, NaN/infinite, or not one per condition.
    """
    if type(actions).__module__ == "numpy":
        try:
            actions = torch.as_tensor(actions)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InvalidParameterError(f"actions must be numbers (ẋ m/s, θ̇ rad/s), got {actions!r}") from exc
    if isinstance(actions, torch.Tensor) and actions.dim() == 2 and actions.shape[-1] == 2:
        rows = actions
    elif not isinstance(actions, torch.Tensor) and isinstance(actions, list | tuple) and actions \
            and all(isinstance(a, list | tuple | torch.Tensor) for a in actions):
        rows = torch.stack([check_action(a) for a in actions])
    else:
        return check_action(actions).expand(count, 2)
    if len(rows) == 1:
        return check_action(rows[0]).expand(count, 2)
    if len(rows) != count:
        raise InvalidParameterError(f"got {len(rows)} actions for {count} clouds")
    return torch.stack([check_action(a) for a in rows]) if count else torch.zeros(0, 2, dtype=torch.float64)


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
        position.frames, features, settings.query_kernels, std, query_bandwidth(settings),
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, generator=generator,
        method=method,
    )


def _robot_density(model: PushModel, features: SurfaceFeatures, generator: torch.Generator | None,
                   method: str) -> QueryDensity:
    settings = model.settings
    std = torch.full((2,), settings.descriptor_std)
    return build_query_density(
        model.contact.frames, features, settings.query_kernels, std, query_bandwidth(settings),
        r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, project_planar=True,
        generator=generator, method=method,
    )


def _subsample(kernels: MotionKernels, count: int, generator: torch.Generator | None) -> MotionKernels:
    if len(kernels) <= count:
        return kernels
    return kernels.take(torch.randperm(len(kernels), generator=generator)[:count])


def clearance_points(features: SurfaceFeatures, depth: float = OCCLUDED_DEPTH,
                     step: float = OCCLUDED_STEP) -> torch.Tensor:
    """The points a robot start must clear: the observed surface and the occluded space just behind it.

    Each feature's point ``p`` gives ``p − t·n`` for ``t = 0, step, …, depth`` (``n`` its outward normal),
    ``(K·N, 3)`` with ``K = ⌊depth/step⌋ + 1`` layers, surface first. The single-shot cloud shows only the
    side facing the camera; the layers stand for the object right behind that surface (for a convex object
    at least as thick as ``depth`` they lie inside it), so a bumper wholly behind the visible face still
    overlaps them. The object's hidden side further back is not represented.

    Raises:
        InvalidParameterError: a negative depth or a step that is not positive.
    """
    if not (math.isfinite(depth) and depth >= 0 and math.isfinite(step) and step > 0):
        raise InvalidParameterError(f"need depth >= 0 and step > 0 (m), got depth={depth!r}, step={step!r}")
    layers = torch.arange(int(round(depth / step, 9)) + 1, dtype=features.p.dtype, device=features.p.device)
    offsets = layers * step
    return (features.p.unsqueeze(0) - offsets[:, None, None] * features.normal.unsqueeze(0)).reshape(-1, 3)


def _overlap_message(backoff: float, model_name: str | None) -> str:
    who = f" of model {model_name!r}" if model_name else ""
    return (
        f"the predicted robot start{who} overlaps the observed object: its bumper or chassis stays within "
        f"{START_CLEARANCE * 1000:g} mm of the cloud (or of the {OCCLUDED_DEPTH * 100:g} cm behind its visible "
        f"surface) until backed off {backoff:.3f} m along the approach, beyond the {MAX_BACKOFF:.2f} m allowed"
    )


def clear_robot_start(robot_start: se3.Pose, features: SurfaceFeatures,
                      clearance: float = START_CLEARANCE) -> tuple[se3.Pose, float]:
    """A robot start pose ``()`` that clears the observed cloud, and how far it was backed off (m).

    The start is moved straight back along its own −x (the approach reversed) by
    :func:`pushtorch.robot.backoff_distance` against :func:`clearance_points`: the smallest distance after
    which the bumper and chassis boxes are at least ``clearance`` from every observed point and from the
    occluded layer behind it. A start that already clears is returned unchanged with back-off 0. The
    back-off is not bounded here; :class:`PushCondition` judges it against :data:`MAX_BACKOFF`.
    """
    distance = backoff_distance(robot_start, clearance_points(features), clearance)
    value = float(distance)
    if value <= 0.0:
        return robot_start, 0.0
    return backed_off(robot_start, distance), value


def _check_start(robot_start: se3.Pose) -> se3.Pose:
    """``robot_start`` if it is one finite pose with a unit quaternion, else InvalidPoseError."""
    robot_start = se3.check_pose(robot_start, "robot_start")
    if robot_start.batch_shape != torch.Size([]):
        raise InvalidPoseError(f"robot_start must be one pose, got batch shape {tuple(robot_start.batch_shape)}")
    return robot_start


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
        features, env_kernels.r, env_kernels.u, contact_bandwidth(settings, with_robot_position=False),
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


def predict(
    model: PushModel | ModelLibrary,
    cloud: PointCloud | SurfaceFeatures,
    action,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: str = "fast",
    robot_start: se3.Pose | None = None,
) -> Prediction:
    """Predict where the object in ``cloud`` ends up after ``action`` (paper, Motion Model, Eq. poe).

    Args:
        model: a trained model, or a library to select from by ``H_r``.
        cloud: the object's single-shot cloud (or its surface features), world frame.
        action: ``(2,)`` (ẋ m/s, θ̇ rad/s), one of the model's actions.
        generator: seeded generator (or an int seed): the same seed (and method) gives the same prediction.
        record_history: keep every annealing step (for Rerun).
        method: ``"fast"`` (default): densities evaluated only where the hard cut-offs let kernels
            reach, fused (compiled when a compiler is available, :func:`pushtorch.kde.fast_path_compiled`),
            query densities annealed together, cheaper exact proposal draws, a shorter annealing
            polished by mean shift (module docstring); ``"dense"``: the reference implementation, the
            paper's full schedule. Both optimise the same densities; their random streams differ, so
            single predictions differ as two seeds do.
        robot_start: the robot's start pose (one pose, world), when the caller places the robot instead of
            the manipulator contact model; the bumper must touch the observed cloud there. Default None:
            the model chooses (the paper's push condition generation).

    Raises:
        InvalidParameterError: an unknown method, or an action that is not finite, misshaped or unknown
            to the model.
        InvalidPointCloudError: an empty, misshaped or non-finite cloud (a float64 cloud is cast).
        InvalidPoseError: a ``robot_start`` that is not one finite pose with a unit quaternion, or whose bumper
            or chassis sits more than :data:`GIVEN_START_OVERLAP` inside the observed object.
        ModelError: a ``robot_start`` at which the bumper touches no observed surface feature.

    The robot start (``prediction.condition.robot_start``) clears the observed cloud by
    :data:`START_CLEARANCE` (a given ``robot_start`` is used as it is): an overlapping annealed start is
    backed off along the approach
    (``condition.backoff``), and ``condition.valid`` is False if that took more than :data:`MAX_BACKOFF`
    (``condition.check_start()`` raises ModelError then).
    """
    return predict_many(model, [cloud], action, generator=generator, record_history=record_history,
                        method=method, robot_starts=None if robot_start is None else [robot_start])[0]


def _motion_density(model: PushModel, condition: PushCondition, a: int, generator: torch.Generator | None,
                    method: str) -> MotionDensity:
    """The action's product of experts; the dense reference keeps every motion kernel (those the contact
    weight cuts off weigh zero), the fast path drops them before anything is evaluated."""
    settings = model.settings
    motion = model.motions[a]
    return MotionDensity(
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
        condition.contact_patch,
        contact_bandwidth(settings),
        motion_bandwidth(settings),
        drop_cut_kernels=method == "fast",
        pool_sharpness=settings.pool_sharpness,
    )


def predict_many(
    model: PushModel | ModelLibrary,
    clouds: list[PointCloud | SurfaceFeatures],
    actions,
    seed: int = 0,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: str = "fast",
    batch_size: int = 1,
    robot_starts: list[se3.Pose | None] | None = None,
) -> list[Prediction]:
    """Predict several conditions (one cloud and action each).

    With ``generator`` None, batch ``k`` (conditions ``k·batch_size …``) draws from its own generator
    seeded ``seed + k·batch_size``, so ``batch_size=1`` gives each condition ``i`` exactly
    ``predict(..., generator=torch.Generator().manual_seed(seed + i))``. With ``method="fast"`` and
    ``batch_size > 1`` the conditions of a batch are annealed together (one density call per step for
    all of them: the robot and pose query densities, then the products of experts), which amortises
    the per-step overhead; the memory of a batch grows linearly with its size (at the paper's sizes,
    measured: peak +56 MB for 8 conditions, +180 MB for 32), so bound it with ``batch_size``.

    Args:
        model, clouds: as :func:`predict`, one cloud per condition.
        actions: ``(2,)`` for all or ``(len(clouds), 2)``.
        seed: base seed when no generator is given; generator: one generator for every batch.
        record_history, method: as :func:`predict`.
        batch_size: conditions annealed together (fast method only; the dense method runs one by one).
        robot_starts: None (the model places the robot) or one entry per cloud: a start pose as
            :func:`predict`'s ``robot_start``, or None for the model's own.

    Raises:
        InvalidParameterError: an unknown method, a batch size < 1, actions or starts that do not match.

    Every condition's robot start is cleared of its cloud as in :func:`predict`. An empty list of clouds
    gives an empty list of predictions.
    """
    _check_method(method)
    if isinstance(batch_size, bool) or not isinstance(batch_size, int | float) or int(batch_size) != batch_size \
            or batch_size < 1:
        raise InvalidParameterError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InvalidParameterError(f"seed must be an integer, got {seed!r}")
    generator = None if generator is None else as_generator(generator)  # None: one seeded stream per batch
    if isinstance(clouds, PointCloud | SurfaceFeatures | torch.Tensor):
        raise InvalidParameterError("clouds must be a list of clouds (use predict for one cloud)")
    clouds = list(clouds)
    if not clouds:  # an empty batch predicts nothing, as map() over nothing
        return []
    actions = _check_actions(actions, len(clouds))
    if robot_starts is None:
        robot_starts = [None] * len(clouds)
    elif isinstance(robot_starts, se3.Pose) or len(robot_starts) != len(clouds):
        raise InvalidParameterError(
            f"robot_starts must be a list with one pose (or None) per cloud, {len(clouds)} in all")
    else:  # refused before any annealing is spent on the batch
        robot_starts = [None if start is None else _check_start(start) for start in robot_starts]
    step = int(batch_size) if method == "fast" else 1
    out: list[Prediction] = []
    for start in range(0, len(clouds), step):
        g = generator if generator is not None else torch.Generator().manual_seed(seed + start)
        out.extend(_predict_batch(model, clouds[start : start + step], actions[start : start + step], g,
                                  record_history, method, list(robot_starts[start : start + step])))
    return out


def _predict_batch(
    model: PushModel | ModelLibrary,
    clouds: list[PointCloud | SurfaceFeatures],
    actions: torch.Tensor,
    generator: torch.Generator | None,
    record_history: bool,
    method: str,
    starts: list[se3.Pose | None],
) -> list[Prediction]:
    """One batch of :func:`predict_many`: a library selects per cloud, then each model's share runs
    together."""
    first = model.models[0] if isinstance(model, ModelLibrary) else model
    features = [_as_features(c, first.settings, first) for c in clouds]
    chosen = [model.select(f)[0] if isinstance(model, ModelLibrary) else model for f in features]
    out: list[Prediction | None] = [None] * len(clouds)
    distinct = [m for i, m in enumerate(chosen) if all(m is not c for c in chosen[:i])]  # first-use order
    for m in distinct:
        rows = [i for i, c in enumerate(chosen) if c is m]
        a_idx = [m.action_index(actions[i]) for i in rows]
        settings = m.settings
        schedule = _schedule(settings, False, method)
        if method == "fast":
            shares = [features[i] for i in rows]
            conditions = _push_conditions_fast(m, shares, a_idx, generator, record_history,
                                               [starts[i] for i in rows])
            densities = [_motion_density(m, c, a, generator, method)
                         for c, a in zip(conditions, a_idx, strict=True)]
            results = anneal_motion_densities(densities, settings.anneal_candidates, schedule, generator,
                                              record_history, settings.polish_steps)
        else:
            conditions, densities, results = [], [], []
            for i, a in zip(rows, a_idx, strict=True):
                condition = generate_push_condition(m, features[i], a, generator, record_history, method,
                                                    starts[i])
                density = _motion_density(m, condition, a, generator, method)
                conditions.append(condition)
                densities.append(density)
                results.append(
                    density.predict(settings.anneal_candidates, schedule, generator, record_history)
                )
        for i, a, condition, density, result in zip(rows, a_idx, conditions, densities, results, strict=True):
            distribution = FinalPoseDistribution.from_motion_densities(
                density, result.final_pose, [result.anneal.candidates], method)
            out[i] = Prediction(m.name, m.motions[a].action, condition, result.final_pose, result.log_prob,
                                distribution, result.anneal.candidates, result.anneal.log_prob, result.anneal,
                                density)
    return out  # type: ignore[return-value]


class _CallableModule(types.ModuleType):
    """This module, callable as :func:`predict`.

    ``pushtorch.predict`` names both this module and, in the package's public face, the function: once the
    module is imported, Python binds the package attribute to the module, whatever the package bound first.
    Calling the module calls the function, so ``pushtorch.predict(model, cloud, action)`` works in any
    import order, and ``from pushtorch.predict import predict_many`` keeps working.
    """

    def __call__(self, *args, **kwargs) -> Prediction:
        return predict(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
