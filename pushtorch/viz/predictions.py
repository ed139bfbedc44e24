"""Rerun logging of a prediction: what each stage chose, from the query kernels to the predicted density.

Paper, §TPMM (Query Density, Environment Contact Model, Motion Model) and Fig. pipeline (prediction): what each
stage of a prediction chose, so a user can see *why* a push was predicted as it was. Everything is in the world
frame (z up, metres); point sets are subsampled with a fixed seed (:mod:`~pushtorch.viz.helpers`). Colours:
viridis, bright = high weight / log-likelihood.

Entity paths (:func:`log_prediction`), root ``world/model/prediction/<label>`` (the experiments' labels
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
``<root>/rollouts/start``                 a residual model's prediction
                                          (:class:`~pushtorch.prediction.residual.ResidualPrediction`)
                                          in place of ``motion/*``: the cloud body's start (axis triad)
``<root>/rollouts/finals``                each simulator rollout's final body position, coloured by its
                                          friction; ``final_frames`` their axis triads, ``paths`` arrows from
                                          the start to each
``<root>/rollouts/point``                 the residual model's point prediction in its density's frame (its
                                          ``final_pose``: the density's mode, the shifted mode or its push
                                          model's own, docs/method.md "The point prediction"); ``/axes``
``<root>/final_predicted``                predicted final pose (transform); ``/mesh``, ``/axes`` (a residual
                                          prediction's: its point's displacement applied to the estimate)
``<root>/initial_true``                   true initial pose, if given; ``/mesh``, ``/axes``
``<root>/final_true``                     true final pose, if given; ``/mesh``, ``/axes``
``<root>/initial_error``                  line from the estimated to the true initial centre, if given
``<root>/final_error``                    line from the predicted to the true final centre, if given
``<root>/truth_push/object``              *(s)* the ground-truth push, if given: the object's transform per
                                          recorded time; its mesh at ``/mesh``
``<root>/truth_push/robot``               *(s)* the robot base's transform; ``/chassis``, ``/bumper``, ``/bumper/mesh``
``<root>/truth_push/object_path``         the object centre's path during the push (``/robot_path``: the robot's)
``<root>/density/samples``                draws from ``prediction.density``
                                          (:data:`~pushtorch.viz.densities.DENSITY_SAMPLES`, at most
                                          ``max_points``): final positions, coloured by log-density
``<root>/density/region_90``              the draws inside the 90 % highest-density region: those whose
                                          log-density is among the highest 90 % of the draws' (a Monte
                                          Carlo estimate of the region's extent; a point set, no hull)
``<root>/density/ghosts``                 :data:`~pushtorch.viz.densities.DENSITY_GHOSTS` of the draws as axis
                                          triads (their orientations)
``<root>/density/mode``                   the density's mode (a push model's ``prediction.final_pose``; a
                                          residual model's point is ``rollouts/point``): a point; its axis
                                          triad at ``/axes``
``<root>/density/truth``                  the truth in the density's frame, if ``truth_final`` is given: the
                                          true motion applied to the estimated start, ``B1 ∘ B0⁻¹ ∘ B̂0``
                                          (``truth_final`` as it is without ``truth_initial``); ``/axes``
``<root>/collision_parts``                the object's convex collision parts, when the simulator used more
                                          than one (:attr:`~pushtorch.objects.ObjectModel.collision_parts`):
                                          a transform (the true initial pose, else the estimate) and a mesh
                                          per part at ``/part_<k>``
========================================  ==========================================================

The query kernels and annealing are :mod:`~pushtorch.viz.queries`' and :mod:`~pushtorch.viz.annealing`'s, the
density's entities :mod:`~pushtorch.viz.densities`', the meshes and the robot :mod:`~pushtorch.viz.bodies`'.
:class:`pushtorch.prediction.Prediction` keeps the motion annealing's candidates but not its per-step history;
if it gains an ``anneal`` attribute (an :class:`~pushtorch.anneal.AnnealResult`), ``motion/candidates`` is
logged from it.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult
from pushtorch.evaluation.metrics import displaced
from pushtorch.prediction.residual import ResidualPrediction
from pushtorch.viz.annealing import log_anneal_history, log_anneal_series
from pushtorch.viz.bodies import log_collision_parts, log_posed_mesh, log_robot, mesh_of
from pushtorch.viz.core import entity_name, log_arrows, log_frames, log_line_strip, log_points
from pushtorch.viz.densities import density_truth, log_density
from pushtorch.viz.helpers import MODEL, TRUE_FINAL_COLOUR, check_limits, range_colors, subsample
from pushtorch.viz.queries import log_query

__all__ = ["PREDICTION", "log_prediction"]

#: Root of predictions (:func:`log_prediction`).
PREDICTION = f"{MODEL}/prediction"

_ESTIMATE_COLOUR = (90, 170, 255, 110)
_PREDICTED_COLOUR = (255, 150, 40, 140)
_TRUE_INITIAL_COLOUR = (160, 160, 160, 110)
_ERROR_COLOUR = (230, 30, 30, 255)
_CLOUD_COLOUR = (150, 150, 150, 255)
_MANIPULATOR_COLOUR = (240, 60, 160, 255)
_ENVIRONMENT_COLOUR = (40, 200, 200, 255)
_ROLLOUT_COLOUR = (120, 220, 90, 255)


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
    drawn: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> str:
    """Log a prediction: query kernels, robot start, contact frames, initial pose, annealing, final pose,
    and the predicted density (:func:`~pushtorch.viz.densities.log_density`).

    Entity paths: see the module docstring. The per-step annealing candidates and series need the
    prediction to have been made with ``record_history=True``; the query kernels need
    ``QueryResult.density``. Logging draws from no caller's random stream and leaves the prediction as
    it was (:func:`~pushtorch.viz.densities.log_density`).

    Args:
        rec: an open recording (:func:`pushtorch.viz.open_recording`).
        prediction: a :class:`~pushtorch.prediction.Prediction`.
        truth_initial, truth_final: the true object poses before and after the push, Pose ``()``, if known.
        object_mesh: the object's mesh (object frame) or its ObjectModel, drawn at every object pose;
            without it, the poses are drawn as axis triads only. An ObjectModel simulated as several
            convex parts also gets them drawn at ``<root>/collision_parts``
            (:func:`~pushtorch.viz.bodies.log_collision_parts`).
        label: entity path under ``world/model/prediction``; ``/`` nests it (``part/object/model/c0a1``).
        cloud: the partial cloud the prediction was made from (a PointCloud, SurfaceFeatures or
            ``(N, 3)`` tensor), logged as ``<root>/cloud`` if given.
        max_points: points shown per point set; max_frames: axis triads shown per frame set.
        truth_push: the ground-truth push as :class:`~pushtorch.sim.records.PushRecords`; its first push
            is played on ``sim_time`` at ``<root>/truth_push`` (:func:`pushtorch.viz.sim.log_push`).
        drawn: the density's draws made beforehand (:func:`~pushtorch.viz.densities.draw_density`), or None.
    Returns:
        The prediction's root entity path.
    Raises:
        InvalidParameterError: a limit below 1, an empty label, or a mesh of the wrong type.
    """
    from pushtorch.viz.sim import log_push

    check_limits(max_points, max_frames)
    mesh = mesh_of(object_mesh)
    root = f"{PREDICTION}/{entity_name(label)}"
    condition = prediction.condition

    if cloud is not None:
        points = getattr(cloud, "points", None)
        points = points if points is not None else getattr(cloud, "p", cloud)
        points = torch.as_tensor(points).reshape(-1, 3)
        log_points(rec, f"{root}/cloud", points[subsample(points.shape[0], max_points, points.device)],
                   colors=_CLOUD_COLOUR, radii=0.0015, static=True)

    if condition.robot_query is not None:  # None: the caller gave the start
        log_query(rec, f"{root}/robot_query", condition.robot_query, max_points)
    log_query(rec, f"{root}/pose_query", condition.pose_query, max_points)

    log_robot(rec, root, condition.robot_start)
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

    log_posed_mesh(rec, f"{root}/initial_estimate", condition.object_pose, mesh, _ESTIMATE_COLOUR)

    if isinstance(prediction, ResidualPrediction):
        _log_rollouts(rec, f"{root}/rollouts", prediction, max_frames)
        # the density is over the cloud body's pose: its displacement, applied to the estimate, places the mesh
        final = displaced(prediction.start, prediction.final_pose, condition.object_pose)
    else:
        _log_motion(rec, f"{root}/motion", prediction, max_points)
        final = prediction.final_pose
    log_posed_mesh(rec, f"{root}/final_predicted", final, mesh, _PREDICTED_COLOUR)
    if truth_initial is not None:
        log_posed_mesh(rec, f"{root}/initial_true", truth_initial, mesh, _TRUE_INITIAL_COLOUR)
        estimate = condition.object_pose.p.reshape(3)
        truth = truth_initial.p.reshape(3).to(estimate)
        log_line_strip(rec, f"{root}/initial_error", torch.stack([estimate, truth]), color=_ERROR_COLOUR,
                       static=True)
    if truth_final is not None:
        log_posed_mesh(rec, f"{root}/final_true", truth_final, mesh, TRUE_FINAL_COLOUR)
        predicted = final.p.reshape(3)
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
        log_density(rec, root, density, truth, max_points, max_frames, drawn)
    return root


def _log_motion(rec: rr.RecordingStream, root: str, prediction, max_points: int) -> None:
    """A pushtorch prediction's experts' kernel means, its motion annealing and its final candidates."""
    experts = prediction.motion_density.experts
    means = experts.means.p.reshape(-1, 3)
    expert_index = torch.arange(experts.batch_shape.numel(), device=means.device).repeat_interleave(
        experts.num_kernels
    )
    real = torch.isfinite(experts.log_weights.reshape(-1)).nonzero().squeeze(-1)  # -inf marks padding
    real = real[subsample(real.shape[0], max_points, real.device)]
    from matplotlib import colormaps

    palette = (np.asarray(colormaps["tab10"].colors)[:, :3] * 255).astype(np.uint8)
    log_points(rec, f"{root}/experts", means[real],
               colors=palette[expert_index[real].cpu().numpy() % len(palette)], radii=0.002, static=True)
    motion_anneal = getattr(prediction, "anneal", None)
    if isinstance(motion_anneal, AnnealResult):
        log_anneal_history(rec, f"{root}/candidates", motion_anneal, max_points)
        log_anneal_series(rec, f"{root}/best_log_prob", motion_anneal)
    candidates = prediction.candidates.p.reshape(-1, 3)
    shown = subsample(candidates.shape[0], max_points, candidates.device)
    log_points(rec, f"{root}/final_candidates", candidates[shown],
               colors=range_colors(prediction.candidate_log_prob.reshape(-1)[shown]), radii=0.004,
               static=True)


def _log_rollouts(rec: rr.RecordingStream, root: str, prediction: ResidualPrediction, max_frames: int) -> None:
    """A residual prediction's simulator rollouts beside its density: the cloud body's start, each rollout's
    final pose (points coloured by the rollout's friction, and axis triads) and a line from the start to each."""
    start = prediction.start.p.reshape(3)
    finals = prediction.rollouts
    log_frames(rec, f"{root}/start", prediction.start.reshape(-1), length=0.05, static=True)
    # the point the model reports, in the density's frame (its density's mode unless the model reports another)
    point = prediction.final_pose.reshape(-1)
    log_points(rec, f"{root}/point", point.p, colors=_PREDICTED_COLOUR[:3], radii=0.008, static=True)
    log_frames(rec, f"{root}/point/axes", point, length=0.05, static=True)
    log_points(rec, f"{root}/finals", finals.p, colors=range_colors(prediction.physics[:, 0]), radii=0.006,
               static=True)
    shown = subsample(finals.p.shape[0], max_frames, finals.p.device)
    log_frames(rec, f"{root}/final_frames", finals.take(shown), length=0.04, static=True)
    log_arrows(rec, f"{root}/paths", start.expand_as(finals.p), finals.p - start.to(finals.p),
               colors=_ROLLOUT_COLOUR, static=True)
