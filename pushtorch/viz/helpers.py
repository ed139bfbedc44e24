"""Helpers shared by the recordings of a trained model and of a prediction: limits, fixed-seed subsets, colours.

Paper, §TPMM and Fig. pipeline (prediction): what :mod:`~pushtorch.viz.contacts`, :mod:`~pushtorch.viz.queries`,
:mod:`~pushtorch.viz.annealing`, :mod:`~pushtorch.viz.densities` and :mod:`~pushtorch.viz.predictions` draw
shares these. Everything is in the world frame (z up, metres). Point sets are subsampled to ``max_points``
(``max_frames`` for axis triads) with a fixed seed (:func:`subsample`), so logging stays cheap and two runs
log the same points. Colours: viridis, bright = high weight / log-likelihood (:func:`weight_colors`,
:func:`range_colors`).
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.models.frames import ContactFrames
from pushtorch.viz.core import WORLD, curvature_colors, log_frames, log_points

__all__ = [
    "MODEL",
    "TRUE_FINAL_COLOUR",
    "check_limits",
    "log_frames_and_points",
    "one_pose",
    "range_colors",
    "subsample",
    "weight_colors",
]

#: Root of every model entity.
MODEL = f"{WORLD}/model"
#: Colour of a true final pose: the prediction's ``final_true`` and the density's ``truth``.
TRUE_FINAL_COLOUR = (60, 200, 90, 140)
_SUBSAMPLE_SEED = 0


def check_limits(max_points: int, max_frames: int) -> None:
    """Check the logging limits: points shown per point set and axis triads shown per frame set.

    Raises:
        InvalidParameterError: either is not an integer >= 1 (a bool included).
    """
    for name, value in (("max_points", max_points), ("max_frames", max_frames)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise InvalidParameterError(f"{name} must be an integer >= 1, got {value!r}")


def subsample(n: int, limit: int, device=None) -> torch.Tensor:
    """Indices of at most ``limit`` of ``n`` items: all of them, or a fixed-seed random subset (sorted)."""
    if n <= limit:
        return torch.arange(n, device=device)
    generator = torch.Generator().manual_seed(_SUBSAMPLE_SEED)
    return torch.randperm(n, generator=generator)[:limit].sort().values.to(device)


def weight_colors(weights: torch.Tensor) -> np.ndarray:
    """Non-negative weights → viridis, saturating at the 95th percentile (weights are heavy-tailed)."""
    w = weights.detach().float().cpu()
    w = torch.where(torch.isfinite(w), w, torch.zeros_like(w)).clamp_min(0)
    return curvature_colors(w)


def range_colors(values: torch.Tensor) -> np.ndarray:
    """Values → viridis over their finite range (min dark, max bright); non-finite (``-inf`` log-likelihood:
    no support) gets the darkest colour."""
    lp = values.detach().double().cpu()
    finite = torch.isfinite(lp)
    if not finite.any():
        return curvature_colors(torch.zeros_like(lp), vmax=1.0)
    low, high = lp[finite].min(), lp[finite].max()
    shifted = torch.where(finite, lp - low, torch.zeros_like(lp))
    return curvature_colors(shifted, vmax=float(high - low) if high > low else 1.0)


def one_pose(pose: se3.Pose, like: torch.Tensor | None = None) -> se3.Pose:
    """A pose ``()`` from a pose of one element (cast to ``like``'s dtype and device if given)."""
    p, q = pose.p.reshape(3), pose.q.reshape(4)
    if like is not None:
        p, q = p.to(like), q.to(like)
    return se3.Pose.unchecked(p, q)


def log_frames_and_points(
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
    shown = subsample(n, max_points, frames.r.device)
    colors = colors[shown.cpu().numpy()] if isinstance(colors, np.ndarray) and colors.ndim == 2 else colors
    log_points(rec, f"{root}/points", frames.v.p[shown], colors=colors, radii=0.002, static=True)
    triads = subsample(n, max_frames, frames.r.device)
    log_frames(rec, f"{root}/frames", frames.v.take(triads), length=frame_length, static=True)
