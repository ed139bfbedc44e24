"""Rerun logging of a query density and its optimisation: its kernels and its annealed candidates.

Paper, §TPMM (Query Density): the robot query (robot start poses) and the position model's pose query
(initial object poses) are each a density over poses, built from kernels on the cloud's features and
maximised by simulated annealing (:mod:`~pushtorch.viz.annealing`). Entity paths, under the root the caller
names (a prediction's ``robot_query`` or ``pose_query``):

================================  ==========================================================
``<root>/features``               the kernels' cloud features ``v``, coloured by kernel weight
``<root>/kernels``                their means ``v ∘ u`` (robot base positions on the ground; object poses)
``<root>/candidates``             annealing candidates per step on ``anneal_step``, coloured by log-likelihood
``<root>/final_candidates``       the annealed candidates, coloured by log-likelihood
``<root>/best_log_prob``          the best log-likelihood per step on ``anneal_step``
================================  ==========================================================

The kernels need :attr:`pushtorch.models.query.QueryResult.density`; a result without it logs everything else.
"""

from __future__ import annotations

import rerun as rr

from pushtorch.models.query import QueryResult
from pushtorch.viz.annealing import log_anneal_history, log_anneal_series
from pushtorch.viz.core import log_points
from pushtorch.viz.helpers import check_limits, range_colors, subsample, weight_colors

__all__ = ["log_query"]


def log_query(rec: rr.RecordingStream, root: str, query: QueryResult, max_points: int = 3000) -> None:
    """A query density and its optimisation under ``root`` (paper, Query Density).

    Logs ``root/features`` (the kernels' cloud features ``v``) and ``root/kernels`` (their means
    ``v ∘ u``, planar-projected for the robot), both coloured by kernel weight, if ``query.density`` is
    set; ``root/candidates`` per annealing step and the series ``root/best_log_prob``
    (:func:`~pushtorch.viz.annealing.log_anneal_series`) if the history was recorded; and
    ``root/final_candidates`` coloured by log-likelihood.

    Raises:
        InvalidParameterError: ``max_points`` < 1.
    """
    check_limits(max_points, 1)
    density = query.density
    if density is not None:
        means = density.kde.means.p.reshape(-1, 3)
        weights = density.kde.log_weights.reshape(-1).exp()
        shown = subsample(means.shape[0], max_points, means.device)
        colors = weight_colors(weights[shown])
        log_points(rec, f"{root}/features", density.kernels.v.p.reshape(-1, 3)[shown], colors=colors,
                   radii=0.002, static=True)
        log_points(rec, f"{root}/kernels", means[shown], colors=colors, radii=0.003, static=True)
    log_anneal_history(rec, f"{root}/candidates", query.anneal, max_points)
    log_anneal_series(rec, f"{root}/best_log_prob", query.anneal)
    candidates = query.anneal.candidates.p.reshape(-1, 3)
    shown = subsample(candidates.shape[0], max_points, candidates.device)
    log_points(rec, f"{root}/final_candidates", candidates[shown],
               colors=range_colors(query.anneal.log_prob.reshape(-1)[shown]), radii=0.004, static=True)
