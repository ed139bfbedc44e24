"""Rerun logging of a trained push model and of a prediction: frames, query kernels, contacts, annealing.

Paper, §TPMM (Manipulator Contact Model, Object Position Model, Query Density, Environment Contact Model,
Motion Model) and Fig. pipeline (prediction): what each stage of a prediction chose, so a user can see
*why* a push was predicted as it was. Everything is in the world frame (z up, metres). Point sets are
subsampled to ``max_points`` (``max_frames`` for axis triads) with a fixed seed, so logging stays cheap
and two runs log the same points. Colours: viridis, bright = high weight / log-likelihood.

Entity paths. Training (:func:`log_contact_model`), root ``world/model/training/<name>``
(``<name>`` defaults to the model's name; ``/`` separates levels of the hierarchy, and within a level
characters outside ``[A-Za-z0-9_.-]`` become ``_``):

=================================  ==============================================================
``<root>/object``                  training pose ``B^O`` of the object (transform, static)
``<root>/object/mesh``             the training object's mesh
``<root>/contact/points``          manipulator contact frames ``c^m``: positions ``v``, coloured by ``w^c``
                                   (over its range: with λ_c = 100 it spans only 0.99–1)
``<root>/contact/frames``          the same frames as axis triads (x red, y green, z blue)
``<root>/contact/implied_robot``   robot base positions ``v ∘ u^m`` implied by each frame (colour: ``w^c``)
``<root>/robot``                   training robot base pose (transform; mean of ``v ∘ u^m`` on the ground)
``<root>/robot/chassis``           the robot's chassis box (base frame)
``<root>/bumper``                  the bumper at the training pose (world-frame mesh)
``<root>/position/points``         position frames ``c^p``: positions, coloured by saliency weight
``<root>/position/frames``         position frames as axis triads
=================================  ==============================================================

Prediction (:func:`log_prediction`), root ``world/model/prediction/<label>`` (the experiments' labels
are ``<part>/<object>/<model>/c<i>a<j>``, the predict app's ``action_<j>``). Entities marked *(t)* are on
the ``anneal_step`` sequence timeline (step 0 = initial candidates), *(s)* on ``sim_time`` (seconds since
the push started); everything else is static.

========================================  ==========================================================
``<root>/cloud``                          the partial cloud, if given
``<root>/robot_query/features``           robot query kernels' cloud features ``v``, coloured by kernel weight
``<root>/robot_query/kernels``            their means ``v ∘ u`` (robot base positions, on the ground)
``<root>/robot_query/candidates``         *(t)* annealing candidates per step, coloured by log-likelihood
``<root>/robot_query/final_candidates``   the annealed candidates, coloured by log-likelihood
``<root>/robot_query/best_log_prob``      *(t)* scalar series: the best log-likelihood of the step's
                                          candidates ("step best") and the best so far ("best so far")
``<root>/pose_query/...``                 the same five for the position model's query density (object poses)
``<root>/robot``                          chosen robot start pose (transform); ``/chassis``, ``/axes``
``<root>/bumper``                         the bumper at the chosen start pose (world-frame mesh)
``<root>/manipulator_contact/frame``      the manipulator contact frame ``c^m`` (axis triad)
``<root>/manipulator_contact/relation``   arrow from ``v`` to ``v ∘ u^m`` (the robot base)
``<root>/environment_contacts/points``    environment contact frames ``c^e`` (positions)
``<root>/environment_contacts/frames``    their axis triads
``<root>/environment_contacts/relation``  arrows from ``v`` to ``v ∘ u^e`` (the floor point below)
``<root>/initial_estimate``               estimated initial pose ``B0'`` (transform); ``/mesh``, ``/axes``
``<root>/motion/experts``                 the experts' kernel means (final object positions), one colour per
                                          expert (expert 0 = manipulator)
``<root>/motion/candidates``              *(t)* motion annealing per step — only if the prediction carries
                                          its annealing record as ``prediction.anneal`` (see below)
``<root>/motion/best_log_prob``           *(t)* the motion annealing's series, as ``robot_query/best_log_prob``
``<root>/motion/final_candidates``        the annealed final-pose candidates, coloured by log-likelihood
``<root>/final_predicted``                predicted final pose (transform); ``/mesh``, ``/axes``
``<root>/initial_true``                   true initial pose, if given; ``/mesh``, ``/axes``
``<root>/final_true``                     true final pose, if given; ``/mesh``, ``/axes``
``<root>/initial_error``                  line from the estimated to the true initial centre, if given
``<root>/final_error``                    line from the predicted to the true final centre, if given
``<root>/truth_push/object``              *(s)* the ground-truth push, if given: the object's transform per
                                          recorded time; its mesh at ``/mesh``
``<root>/truth_push/robot``               *(s)* the robot base's transform; ``/chassis``, ``/bumper``, ``/bumper/mesh``
``<root>/truth_push/object_path``         the object centre's path during the push (``/robot_path``: the robot's)
``<root>/density/samples``                draws from ``prediction.density`` (:data:`DENSITY_SAMPLES`, at most
                                          ``max_points``): final positions, coloured by log-density
``<root>/density/region_90``              the draws inside the 90 % highest-density region: those whose
                                          log-density is among the highest 90 % of the draws' (a Monte
                                          Carlo estimate of the region's extent; a point set, no hull)
``<root>/density/ghosts``                 :data:`DENSITY_GHOSTS` of the draws as axis triads (their
                                          orientations)
``<root>/density/mode``                   the density's mode (``prediction.final_pose``): a point; its axis
                                          triad at ``/axes``
``<root>/density/truth``                  the truth in the density's frame, if ``truth_final`` is given: the
                                          true motion applied to the estimated start, ``B1 ∘ B0⁻¹ ∘ B̂0``
                                          (``truth_final`` as it is without ``truth_initial``); ``/axes``
``<root>/collision_parts``                the object's convex collision parts, when the simulator used more
                                          than one (:attr:`~pushtorch.objects.ObjectModel.collision_parts`):
                                          a transform (the true initial pose, else the estimate) and a mesh
                                          per part at ``/part_<k>``
========================================  ==========================================================

The density's draws come from a generator of their own, seeded with :data:`DENSITY_SEED` inside
:func:`log_density`: a recording never changes a prediction or a random stream of the caller, and two
recordings of one prediction show the same draws. Draws are importance-resampled
(:meth:`~pushtorch.distribution.FinalPoseDistribution.sample`), so a draw may repeat.

The query kernels need :attr:`pushtorch.models.query.QueryResult.density`; a result without it logs
everything else. :class:`pushtorch.prediction.Prediction` keeps the motion annealing's candidates but
not its per-step history; if it gains an ``anneal`` attribute (an
:class:`~pushtorch.anneal.AnnealResult`), ``motion/candidates`` is logged from it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import rerun as rr
import torch
import trimesh

from pushtorch import se3
from pushtorch.anneal import AnnealResult
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.models.frames import ContactFrames
from pushtorch.models.query import QueryResult, planar
from pushtorch.viz.core import (
    WORLD,
    curvature_colors,
    entity_name,
    log_arrows,
    log_frames,
    log_line_strip,
    log_mesh,
    log_points,
    log_pose,
)

__all__ = [
    "ANNEAL_SERIES",
    "ANNEAL_TIMELINE",
    "DENSITY_GHOSTS",
    "DENSITY_REGION",
    "DENSITY_SAMPLES",
    "DENSITY_SEED",
    "MODEL",
    "PREDICTION",
    "TRAINING",
    "density_truth",
    "log_anneal_history",
    "log_anneal_series",
    "log_collision_parts",
    "log_contact_model",
    "log_density",
    "log_prediction",
    "log_query",
]

log = logging.getLogger(__name__)

#: Root of every model entity.
MODEL = f"{WORLD}/model"
#: Root of trained models' frames (:func:`log_contact_model`).
TRAINING = f"{MODEL}/training"
#: Root of predictions (:func:`log_prediction`).
PREDICTION = f"{MODEL}/prediction"
#: The sequence timeline of simulated annealing: step 0 holds the initial candidates.
ANNEAL_TIMELINE = "anneal_step"
#: Where a prediction's annealing series are, relative to its root, and what each annealing optimises.
ANNEAL_SERIES = {
    "robot_query/best_log_prob": "robot start pose (robot query)",
    "pose_query/best_log_prob": "initial object pose (pose query)",
    "motion/best_log_prob": "final object pose (motion)",
}

_OBJECT_COLOUR = (70, 130, 220, 255)
_ESTIMATE_COLOUR = (90, 170, 255, 110)
_PREDICTED_COLOUR = (255, 150, 40, 140)
_TRUE_INITIAL_COLOUR = (160, 160, 160, 110)
_TRUE_FINAL_COLOUR = (60, 200, 90, 140)
_ERROR_COLOUR = (230, 30, 30, 255)
_CHASSIS_COLOUR = (190, 40, 40, 160)
_BUMPER_COLOUR = (240, 200, 40, 255)
_CLOUD_COLOUR = (150, 150, 150, 255)
_MANIPULATOR_COLOUR = (240, 60, 160, 255)
_ENVIRONMENT_COLOUR = (40, 200, 200, 255)
_REGION_COLOUR = (255, 120, 30, 255)
_MODE_COLOUR = (255, 40, 200, 255)
_SUBSAMPLE_SEED = 0
#: Draws from a prediction's density logged per prediction (at most ``max_points``).
DENSITY_SAMPLES = 1000
#: Draws shown as ghost poses (axis triads; at most ``max_frames``).
DENSITY_GHOSTS = 20
#: Probability mass of the highest-density region shown.
DENSITY_REGION = 0.9
#: Seed of the generator the logged draws come from (made inside :func:`log_density`).
DENSITY_SEED = 0


def _check_limits(max_points: int, max_frames: int) -> None:
    for name, value in (("max_points", max_points), ("max_frames", max_frames)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise InvalidParameterError(f"{name} must be an integer >= 1, got {value!r}")


def _subsample(n: int, limit: int, device=None) -> torch.Tensor:
    """Indices of at most ``limit`` of ``n`` items: all of them, or a fixed-seed random subset (sorted)."""
    if n <= limit:
        return torch.arange(n, device=device)
    generator = torch.Generator().manual_seed(_SUBSAMPLE_SEED)
    return torch.randperm(n, generator=generator)[:limit].sort().values.to(device)


def _weight_colors(weights: torch.Tensor) -> np.ndarray:
    """Non-negative weights → viridis, saturating at the 95th percentile (weights are heavy-tailed)."""
    w = weights.detach().float().cpu()
    w = torch.where(torch.isfinite(w), w, torch.zeros_like(w)).clamp_min(0)
    return curvature_colors(w)


def _range_colors(values: torch.Tensor) -> np.ndarray:
    """Values → viridis over their finite range (min dark, max bright); non-finite (``-inf`` log-likelihood:
    no support) gets the darkest colour."""
    lp = values.detach().double().cpu()
    finite = torch.isfinite(lp)
    if not finite.any():
        return curvature_colors(torch.zeros_like(lp), vmax=1.0)
    low, high = lp[finite].min(), lp[finite].max()
    shifted = torch.where(finite, lp - low, torch.zeros_like(lp))
    return curvature_colors(shifted, vmax=float(high - low) if high > low else 1.0)


def _mesh_of(obj) -> trimesh.Trimesh | None:
    """The mesh of an :class:`~pushtorch.objects.ObjectModel`, a mesh itself, or None."""
    if obj is None or isinstance(obj, trimesh.Trimesh):
        return obj
    mesh = getattr(obj, "mesh", None)
    if not isinstance(mesh, trimesh.Trimesh):
        raise InvalidParameterError(f"expected an ObjectModel or a trimesh.Trimesh, got {type(obj).__name__}")
    return mesh


def _log_posed_mesh(
    rec: rr.RecordingStream,
    entity_path: str,
    pose: se3.Pose,
    mesh: trimesh.Trimesh | None,
    color: tuple[int, int, int, int],
    axis_length: float = 0.05,
) -> None:
    """A pose as a transform with an axis triad, and the mesh under it if there is one (all static)."""
    pose = se3.Pose.unchecked(pose.p.reshape(3), pose.q.reshape(4))
    log_pose(rec, entity_path, pose, static=True)
    origin = se3.identity((1,), dtype=pose.p.dtype)
    log_frames(rec, f"{entity_path}/axes", origin, length=axis_length, static=True)
    if mesh is not None:
        log_mesh(rec, f"{entity_path}/mesh", mesh, color=color, static=True)


def _log_robot(rec: rr.RecordingStream, root: str, base: se3.Pose) -> None:
    """The robot at one base pose: ``<root>/robot`` (transform, chassis, axes), ``<root>/bumper`` (world)."""
    from pushtorch.robot import bumper_geometry, bumper_mesh

    base = se3.Pose.unchecked(base.p.reshape(3), base.q.reshape(4))
    geometry = bumper_geometry()
    chassis = trimesh.creation.box(extents=geometry.chassis_size)
    chassis.apply_translation(geometry.chassis_centre)
    log_pose(rec, f"{root}/robot", base, static=True)
    log_mesh(rec, f"{root}/robot/chassis", chassis, color=_CHASSIS_COLOUR)
    log_frames(rec, f"{root}/robot/axes", se3.identity((1,), dtype=base.p.dtype), length=0.1, static=True)
    log_mesh(rec, f"{root}/bumper", bumper_mesh(base), color=_BUMPER_COLOUR)


def _log_frames_and_points(
    rec: rr.RecordingStream,
    root: str,
    frames: ContactFrames,
    colors,
    max_points: int,
    max_frames: int,
    frame_length: float = 0.01,
) -> None:
    """``<root>/points`` (positions ``v``) and ``<root>/frames`` (axis triads), each subsampled."""
    n = len(frames)
    shown = _subsample(n, max_points, frames.r.device)
    colors = colors[shown.cpu().numpy()] if isinstance(colors, np.ndarray) and colors.ndim == 2 else colors
    log_points(rec, f"{root}/points", frames.v.p[shown], colors=colors, radii=0.002, static=True)
    triads = _subsample(n, max_frames, frames.r.device)
    log_frames(rec, f"{root}/frames", frames.v.take(triads), length=frame_length, static=True)


def log_anneal_history(
    rec: rr.RecordingStream,
    entity_path: str,
    result: AnnealResult,
    max_points: int = 3000,
    radius: float = 0.003,
) -> bool:
    """Annealing candidates per step on the ``anneal_step`` timeline, in one columnar send.

    Step ``k`` of the timeline shows the chains' current positions ``history.p[k]`` (``k = 0``: the
    initial candidates), coloured by their log-likelihood over the whole run (so colours compare
    across steps). Batch dims of the problem are flattened with the candidates.

    Args:
        rec: an open recording.
        entity_path: where to log the points.
        result: an :class:`~pushtorch.anneal.AnnealResult`; its ``history`` is Pose ``(steps+1, *B, C)``.
        max_points: candidates shown per step (the same subset every step).
        radius: point radius in metres.
    Returns:
        False (and nothing logged) if ``result`` has no history (annealing ran without
        ``record_history=True``), else True.
    Raises:
        InvalidParameterError: ``max_points`` < 1.
    """
    _check_limits(max_points, 1)
    if result.history is None:
        return False
    steps = result.history.p.shape[0]
    positions = result.history.p.reshape(steps, -1, 3)
    shown = _subsample(positions.shape[1], max_points, positions.device)
    positions = positions[:, shown]
    if result.history_log_prob is not None:
        colors = _range_colors(result.history_log_prob.reshape(steps, -1)[:, shown].reshape(-1))
    else:
        colors = np.full((positions.shape[0] * positions.shape[1], 3), 200, dtype=np.uint8)
    count = positions.shape[1]
    rec.send_columns(
        entity_path,
        indexes=[rr.TimeColumn(ANNEAL_TIMELINE, sequence=np.arange(steps))],
        columns=rr.Points3D.columns(
            positions=positions.detach().cpu().numpy().reshape(-1, 3).astype(np.float32),
            colors=colors,
            radii=np.full(steps * count, radius, dtype=np.float32),
        ).partition([count] * steps),
    )
    return True


def log_anneal_series(rec: rr.RecordingStream, entity_path: str, result: AnnealResult) -> bool:
    """The annealing's best log-likelihood per step as a scalar series on ``anneal_step``, in one send.

    Two series on ``entity_path``: "step best", the highest log-likelihood among the chains' current
    positions at each step (``history_log_prob``; step 0: the initial candidates), and "best so far",
    its running maximum. Batch dims of the problem are pooled with the candidates. A step with no
    candidate in the density's support (``-inf``) is a gap (NaN) in the plot.

    Returns:
        False (and nothing logged) if ``result`` has no per-step log-likelihoods (annealing ran without
        ``record_history=True``), else True.
    """
    if result.history_log_prob is None:
        return False
    steps = result.history_log_prob.shape[0]
    step_best = result.history_log_prob.detach().double().cpu().reshape(steps, -1).max(dim=1).values
    best_so_far = torch.cummax(step_best, dim=0).values
    series = torch.stack([step_best, best_so_far], dim=1)  # (steps, 2)
    series = torch.where(torch.isfinite(series), series, torch.full_like(series, float("nan")))
    rec.log(entity_path, rr.SeriesLines(names=["step best", "best so far"]), static=True)
    rec.send_columns(
        entity_path,
        indexes=[rr.TimeColumn(ANNEAL_TIMELINE, sequence=np.arange(steps))],
        columns=rr.Scalars.columns(scalars=series.numpy().reshape(-1)).partition([2] * steps),
    )
    return True


def log_query(rec: rr.RecordingStream, root: str, query: QueryResult, max_points: int = 3000) -> None:
    """A query density and its optimisation under ``root`` (paper, Query Density).

    Logs ``root/features`` (the kernels' cloud features ``v``) and ``root/kernels`` (their means
    ``v ∘ u``, planar-projected for the robot), both coloured by kernel weight, if ``query.density`` is
    set; ``root/candidates`` per annealing step and the series ``root/best_log_prob``
    (:func:`log_anneal_series`) if the history was recorded; and ``root/final_candidates`` coloured by
    log-likelihood.

    Raises:
        InvalidParameterError: ``max_points`` < 1.
    """
    _check_limits(max_points, 1)
    density = query.density
    if density is not None:
        means = density.kde.means.p.reshape(-1, 3)
        weights = density.kde.log_weights.reshape(-1).exp()
        shown = _subsample(means.shape[0], max_points, means.device)
        colors = _weight_colors(weights[shown])
        log_points(rec, f"{root}/features", density.kernels.v.p.reshape(-1, 3)[shown], colors=colors,
                   radii=0.002, static=True)
        log_points(rec, f"{root}/kernels", means[shown], colors=colors, radii=0.003, static=True)
    log_anneal_history(rec, f"{root}/candidates", query.anneal, max_points)
    log_anneal_series(rec, f"{root}/best_log_prob", query.anneal)
    candidates = query.anneal.candidates.p.reshape(-1, 3)
    shown = _subsample(candidates.shape[0], max_points, candidates.device)
    log_points(rec, f"{root}/final_candidates", candidates[shown],
               colors=_range_colors(query.anneal.log_prob.reshape(-1)[shown]), radii=0.004, static=True)


def log_contact_model(
    rec: rr.RecordingStream,
    model,
    obj=None,
    object_pose: se3.Pose | None = None,
    label: str | None = None,
    max_points: int = 3000,
    max_frames: int = 300,
) -> str:
    """Log a trained model's manipulator contact frames, training placement and position frames.

    The frames are stored relative to the training object's origin ``B^O``; they are drawn on the
    object at ``object_pose`` (default: its training pose, upright at the origin), and the robot where
    the frames put it: ``object_pose ∘ v ∘ u^m`` (their mean, on the ground). Entity paths: see the
    module docstring.

    Args:
        rec: an open recording (:func:`pushtorch.viz.open_recording`).
        model: a :class:`~pushtorch.models.library.PushModel`.
        obj: the training :class:`~pushtorch.objects.ObjectModel` or its mesh (object frame); default
            the catalogue object named ``model.object_name``.
        object_pose: where to draw the object, Pose ``()``; default its resting pose at the origin
            (the pose the model was trained at).
        label: entity name under ``world/model/training`` (default the model's name).
        max_points: points shown per point set; max_frames: axis triads shown per frame set.
    Returns:
        The model's root entity path.
    Raises:
        InvalidParameterError: a limit below 1, an empty label, or ``obj`` of the wrong type.
        PushtorchError: ``obj`` is None and ``model.object_name`` is not a catalogue object.
    """
    from pushtorch.objects import load_object

    _check_limits(max_points, max_frames)
    if obj is None:
        obj = load_object(model.object_name)
    mesh = _mesh_of(obj)
    if object_pose is None:
        # ObjectModel.resting_pose's definition, which a bare mesh lacks
        object_pose = se3.from_xy_yaw(0.0, 0.0, 0.0, z=float(-mesh.bounds[0, 2]))
    object_pose = se3.Pose.unchecked(object_pose.p.reshape(3).float(), object_pose.q.reshape(4).float())
    root = f"{TRAINING}/{entity_name(label if label is not None else model.name)}"
    _log_posed_mesh(rec, f"{root}/object", object_pose, mesh, _OBJECT_COLOUR, axis_length=0.1)

    contact = model.contact.frames.to(torch.float32).transformed(object_pose)
    # w^c = exp(-λ_c d²) spans a narrow band (0.99–1 with the paper's λ_c, δ_c): show its range
    contact_colors = _range_colors(contact.weight)
    _log_frames_and_points(rec, f"{root}/contact", contact, contact_colors, max_points, max_frames)
    implied = contact.entity  # (N,): the robot base pose each frame implies
    shown = _subsample(len(contact), max_points, implied.p.device)
    log_points(rec, f"{root}/contact/implied_robot", implied.p[shown],
               colors=contact_colors[shown.cpu().numpy()], radii=0.004, static=True)
    _log_robot(rec, root, planar(se3.mean_pose(implied)))

    position = model.position.frames.to(torch.float32).transformed(object_pose)
    _log_frames_and_points(rec, f"{root}/position", position, _weight_colors(position.weight),
                           max_points, max_frames)
    return root


def _one_pose(pose: se3.Pose, like: torch.Tensor | None = None) -> se3.Pose:
    """A pose ``()`` from a pose of one element (cast to ``like``'s dtype and device if given)."""
    p, q = pose.p.reshape(3), pose.q.reshape(4)
    if like is not None:
        p, q = p.to(like), q.to(like)
    return se3.Pose.unchecked(p, q)


def density_truth(prediction, truth_final: se3.Pose, truth_initial: se3.Pose | None = None) -> se3.Pose:
    """The truth where the prediction's density is: the true motion ``B1 ∘ B0⁻¹`` applied to the estimated
    start ``B̂0`` (``truth_final`` as it is if ``truth_initial`` is None), Pose ``()``.

    The density is over the final pose given the *estimated* start, so this is the pose whose
    ``prediction.density.log_prob`` scores the truth (README's library example).
    """
    estimate = _one_pose(prediction.condition.object_pose)
    final = _one_pose(truth_final, estimate.p)
    if truth_initial is None:
        return final
    start = _one_pose(truth_initial, estimate.p)
    return final.compose(start.inverse()).compose(estimate)


def log_density(
    rec: rr.RecordingStream,
    root: str,
    density,
    truth: se3.Pose | None = None,
    max_points: int = 3000,
    max_frames: int = 300,
) -> bool:
    """A prediction's density over final poses: draws, its 90 % region, ghost poses, mode and truth.

    Logs, all static, ``<root>/density/samples`` (:data:`DENSITY_SAMPLES` draws, at most ``max_points``:
    final positions coloured by log-density, viridis over their range), ``<root>/density/region_90`` (the
    draws inside the :data:`DENSITY_REGION` highest-density region: the ``ceil(0.9 n)`` draws of highest
    log-density, since the draws' log-densities at or above their 10 % quantile mark the region that holds
    90 % of the mass; a point set, no hull or box), ``<root>/density/ghosts`` (the first
    :data:`DENSITY_GHOSTS` draws, at most ``max_frames``, as axis triads), ``<root>/density/mode`` (the
    density's mode, a point, with its triad at ``/axes``) and, if given, ``<root>/density/truth`` (a point
    and ``/axes``).

    The draws come from a generator made here and seeded with :data:`DENSITY_SEED` (on the density's
    device): no caller's stream and not torch's global one is drawn from, and the density's own values do
    not change (its normaliser is seeded too).

    Args:
        rec: an open recording.
        root: the prediction's root entity path.
        density: a :class:`~pushtorch.distribution.FinalPoseDistribution` (any batch shape: draws pooled).
        truth: the truth in the density's frame (:func:`density_truth`), Pose ``()``, or None.
        max_points: draws shown; max_frames: ghost poses shown.
    Returns:
        False if the density could not be drawn from (no proposal with non-zero density: a warning, and
        only the mode and truth are logged), else True.
    Raises:
        InvalidParameterError: a limit below 1.
    """
    _check_limits(max_points, max_frames)
    mode = density.mode.detach().reshape(-1, 7)
    modes = se3.Pose.unchecked(mode[:, :3], mode[:, 3:])
    log_points(rec, f"{root}/density/mode", modes.p, colors=_MODE_COLOUR, radii=0.006, static=True)
    log_frames(rec, f"{root}/density/mode/axes", modes, length=0.05, static=True)
    if truth is not None:
        truth = _one_pose(truth)
        log_points(rec, f"{root}/density/truth", truth.p.reshape(1, 3), colors=_TRUE_FINAL_COLOUR[:3],
                   radii=0.006, static=True)
        log_frames(rec, f"{root}/density/truth/axes", truth.reshape(1), length=0.05, static=True)
    n = min(DENSITY_SAMPLES, max_points)
    generator = torch.Generator(device=mode.device).manual_seed(DENSITY_SEED)
    try:
        with torch.no_grad():
            draws = density.sample((n,), generator)  # (n, *B, 7)
            log_p = density.log_prob(draws).reshape(-1).double()
    except ModelError as exc:
        log.warning("%s: no draws from the prediction's density logged: %s", root, exc)
        return False
    draws = draws.reshape(-1, 7)
    poses = se3.Pose.unchecked(draws[:, :3], draws[:, 3:])
    log_points(rec, f"{root}/density/samples", poses.p, colors=_range_colors(log_p), radii=0.002, static=True)
    # highest log-density first; ties keep draw order, so the region is the same every time
    order = torch.sort(torch.nan_to_num(log_p, nan=-math.inf), descending=True, stable=True).indices
    inside = order[: math.ceil(DENSITY_REGION * order.numel())].sort().values
    log_points(rec, f"{root}/density/region_90", poses.p[inside], colors=_REGION_COLOUR, radii=0.0035,
               static=True)
    ghosts = torch.arange(min(DENSITY_GHOSTS, max_frames, poses.p.shape[0]), device=poses.p.device)
    log_frames(rec, f"{root}/density/ghosts", poses.take(ghosts), length=0.03, static=True)
    return True


def log_collision_parts(rec: rr.RecordingStream, entity_path: str, obj, pose: se3.Pose | None = None) -> bool:
    """The convex parts the simulator collides ``obj`` as, if there are several (static).

    ``entity_path`` gets ``pose``'s transform (if given) and ``entity_path/part_<k>`` a mesh per part of
    :attr:`~pushtorch.objects.ObjectModel.collision_parts` (object frame), one tab10 colour each.

    Returns:
        True if the parts were logged; False (nothing logged) for an object simulated as one part, or
        anything that is not an ObjectModel (a bare mesh).
    """
    parts = getattr(obj, "collision_parts", None)
    if isinstance(obj, trimesh.Trimesh) or not parts or len(parts) < 2:
        return False
    from matplotlib import colormaps

    palette = (np.asarray(colormaps["tab10"].colors)[:, :3] * 255).astype(np.uint8)
    if pose is not None:
        log_pose(rec, entity_path, _one_pose(pose), static=True)
    for k, part in enumerate(parts):
        colour = tuple(int(c) for c in palette[k % len(palette)]) + (200,)
        log_mesh(rec, f"{entity_path}/part_{k}", part, color=colour, static=True)
    return True


def log_prediction(
    rec: rr.RecordingStream,
    prediction,
    truth_initial: se3.Pose | None = None,
    truth_final: se3.Pose | None = None,
    object_mesh=None,
    label: str = "prediction",
    cloud=None,
    max_points: int = 3000,
    max_frames: int = 300,
    truth_push=None,
) -> str:
    """Log a prediction: query kernels, robot start, contact frames, initial pose, annealing, final pose,
    and the predicted density (:func:`log_density`).

    Entity paths: see the module docstring. The per-step annealing candidates and series need the
    prediction to have been made with ``record_history=True``; the query kernels need
    ``QueryResult.density``. Logging draws from no caller's random stream and leaves the prediction as
    it was (:func:`log_density`).

    Args:
        rec: an open recording (:func:`pushtorch.viz.open_recording`).
        prediction: a :class:`~pushtorch.prediction.Prediction`.
        truth_initial, truth_final: the true object poses before and after the push, Pose ``()``, if known.
        object_mesh: the object's mesh (object frame) or its ObjectModel, drawn at every object pose;
            without it, the poses are drawn as axis triads only. An ObjectModel simulated as several
            convex parts also gets them drawn at ``<root>/collision_parts`` (:func:`log_collision_parts`).
        label: entity path under ``world/model/prediction``; ``/`` nests it (``part/object/model/c0a1``).
        cloud: the partial cloud the prediction was made from (a PointCloud, SurfaceFeatures or
            ``(N, 3)`` tensor), logged as ``<root>/cloud`` if given.
        max_points: points shown per point set; max_frames: axis triads shown per frame set.
        truth_push: the ground-truth push as :class:`~pushtorch.sim.records.PushRecords`; its first push
            is played on ``sim_time`` at ``<root>/truth_push`` (:func:`pushtorch.viz.sim.log_push`).
    Returns:
        The prediction's root entity path.
    Raises:
        InvalidParameterError: a limit below 1, an empty label, or a mesh of the wrong type.
    """
    from pushtorch.viz.sim import log_push

    _check_limits(max_points, max_frames)
    mesh = _mesh_of(object_mesh)
    root = f"{PREDICTION}/{entity_name(label)}"
    condition = prediction.condition

    if cloud is not None:
        points = getattr(cloud, "points", None)
        points = points if points is not None else getattr(cloud, "p", cloud)
        points = torch.as_tensor(points).reshape(-1, 3)
        log_points(rec, f"{root}/cloud", points[_subsample(points.shape[0], max_points, points.device)],
                   colors=_CLOUD_COLOUR, radii=0.0015, static=True)

    if condition.robot_query is not None:  # None: the caller gave the start
        log_query(rec, f"{root}/robot_query", condition.robot_query, max_points)
    log_query(rec, f"{root}/pose_query", condition.pose_query, max_points)

    _log_robot(rec, root, condition.robot_start)
    manipulator, environment = condition.manipulator_frame, condition.environment_frames
    log_frames(rec, f"{root}/manipulator_contact/frame", manipulator.v.reshape(-1), length=0.03, static=True)
    log_arrows(rec, f"{root}/manipulator_contact/relation", manipulator.v.p.reshape(-1, 3),
               (manipulator.entity.p - manipulator.v.p).reshape(-1, 3), colors=_MANIPULATOR_COLOUR,
               static=True)
    log_points(rec, f"{root}/environment_contacts/points", environment.v.p.reshape(-1, 3),
               colors=_ENVIRONMENT_COLOUR, radii=0.005, static=True)
    log_frames(rec, f"{root}/environment_contacts/frames", environment.v.reshape(-1), length=0.03,
               static=True)
    log_arrows(rec, f"{root}/environment_contacts/relation", environment.v.p.reshape(-1, 3),
               (environment.entity.p - environment.v.p).reshape(-1, 3), colors=_ENVIRONMENT_COLOUR,
               static=True)

    _log_posed_mesh(rec, f"{root}/initial_estimate", condition.object_pose, mesh, _ESTIMATE_COLOUR)

    experts = prediction.motion_density.experts
    means = experts.means.p.reshape(-1, 3)
    expert_index = torch.arange(experts.batch_shape.numel(), device=means.device).repeat_interleave(
        experts.num_kernels
    )
    real = torch.isfinite(experts.log_weights.reshape(-1)).nonzero().squeeze(-1)  # -inf marks padding
    real = real[_subsample(real.shape[0], max_points, real.device)]
    from matplotlib import colormaps

    palette = (np.asarray(colormaps["tab10"].colors)[:, :3] * 255).astype(np.uint8)
    log_points(rec, f"{root}/motion/experts", means[real],
               colors=palette[expert_index[real].cpu().numpy() % len(palette)], radii=0.002, static=True)
    motion_anneal = getattr(prediction, "anneal", None)
    if isinstance(motion_anneal, AnnealResult):
        log_anneal_history(rec, f"{root}/motion/candidates", motion_anneal, max_points)
        log_anneal_series(rec, f"{root}/motion/best_log_prob", motion_anneal)
    candidates = prediction.candidates.p.reshape(-1, 3)
    shown = _subsample(candidates.shape[0], max_points, candidates.device)
    log_points(rec, f"{root}/motion/final_candidates", candidates[shown],
               colors=_range_colors(prediction.candidate_log_prob.reshape(-1)[shown]), radii=0.004,
               static=True)

    _log_posed_mesh(rec, f"{root}/final_predicted", prediction.final_pose, mesh, _PREDICTED_COLOUR)
    if truth_initial is not None:
        _log_posed_mesh(rec, f"{root}/initial_true", truth_initial, mesh, _TRUE_INITIAL_COLOUR)
        estimate = condition.object_pose.p.reshape(3)
        truth = truth_initial.p.reshape(3).to(estimate)
        log_line_strip(rec, f"{root}/initial_error", torch.stack([estimate, truth]), color=_ERROR_COLOUR,
                       static=True)
    if truth_final is not None:
        _log_posed_mesh(rec, f"{root}/final_true", truth_final, mesh, _TRUE_FINAL_COLOUR)
        predicted = prediction.final_pose.p.reshape(3)
        truth = truth_final.p.reshape(3).to(predicted)
        log_line_strip(rec, f"{root}/final_error", torch.stack([predicted, truth]), color=_ERROR_COLOUR,
                       static=True)
    if truth_push is not None:
        log_push(rec, truth_push, 0, mesh, root=f"{root}/truth_push", with_final_pose=False)
    log_collision_parts(rec, f"{root}/collision_parts", object_mesh,
                        truth_initial if truth_initial is not None else condition.object_pose)
    density = getattr(prediction, "density", None)
    if density is not None:
        truth = None if truth_final is None else density_truth(prediction, truth_final, truth_initial)
        log_density(rec, root, density, truth, max_points, max_frames)
    return root
