"""Rerun logging of simulated annealing: each step's candidates and the best log-likelihood per step, on the
``anneal_step`` timeline.

Paper, Query Density (and Motion Model, which reuses it): the candidates sampled from a density's kernels and
annealed towards its highest likelihood (:mod:`pushtorch.anneal`). Step 0 of :data:`ANNEAL_TIMELINE` holds the
initial candidates; the per-step history needs annealing run with ``record_history=True``.
:data:`ANNEAL_SERIES` names where a prediction (:mod:`~pushtorch.viz.predictions`) logs its three annealing
series, which its blueprint plots (:mod:`~pushtorch.viz.blueprint`).
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import torch

from pushtorch.anneal import AnnealResult
from pushtorch.viz.helpers import check_limits, range_colors, subsample

__all__ = [
    "ANNEAL_SERIES",
    "ANNEAL_TIMELINE",
    "log_anneal_history",
    "log_anneal_series",
]

#: The sequence timeline of simulated annealing: step 0 holds the initial candidates.
ANNEAL_TIMELINE = "anneal_step"
#: Where a prediction's annealing series are, relative to its root, and what each annealing optimises.
ANNEAL_SERIES = {
    "robot_query/best_log_prob": "robot start pose (robot query)",
    "pose_query/best_log_prob": "initial object pose (pose query)",
    "motion/best_log_prob": "final object pose (motion)",
}


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
    check_limits(max_points, 1)
    if result.history is None:
        return False
    steps = result.history.p.shape[0]
    positions = result.history.p.reshape(steps, -1, 3)
    shown = subsample(positions.shape[1], max_points, positions.device)
    positions = positions[:, shown]
    if result.history_log_prob is not None:
        colors = range_colors(result.history_log_prob.reshape(steps, -1)[:, shown].reshape(-1))
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
