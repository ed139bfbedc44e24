"""Rerun logging of a prediction's density over final poses: draws, its 90 % region, ghost poses, mode and truth.

Paper, §Motion Model, Eq. poe (the prediction as a product of experts, here a
:class:`~pushtorch.distribution.FinalPoseDistribution`). Entity paths (:func:`log_density`), all static, under a
prediction's root:

========================================  ==========================================================
``<root>/density/samples``                draws from ``prediction.density`` (:data:`DENSITY_SAMPLES`, at most
                                          ``max_points``): final positions, coloured by log-density
``<root>/density/region_90``              the draws inside the 90 % highest-density region: those whose
                                          log-density is among the highest 90 % of the draws' (a Monte
                                          Carlo estimate of the region's extent; a point set, no hull)
``<root>/density/ghosts``                 :data:`DENSITY_GHOSTS` of the draws as axis triads (their
                                          orientations)
``<root>/density/mode``                   the density's mode (a push model's ``prediction.final_pose``; a
                                          residual model may report another point): a point; its axis
                                          triad at ``/axes``
``<root>/density/truth``                  the truth in the density's frame, if ``truth_final`` is given: the
                                          true motion applied to the estimated start, ``B1 ∘ B0⁻¹ ∘ B̂0``
                                          (``truth_final`` as it is without ``truth_initial``); ``/axes``
========================================  ==========================================================

The density's draws come from a generator of their own, seeded with :data:`DENSITY_SEED` inside
:func:`log_density`: a recording never changes a prediction or a random stream of the caller, and two
recordings of one prediction show the same draws. Draws are importance-resampled
(:meth:`~pushtorch.distribution.FinalPoseDistribution.sample`), so a draw may repeat.
"""

from __future__ import annotations

import logging
import math

import rerun as rr
import torch

from pushtorch import se3
from pushtorch.errors import ModelError
from pushtorch.prediction.residual import ResidualPrediction
from pushtorch.viz.core import log_frames, log_points
from pushtorch.viz.helpers import TRUE_FINAL_COLOUR, check_limits, one_pose, range_colors

__all__ = [
    "DENSITY_GHOSTS",
    "DENSITY_REGION",
    "DENSITY_SAMPLES",
    "DENSITY_SEED",
    "density_truth",
    "draw_density",
    "log_density",
]

log = logging.getLogger(__name__)

_REGION_COLOUR = (255, 120, 30, 255)
_MODE_COLOUR = (255, 40, 200, 255)
#: Draws from a prediction's density logged per prediction (at most ``max_points``).
DENSITY_SAMPLES = 1000
#: Draws shown as ghost poses (axis triads; at most ``max_frames``).
DENSITY_GHOSTS = 20
#: Probability mass of the highest-density region shown.
DENSITY_REGION = 0.9
#: Seed of the generator the logged draws come from (made inside :func:`log_density`).
DENSITY_SEED = 0


def density_truth(prediction, truth_final: se3.Pose, truth_initial: se3.Pose | None = None) -> se3.Pose:
    """The truth where the prediction's density is: the true motion ``B1 ∘ B0⁻¹`` applied to the estimated
    start ``B̂0`` (a residual prediction's: its cloud body's start; ``truth_final`` as it is if ``truth_initial``
    is None), Pose ``()``.

    The density is over the final pose given the *estimated* start, so this is the pose whose
    ``prediction.density.log_prob`` scores the truth (README's library example).
    """
    # a residual model's density is over its cloud body's pose, from the body's start
    estimate = one_pose(prediction.start if isinstance(prediction, ResidualPrediction)
                        else prediction.condition.object_pose)
    final = one_pose(truth_final, estimate.p)
    if truth_initial is None:
        return final
    start = one_pose(truth_initial, estimate.p)
    return final.compose(start.inverse()).compose(estimate)


def draw_density(density, n: int = DENSITY_SAMPLES) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` draws of a density and their log-densities up to a constant, as :func:`log_density` shows them: draws
    ``(n * B, 7)`` (``B`` the density's batch size, pooled) and log-densities ``(n * B,)`` float64, from a generator
    of their own seeded with :data:`DENSITY_SEED` (no caller's stream is drawn from).

    Raises:
        ModelError: no proposal with non-zero density (nothing can be drawn).
    """
    generator = torch.Generator(device=density.mode.device).manual_seed(DENSITY_SEED)
    with torch.no_grad():
        draws = density.sample((n,), generator)  # (n, *B, 7)
        # colours and the region need only the order of the draws: no normaliser is estimated for them
        log_p = density.unnormalised_log_prob(draws).reshape(-1).double()
    return draws.reshape(-1, 7), log_p


def log_density(
    rec: rr.RecordingStream,
    root: str,
    density,
    truth: se3.Pose | None = None,
    max_points: int = 3000,
    max_frames: int = 300,
    drawn: tuple[torch.Tensor, torch.Tensor] | None = None,
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
        drawn: the draws :func:`draw_density` made of this density beforehand (where the prediction was made,
            say a cluster task), used as they are if there are as many as would be drawn; None: drawn here.
    Returns:
        False if the density could not be drawn from (no proposal with non-zero density: a warning, and
        only the mode and truth are logged), else True.
    Raises:
        InvalidParameterError: a limit below 1.
    """
    check_limits(max_points, max_frames)
    mode = density.mode.detach().reshape(-1, 7)
    modes = se3.Pose.unchecked(mode[:, :3], mode[:, 3:])
    log_points(rec, f"{root}/density/mode", modes.p, colors=_MODE_COLOUR, radii=0.006, static=True)
    log_frames(rec, f"{root}/density/mode/axes", modes, length=0.05, static=True)
    if truth is not None:
        truth = one_pose(truth)
        log_points(rec, f"{root}/density/truth", truth.p.reshape(1, 3), colors=TRUE_FINAL_COLOUR[:3],
                   radii=0.006, static=True)
        log_frames(rec, f"{root}/density/truth/axes", truth.reshape(1), length=0.05, static=True)
    n = min(DENSITY_SAMPLES, max_points)
    if drawn is None or drawn[0].shape[0] != n * density.batch_shape.numel():
        try:
            drawn = draw_density(density, n)
        except ModelError as exc:
            log.warning("%s: no draws from the prediction's density logged: %s", root, exc)
            return False
    draws, log_p = drawn
    poses = se3.Pose.unchecked(draws[:, :3], draws[:, 3:])
    log_points(rec, f"{root}/density/samples", poses.p, colors=range_colors(log_p), radii=0.002, static=True)
    # highest log-density first; ties keep draw order, so the region is the same every time
    order = torch.sort(torch.nan_to_num(log_p, nan=-math.inf), descending=True, stable=True).indices
    inside = order[: math.ceil(DENSITY_REGION * order.numel())].sort().values
    log_points(rec, f"{root}/density/region_90", poses.p[inside], colors=_REGION_COLOUR, radii=0.0035,
               static=True)
    ghosts = torch.arange(min(DENSITY_GHOSTS, max_frames, poses.p.shape[0]), device=poses.p.device)
    log_frames(rec, f"{root}/density/ghosts", poses.take(ghosts), length=0.03, static=True)
    return True
