"""The trial-round search: a density's kernels widened, one factor at a time, until some query survives the
cut-offs (:func:`fit_trial_rounds`, counting with :func:`coverage`).

Paper, Background → Kernel Density Estimation: a trial round fails when every (query, kernel) pair is cut off;
then one of the trial rounds T = (T_p, T_q, T_r) is incremented and the bandwidth multipliers β = α_T^(−T)
recomputed. The scaled distances are the dense reference's (:mod:`pushtorch.kde.dense`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from pushtorch.errors import ModelError
from pushtorch.kde.queries import prepare_queries, query_chunks
from pushtorch.kde.reductions import amin_to_size
from pushtorch.se3 import Pose

if TYPE_CHECKING:
    from pushtorch.kde.density import PoseKDE

Tensor = torch.Tensor

__all__ = ["coverage", "fit_trial_rounds"]


def coverage(
    kde: PoseKDE, pose: Pose, descriptors: Tensor | None, chunk_size: int | None
) -> tuple[Tensor, Tensor, Tensor]:
    """Per batch element: surviving (query, kernel) pairs ``(*B,)``, cut-offs per factor ``(*B, 3)``
    and the smallest β·d per factor ``(*B, 3)``, over valid (non-padding) kernels."""
    delta = kde.bandwidth.delta
    valid = kde.log_weights > -math.inf  # (*B, N)
    batch = kde.batch_shape
    survivors = torch.zeros(batch, dtype=torch.int64, device=kde.device)
    cuts = torch.zeros(*batch, 3, dtype=torch.int64, device=kde.device)
    nearest = torch.full((*batch, 3), math.inf, dtype=kde.dtype, device=kde.device)
    dense = kde.dense_kernels
    for p, q, r in query_chunks(kde, pose, descriptors, chunk_size):
        terms = dense.scaled_terms(p, q, r)
        valid_b = valid.unsqueeze(-2).expand_as(terms[0])
        alive = valid_b.clone()
        for k, bd in enumerate(terms):
            if bd is None:
                continue
            cut = bd >= delta[k]
            alive &= ~cut
            cuts[..., k] += (cut & valid_b).sum((-1, -2)).sum_to_size(batch)
            masked = bd.masked_fill(~valid_b, math.inf).amin((-1, -2))
            while masked.dim() > len(batch):
                masked = masked.amin(0)
            nearest[..., k] = torch.minimum(nearest[..., k], amin_to_size(masked, batch))
        survivors += alive.sum((-1, -2)).sum_to_size(batch)
    return survivors, cuts, nearest


def fit_trial_rounds(
    kde: PoseKDE, pose: Pose, descriptors: Tensor | None = None, chunk_size: int | None = None
) -> PoseKDE:
    """Widen the kernels by trial rounds until some (query, kernel) pair survives the cut-offs.

    Paper (Kernel Density Estimation): a trial round fails when every (query, kernel) pair is cut
    off by at least one factor; then one of T_p, T_q, T_r is incremented — the smallest, ties broken
    by which factor (N3, Θ, N2) caused the most cut-offs — and β = α_T^(−T) recomputed. A factor
    that cut off no pair is never raised (widening it cannot help); remaining ties go p, q, r.
    Each batch element is fitted independently; queries broadcast as in :meth:`log_prob` and every
    query batch that maps onto one density element counts toward that element.

    Args:
        pose: query poses ``(*B', M)``; descriptors: ``(*B', M, k)`` or None; chunk_size: as log_prob.

    Returns:
        A new PoseKDE with the fitted ``trial_rounds``; itself if no round fails or M = 0.

    Raises:
        ModelError: some element still fails when T_p + T_q + T_r reaches
            ``bandwidth.max_trial_rounds``.
    """
    p, _, _ = prepare_queries(kde, pose, descriptors)
    if p.shape[-2] == 0:
        return kde
    current = kde
    max_rounds = kde.bandwidth.max_trial_rounds
    while True:
        survivors, cuts, nearest = coverage(current, pose, descriptors, chunk_size)
        failed = survivors == 0
        if not failed.any():
            return current
        rounds = current.trial_rounds
        exhausted = failed & (rounds.sum(-1) >= max_rounds)
        if exhausted.any():
            where = exhausted.nonzero().tolist()
            first = tuple(where[0])
            raise ModelError(
                f"no kernel covers any query after {max_rounds} trial rounds"
                f" (T=(T_p, T_q, T_r)={tuple(rounds[first].tolist())}) for batch element(s)"
                f" {where[:5]}{'...' if len(where) > 5 else ''}; the smallest scaled distances β·d there"
                f" are (p, q, r)={tuple(round(v, 3) for v in nearest[first].tolist())} against cut-offs"
                f" δ={tuple(round(v, 3) for v in kde.bandwidth.delta)}. The queries lie far outside the"
                " model: widen the bandwidth, relax cutoff_std or raise max_trial_rounds."
            )
        eligible = cuts > 0
        big = torch.iinfo(torch.int64).max
        masked_rounds = torch.where(eligible, rounds, torch.full_like(rounds, big))
        smallest = masked_rounds.amin(-1, keepdim=True)
        candidates = eligible & (rounds == smallest)
        choice = torch.where(candidates, cuts, torch.full_like(cuts, -1)).argmax(-1)
        step = torch.nn.functional.one_hot(choice, 3) * failed.unsqueeze(-1)
        current = current.with_trial_rounds(rounds + step)
