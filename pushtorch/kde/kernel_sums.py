"""The fast path's fused functions: exact kernel sums ``Σ_i w_i K(x | μ_i)`` with the hard cut-offs, each in a
single pass over (queries × kernels), written out so that torch.compile fuses them and nothing of size
``queries × kernels`` is stored (:func:`dense_sums`, :func:`descriptor_sums`, :func:`block_sums`,
:func:`block_moments`, the pruning test :func:`reachable_blocks` and the distances :func:`pose_distances`).

Paper, Background → Kernel Density Estimation: the kernel of Eq. surface_feature_kernel with its cut-offs
(N3 / N2 and the antipodal vMF pair Θ, zero where ``β d ≥ δ``) and the weighted sum of Eq.
surface_feature_probability, the same values as the dense reference (:class:`pushtorch.kde.PoseKDE`) up to float
rounding. Sums run in the linear domain relative to each density's largest weight (:func:`linear_sums_exact`
says when that is exact). Pure tensor functions: :func:`pushtorch.kde.fused.fused_function` compiles them, and
:mod:`pushtorch.kde.fast_index` and :mod:`pushtorch.kde.products` lay out the kernels they take.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

Tensor = torch.Tensor

__all__ = [
    "block_moments",
    "block_sums",
    "dense_sums",
    "descriptor_sums",
    "linear_sums_exact",
    "pose_distances",
    "reachable_blocks",
]


def pose_distances(x: Sequence[Tensor], t: Sequence[Tensor], scale_p: Tensor, scale_q: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """The fused passes' kernel distances from the rows of queries ``x`` and kernels ``t`` (p then q, in
    any broadcastable layout): ``(β_p/σ_p |x_p − μ_p|², <x_q, μ_q>, β_q/σ_q (1 − |<x_q, μ_q>|))`` — the
    scaled terms :meth:`PoseKDE.log_prob` cuts off and sums (written out: compiled, nothing is stored)."""
    d_p = ((x[0] - t[0]) ** 2 + (x[1] - t[1]) ** 2 + (x[2] - t[2]) ** 2) * scale_p
    dot = x[3] * t[3] + x[4] * t[4] + x[5] * t[5] + x[6] * t[6]
    return d_p, dot, (1.0 - dot.abs()).clamp_min(0.0) * scale_q


def dense_sums(x: Tensor, table: Tensor, scale: Tensor, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) for every query against every kernel of its density: ``(Q, M)``.

    x: queries ``(Q, 7, M)`` (rows p, q); table: kernels ``(Q, 8, N)`` (rows p, q, log w relative to the
    largest); scale: ``(Q, 2)`` (β_p/σ_p, β_q/σ_q). Exact distances, the cut-offs of
    :meth:`PoseKDE.log_prob`; compiled, no ``(Q, M, N)`` tensor is stored.
    """
    t = table.unsqueeze(2)  # (Q, 8, 1, N)
    sc = scale[:, :, None, None]
    d_p, _, d_q = pose_distances(x.unsqueeze(-1).unbind(1), t.unbind(1), sc[:, 0], sc[:, 1])  # x: (Q, 7, M, 1)
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)).sum(-1)


def linear_sums_exact(relative_log_w: Tensor) -> bool:
    """Whether weights given relative to the largest (``≤ 0``, ``-inf`` padding) can be summed in the
    linear domain: exactly unless a kernel weighs ~e^-60 less than the largest (float32)."""
    live = relative_log_w[relative_log_w > -math.inf]
    return bool((live > math.log(torch.finfo(relative_log_w.dtype).tiny) + 25.0).all())


def descriptor_sums(x: Tensor, table: Tensor, scale: Tensor, r_scale: Tensor, delta_p: float, delta_q: float,
                     delta_r: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) with descriptors for queries ``x (7 + k, M)`` (rows p, q, r) against kernels
    ``table (8 + k, N)`` (rows p, q, relative log w, r): ``(M,)``. scale: ``(3,)`` (β_p/σ_p, β_q/σ_q,
    β_r), r_scale: ``(k,)`` 1/σ_r. Exact distances and every cut-off of :meth:`PoseKDE.log_prob`."""
    xs = x.unsqueeze(-1)  # (7 + k, M, 1)
    t = table.unsqueeze(1)  # (8 + k, 1, N)
    d_p, _, d_q = pose_distances(xs, t, scale[0], scale[1])
    d_r = sum((xs[7 + k] - t[8 + k]) ** 2 * r_scale[k] for k in range(r_scale.shape[0])) * scale[2]
    keep = (d_p < delta_p) & (d_q < delta_q) & (d_r < delta_r)
    return torch.where(keep, torch.exp(t[7] - d_p - d_q - d_r), torch.zeros_like(d_p)).sum(-1)


def reachable_blocks(
    x: Tensor, lo: Tensor, hi: Tensor, centre: Tensor, cos_reach: Tensor, r2: Tensor
) -> Tensor:
    """Which blocks each query may touch: ``(Q, M, nb)``, 1.0 where it may (float: compiles ~10× faster).

    x: queries ``(Q, 7, M)``; lo, hi: block bounding boxes ``(Q, 3, nb)``; centre: block rotation centres
    ``(Q, 4, nb)``; cos_reach: ``(Q, nb)`` cosine of half the largest angle at which the block can
    still hold a live kernel (−1: any, 2: none); r2: ``(Q, 1)`` squared translation reach (m²).
    """
    xs = x.unsqueeze(-1)  # (Q, 7, M, 1)
    lo, hi, centre = lo.unsqueeze(2), hi.unsqueeze(2), centre.unsqueeze(2)  # (Q, k, 1, nb)
    g0 = torch.clamp(torch.maximum(lo[:, 0] - xs[:, 0], xs[:, 0] - hi[:, 0]), min=0.0)
    g1 = torch.clamp(torch.maximum(lo[:, 1] - xs[:, 1], xs[:, 1] - hi[:, 1]), min=0.0)
    g2 = torch.clamp(torch.maximum(lo[:, 2] - xs[:, 2], xs[:, 2] - hi[:, 2]), min=0.0)
    near = g0 * g0 + g1 * g1 + g2 * g2 <= r2.unsqueeze(-1)
    dot = (xs[:, 3] * centre[:, 0] + xs[:, 4] * centre[:, 1] + xs[:, 5] * centre[:, 2]
           + xs[:, 6] * centre[:, 3]).abs()
    return (near & (dot >= cos_reach.unsqueeze(1))).to(x.dtype)


def _pair_kernels(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                  pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """``w K`` of every kernel of every (query, block) pair ``(P, L)``, with the pairs' blocks
    ``(P, 8, L)`` and the quaternion dot products ``(P, L)``; arguments as :func:`block_sums`."""
    density = query_density[pair_query]
    t = table[density * num_blocks + pair_block]  # (P, 8, L)
    xs = x[pair_query].unsqueeze(-1)  # (P, 7, 1)
    sc = scale[density]
    d_p, dot, d_q = pose_distances(xs.unbind(1), t.unbind(1), sc[:, 0:1], sc[:, 1:2])
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)), t, dot


def block_sums(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) per query ``(R,)`` over its (query, block) pairs.

    x: ``(R, 7)`` queries; table: ``(D·nb + 1, 8, L)`` blocks (rows p, q, relative log w; kernels along
    L); scale: ``(D, 2)``; query_density: ``(R,)`` each query's density row; pair_query, pair_block:
    ``(P,)`` the pairs. Exact distances and the cut-offs of :meth:`PoseKDE.log_prob`.
    """
    k, _, _ = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p, delta_q)
    return torch.zeros_like(x[:, 0]).index_add(0, pair_query, k.sum(-1))


def block_moments(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                   pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """The mean-shift moments of each query over its (query, block) pairs: ``(R, 8)``, columns
    ``Σ w K``, ``Σ w K μ_p`` (3) and ``Σ w K s μ_q`` (4) with ``s = sign<x_q, μ_q>``; arguments as
    :func:`block_sums`."""
    k, t, dot = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p,
                              delta_q)
    ks = torch.where(dot < 0, -k, k)
    moments = torch.stack([k.sum(-1)] + [(k * t[:, i]).sum(-1) for i in range(3)]
                          + [(ks * t[:, i]).sum(-1) for i in range(3, 7)], -1)  # (P, 8)
    return torch.zeros(x.shape[0], 8, dtype=x.dtype, device=x.device).index_add(0, pair_query, moments)
