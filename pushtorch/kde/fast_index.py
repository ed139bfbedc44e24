"""A density's kernels laid out for the fast path: :class:`FastIndex` (one dense table, or k-d leaf blocks pruned
by the hard cut-offs) and :class:`DescriptorTable` (one density's kernels with their descriptors, one fused pass),
and the annealing steps of a query density fused with its evaluation on those blocks
(:meth:`FastIndex.anneal_blocks`).

Paper, Background → Kernel Density Estimation: the cut-offs make every kernel of Eq. surface_feature_kernel
exactly zero beyond a translation radius and a rotation angle. For a density with many kernels (a query
density: 3,000), kernels are put once into leaf blocks of a k-d tree over (position, rotation); a query visits
only the blocks whose bounding box and rotation cap come within the cut-offs (a bound: nothing that could
survive is skipped) and each visited block is evaluated with the exact distances in one fused pass
(:mod:`pushtorch.kde.kernel_sums`). A density with few kernels (an expert of the product: ~500, most of them
near every candidate) is evaluated in one fused dense pass instead. Sums run in the linear domain relative to
each density's largest weight: a surviving kernel factor is at least e^(−δ_p−δ_q), so nothing underflows
unless weights span ~e^60 (then the dense reference path is used). Query Density: the simulated annealing of
a query density runs its steps on the same blocks.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from pushtorch.kde.annealing import AnnealInputs, AnnealOutcome, chain_state, metropolis_update, propose_from_offsets
from pushtorch.kde.fused import DEFAULT_BLOCK_ELEMENTS, compile_failed, fast_path_compiled, fused_function
from pushtorch.kde.kernel_sums import (
    block_moments,
    block_sums,
    dense_sums,
    descriptor_sums,
    linear_sums_exact,
    reachable_blocks,
)
from pushtorch.se3 import Pose

if TYPE_CHECKING:
    from pushtorch.kde.density import PoseKDE

Tensor = torch.Tensor

__all__ = ["FAST_DENSE_KERNELS", "FAST_LEAF_SIZE", "DescriptorTable", "FastIndex"]

FAST_LEAF_SIZE = 16  # kernels per leaf block: prunes best on the paper-scale query densities (measured)
# Densities with at most this many kernels skip the blocks: pruning cannot pay for its bookkeeping.
FAST_DENSE_KERNELS = 1024
# Relative slack on the pruning bounds: float rounding of a bound must never skip a live kernel.
_BOUND_SLACK = 1e-3
_DENSE_ROW_GROUPS = 4  # at most this many kernel-count groups per dense evaluation (one call each)
# Cost of one more fused call, in kernel evaluations (~100 µs of dispatch against ~0.5 ns per kernel
# and query, measured on CPU): grouping rows only pays when it skips more padding than this.
_CALL_COST_KERNELS = 200_000


def _row_groups(counts: Tensor, queries: int, max_groups: int) -> list[tuple[Tensor | None, int]]:
    """Rows split into groups of similar kernel counts, ``[(rows, width)]``, minimising padded work.

    Candidates are 1 … ``max_groups`` quantile splits of the rows sorted by count; each group is
    evaluated up to its largest count (≥ 1). A single group of every row is ``[(None, width)]``.
    """
    order = torch.argsort(counts, stable=True)
    ordered = [max(1, int(c)) for c in counts[order].tolist()]
    d = len(ordered)
    best, best_cost = [(None, ordered[-1])], _CALL_COST_KERNELS + queries * d * ordered[-1]
    for k in range(2, min(max_groups, d) + 1):
        bounds = sorted({round(d * j / k) for j in range(1, k + 1)})
        groups, start, cost = [], 0, 0
        for end in bounds:
            if end > start:
                groups.append((order[start:end], ordered[end - 1]))
                cost += _CALL_COST_KERNELS + queries * (end - start) * ordered[end - 1]
                start = end
        if cost < best_cost:
            best, best_cost = groups, cost
    return best


def _kd_leaf_order(features: Tensor, valid: Tensor, leaf: int) -> Tensor:
    """Kernel order ``(D, S)`` grouping kernels into leaf blocks of a k-d tree (median splits).

    features: ``(D, N, F)`` split coordinates; valid: ``(D, N)``. ``S = leaf · 2^levels ≥ N``; index
    ``N`` marks padding. Invalid kernels sort last and end up in padding-only blocks where possible.
    """
    d, n, f = features.shape
    levels = max(0, math.ceil(math.log2(max(1.0, n / leaf))))
    size = leaf * 2**levels
    feats = torch.where(valid.unsqueeze(-1), features, torch.full_like(features, math.inf))
    filler = torch.full((d, size - n, f), math.inf, dtype=feats.dtype, device=feats.device)
    feats = torch.cat([feats, filler], 1)
    order = torch.arange(size, device=features.device).expand(d, size).contiguous()
    for level in range(levels):
        nodes = 2**level
        node = torch.gather(feats, 1, order.unsqueeze(-1).expand(-1, -1, f)).reshape(d, nodes, -1, f)
        finite = torch.isfinite(node)
        low = torch.where(finite, node, torch.full_like(node, math.inf)).amin(2)
        high = torch.where(finite, node, torch.full_like(node, -math.inf)).amax(2)
        axis = torch.nan_to_num(high - low, nan=0.0, posinf=0.0, neginf=0.0).argmax(-1)  # (D, nodes)
        values = torch.gather(node, 3, axis[:, :, None, None].expand(-1, -1, node.shape[2], 1)).squeeze(-1)
        split = values.argsort(dim=-1, stable=True)
        order = torch.gather(order.reshape(d, nodes, -1), 2, split).reshape(d, size)
    return torch.where(order < n, order, torch.full_like(order, n))


class FastIndex:
    """A PoseKDE's kernels laid out for the fast path: a dense table or pruned leaf blocks."""

    def __init__(self, kde: PoseKDE, leaf: int = FAST_LEAF_SIZE, blocks: bool | None = None) -> None:
        """Lay out ``kde``'s kernels; ``blocks`` forces leaf blocks (True) or the dense table (False),
        None chooses by size (blocks above ``FAST_DENSE_KERNELS`` kernels)."""
        bw = kde.bandwidth
        dtype, device = kde.dtype, kde.device
        n = kde.num_kernels
        self.batch_shape = kde.batch_shape
        d = max(1, self.batch_shape.numel())
        p = kde.means.p.reshape(d, n, 3)
        q = kde.means.q.reshape(d, n, 4)
        log_w = kde.log_weights.reshape(d, n)
        valid = log_w > -math.inf
        beta = kde.beta.reshape(d, 3).double()
        self.delta_p, self.delta_q, _ = bw.delta
        sp = beta[:, 0] / bw.sigma_p
        kappa = beta[:, 1] / bw.sigma_q
        self.scale = torch.stack([sp, kappa], -1).to(dtype)  # (D, 2)
        self.log_w_max = log_w.amax(-1)  # (D,): every element has a finite weight
        relative = log_w - self.log_w_max.unsqueeze(-1)
        self.linear = linear_sums_exact(relative)
        rows = torch.cat([p, q, relative.unsqueeze(-1)], -1)  # (D, N, 8)
        self.blocks = n > FAST_DENSE_KERNELS if blocks is None else bool(blocks)
        if not self.blocks:
            # Valid kernels first, and rows grouped by how many they hold, so that densities padded to
            # a common N (experts of a product, stacked conditions) are not evaluated on their padding.
            front = torch.argsort((~valid).to(torch.int8), dim=-1, stable=True)
            rows = torch.gather(rows, 1, front.unsqueeze(-1).expand(-1, -1, 8))
            self.table = rows.transpose(1, 2).contiguous()  # (D, 8, N)
            self.counts = valid.sum(-1)
            self.groups: dict[int, list[tuple[Tensor | None, int]]] = {}  # per query count
            return
        # translation reach r (β d_p < δ_p ⇔ |Δp| < r) and rotation reach θ (κ(1−|<q,μ>|) < δ_q)
        reach_p = torch.sqrt(self.delta_p / sp)
        cos_half = 1.0 - self.delta_q / kappa
        reach_q = torch.where(cos_half > -1.0, 2.0 * torch.acos(cos_half.clamp(-1.0, 1.0)),
                              torch.full_like(cos_half, 2 * math.pi))
        self.r2 = (reach_p**2 * (1 + _BOUND_SLACK)).unsqueeze(-1).to(dtype)  # (D, 1); inf: no cut-off
        # split coordinates: the cut-off radii map to one unit (rotation: vector part ≈ θ/2 · axis)
        q_canon = torch.where(q[..., :1] < 0, -q, q).double()
        p_unit = torch.where(torch.isfinite(reach_p), 1.0 / reach_p, torch.zeros_like(reach_p))
        q_unit = torch.where(reach_q < math.pi, 2.0 / reach_q.clamp_min(1e-6), torch.zeros_like(reach_q))
        features = torch.cat([p.double() * p_unit[:, None, None], q_canon[..., 1:] * q_unit[:, None, None]],
                             -1)
        order = _kd_leaf_order(features, valid, leaf)  # (D, S)
        padding = torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -math.inf], dtype=dtype, device=device)
        rows = torch.cat([rows, padding.expand(d, 1, 8)], 1)
        blocks = torch.gather(rows, 1, order.unsqueeze(-1).expand(-1, -1, 8)).reshape(d, -1, leaf, 8)
        self.num_blocks = blocks.shape[1]
        live = blocks[..., 7] > -math.inf  # (D, nb, L)
        bp = blocks[..., 0:3]
        big = torch.finfo(dtype).max
        lo = torch.where(live.unsqueeze(-1), bp, torch.full_like(bp, big)).amin(2)  # (D, nb, 3)
        hi = torch.where(live.unsqueeze(-1), bp, torch.full_like(bp, -big)).amax(2)
        self.lo, self.hi = lo.transpose(1, 2).contiguous(), hi.transpose(1, 2).contiguous()
        bq = blocks[..., 3:7].double()
        aligned = bq * torch.where((bq * bq[:, :, :1]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        centre = (aligned * live.unsqueeze(-1)).sum(2)
        centre = centre / centre.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # (D, nb, 4)
        cos_cap = (bq * centre.unsqueeze(2)).sum(-1).abs().clamp(max=1.0)
        cap = torch.where(live, 2.0 * torch.acos(cos_cap), torch.zeros_like(cos_cap)).amax(-1)  # (D, nb)
        half = (reach_q.unsqueeze(-1) + cap) * (1 + _BOUND_SLACK) / 2 + _BOUND_SLACK
        cos_reach = torch.where(half < math.pi / 2, torch.cos(half.clamp(max=math.pi / 2)),
                                torch.full_like(half, -1.0))
        # an empty block is never reached: |cos| < 2
        self.cos_reach = torch.where(live.any(-1), cos_reach, torch.full_like(cos_reach, 2.0)).to(dtype)
        self.centre = centre.to(dtype).transpose(1, 2).contiguous()
        self.table = torch.cat([blocks.transpose(-1, -2).reshape(-1, 8, leaf),
                                padding[None, :, None].expand(1, 8, leaf)], 0).contiguous()

    def log_prob(self, p: Tensor, q: Tensor) -> Tensor:
        """Log densities of prepared queries ``p (*BB, M, 3)``, ``q (*BB, M, 4)`` → ``(*BB, M)``."""
        x, density, own, batch = self._queries(p, q)
        rows, m = x.shape[:2]
        if m == 0 or rows == 0:
            return torch.empty(*batch, m, dtype=x.dtype, device=x.device)

        def per_query(t: Tensor) -> Tensor:
            return t if own else t[density]

        compiled = fast_path_compiled(x.device)  # compiled code streams; eager code is chunked below
        x_t = x.transpose(1, 2)  # (Q, 7, M)
        if not self.blocks:
            evaluate = fused_function("dense_sums", dense_sums, x.device)
            if own and m not in self.groups:
                self.groups[m] = _row_groups(self.counts, m, _DENSE_ROW_GROUPS)
            groups = self.groups[m] if own else [(None, self.table.shape[-1])]
            total = x.new_empty(rows, m)
            for members, width in groups:
                if members is None:
                    table, scale, xg = per_query(self.table)[..., :width], per_query(self.scale), x_t
                else:
                    table, scale, xg = self.table[members, :, :width], self.scale[members], x_t[members]
                streamed = compiled and not compile_failed("dense_sums")
                step = m if streamed else max(1, DEFAULT_BLOCK_ELEMENTS // max(1, table.shape[0] * width))
                part = torch.cat([evaluate(xg[..., s : s + step], table, scale, self.delta_p, self.delta_q)
                                  for s in range(0, m, step)], -1)
                if members is None:
                    total = part
                else:
                    total[members] = part
        else:
            total = self._pair_sums("block_sums", block_sums, x, density, own, ())
        offset = self.log_w_max[density].unsqueeze(-1)
        return (torch.log(total.reshape(rows, m)) + offset).reshape(*batch, m)

    def _queries(self, p: Tensor, q: Tensor) -> tuple[Tensor, Tensor, bool, torch.Size]:
        """Queries ``(rows, M, 7)``, each row's density index, whether rows are the density's own
        batch, and the broadcast batch shape."""
        batch = torch.broadcast_shapes(p.shape[:-2], self.batch_shape)
        m = p.shape[-2]
        x = torch.cat([p.expand(*batch, m, 3), q.expand(*batch, m, 4)], -1).reshape(-1, m, 7)
        if len(self.batch_shape) == 0:
            density = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        else:
            density = torch.arange(self.batch_shape.numel(), device=x.device).reshape(self.batch_shape)
            density = density.expand(batch).reshape(-1)
        own = tuple(batch) == tuple(self.batch_shape) or (len(self.batch_shape) == 0 and x.shape[0] == 1)
        return x, density, own, batch

    def _pair_sums(self, name: str, fn: Callable, x: Tensor, density: Tensor, own: bool,
                   columns: tuple[int, ...]) -> Tensor:
        """``fn`` (:func:`block_sums` or :func:`block_moments`) summed over the (query, block) pairs
        in reach: ``(rows · M, *columns)``."""
        rows, m = x.shape[:2]
        bounds = [t if own else t[density] for t in (self.lo, self.hi, self.centre, self.cos_reach, self.r2)]
        # compiled reach is ~10x faster with a float result; nonzero is faster on bool
        reach = fused_function("reach", reachable_blocks, x.device)(x.transpose(1, 2), *bounds) > 0
        pair_query, pair_block = reach.reshape(rows * m, self.num_blocks).nonzero(as_tuple=True)
        query_density = density.repeat_interleave(m)
        flat_x = x.reshape(rows * m, 7)
        evaluate = fused_function(name, fn, x.device)
        # eager evaluation materialises (pairs, 8, L): chunk it; compiled code streams it
        streamed = fast_path_compiled(x.device) and not compile_failed(name)
        step = pair_query.numel() if streamed else DEFAULT_BLOCK_ELEMENTS // (8 * self.table.shape[-1])
        total = torch.zeros(rows * m, *columns, dtype=x.dtype, device=x.device)
        for s in range(0, pair_query.numel(), max(1, step)):
            pairs = (pair_query[s : s + step], pair_block[s : s + step])
            total = total + evaluate(flat_x, self.table, self.scale, query_density, *pairs, self.num_blocks,
                                     self.delta_p, self.delta_q)
        return total

    def mean_shift(self, p: Tensor, q: Tensor) -> Pose:
        """:meth:`PoseKDE.mean_shift` of prepared queries over the leaf blocks in reach (block layout)."""
        x, density, own, batch = self._queries(p, q)
        m = x.shape[1]
        if m == 0 or x.shape[0] == 0:
            return Pose.unchecked(p.expand(*batch, m, 3), q.expand(*batch, m, 4))
        moments = self._pair_sums("block_moments", block_moments, x, density, own, (8,)).reshape(*batch, m, 8)
        p, q = p.expand(*batch, m, 3), q.expand(*batch, m, 4)
        alive = moments[..., :1] > 0
        moved_q = moments[..., 4:]
        moved_q = moved_q / moved_q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        return Pose.unchecked(torch.where(alive, moments[..., 1:4] / moments[..., :1].clamp_min(1e-30), p),
                    torch.where(alive, moved_q, q))

    def anneal_blocks(self, inputs: AnnealInputs, start_log_prob: Tensor) -> AnnealOutcome:
        """The annealer's fast steps against this density on its leaf blocks (see
        :mod:`pushtorch.kde.annealing`): each step two fused calls — proposal with block reach, then the pair
        sums with the Metropolis test — around the one data-dependent step, the list of (query, block) pairs,
        instead of four calls and the glue of :meth:`PoseKDE.log_prob`. The start poses must be the
        density's own batch ``(*B, C)``; no history is recorded. Compiled, the pair sums stream; eagerly
        they are not chunked (use :func:`~pushtorch.kde.annealing.anneal_chains` over ``log_prob``)."""
        start = inputs.start
        shape = start.batch_shape
        d, c = max(1, self.batch_shape.numel()), shape[-1]
        device = start.p.device
        propose = fused_function("anneal_propose_and_reach", _propose_and_reach, device)
        accept = fused_function("anneal_block_step_acceptance", _block_step_acceptance, device)
        state = chain_state(start.p.reshape(d, c, 3), start.q.reshape(d, c, 4), start_log_prob.reshape(d, c))
        query_density = torch.arange(d, device=device).repeat_interleave(c)
        log_w_max = self.log_w_max.reshape(d, 1)
        bounds = (self.lo, self.hi, self.centre, self.cos_reach, self.r2)
        for chunk, step_p, left, right, accept_u in inputs.steps:
            step_p, accept_u = step_p.reshape(len(chunk), d, c, 3), accept_u.reshape(len(chunk), d, c)
            left, right = left.reshape(len(chunk), d, c, 4), right.reshape(len(chunk), d, c, 4)
            for k, temperature in enumerate(chunk):
                x, reach = propose(state[0], state[1], step_p[k], left[k], right[k], *bounds)
                pair_query, pair_block = (reach.reshape(d * c, self.num_blocks) > 0).nonzero(as_tuple=True)
                state = accept(*state, x, accept_u[k], inputs.inverse_energy(temperature), self.table, self.scale,
                               query_density, pair_query, pair_block, self.num_blocks, log_w_max, self.delta_p,
                               self.delta_q)
        best = Pose.unchecked(state[3].reshape(*shape, 3), state[4].reshape(*shape, 4))
        return AnnealOutcome(start_log_prob, best, state[5].reshape(shape), state[6])


class DescriptorTable:
    """One density's kernels (batch shape ``()``) with their descriptors, as rows ``(8 + k, N)`` (p, q, log w
    relative to the largest, r) for the fused pass with descriptors (:func:`~pushtorch.kde.kernel_sums.
    descriptor_sums`): every kernel, no pruning, in chunks bounded in memory."""

    def __init__(self, rows: Tensor, top: Tensor, kde: PoseKDE) -> None:
        self.rows, self.top = rows, top
        self.bandwidth, self.beta, self.dtype = kde.bandwidth, kde.beta, kde.dtype

    @staticmethod
    def of(kde: PoseKDE) -> DescriptorTable | None:
        """``kde``'s table; None when its weights cannot be summed in the linear domain."""
        top = kde.log_weights.amax()
        relative = kde.log_weights - top
        rows = torch.cat([kde.means.p, kde.means.q, relative.unsqueeze(-1), kde.descriptors], -1).T.contiguous()
        return DescriptorTable(rows, top, kde) if linear_sums_exact(relative) else None

    def log_prob(self, p: Tensor, q: Tensor, r: Tensor) -> Tensor:
        """Log densities of prepared queries ``p (*B', M, 3)``, ``q (*B', M, 4)``, ``r (*B', M, k)`` →
        ``(*B', M)``, one fused pass per chunk."""
        shape = p.shape[:-1]
        x = torch.cat([p, q, r], -1).reshape(-1, p.shape[-1] + q.shape[-1] + r.shape[-1]).T.contiguous()
        bw = self.bandwidth
        beta = self.beta.double()
        scale = torch.stack([beta[0] / bw.sigma_p, beta[1] / bw.sigma_q, beta[2]]).to(self.dtype)
        r_scale = (1.0 / torch.tensor(bw.sigma_r, dtype=torch.float64)).to(device=x.device, dtype=self.dtype)
        evaluate = fused_function("descriptor_sums", descriptor_sums, x.device)
        step = max(1, DEFAULT_BLOCK_ELEMENTS // self.rows.shape[1])
        total = torch.cat([evaluate(x[:, s : s + step], self.rows, scale, r_scale, *bw.delta)
                           for s in range(0, x.shape[1], step)])
        return (torch.log(total) + self.top).reshape(shape)


def _propose_and_reach(
    p: Tensor, q: Tensor, step_p: Tensor, left: Tensor, right: Tensor,
    lo: Tensor, hi: Tensor, centre: Tensor, cos_reach: Tensor, r2: Tensor,
) -> tuple[Tensor, Tensor]:
    """A step's proposals against a block-pruned density (fused): the proposals as query rows
    ``(D, C, 7)`` and which leaf blocks each may touch ``(D, C, nb)`` (see :func:`reachable_blocks`)."""
    prop_p, prop_q = propose_from_offsets(p, q, step_p, left, right)
    x = torch.cat([prop_p, prop_q], -1)
    return x, reachable_blocks(x.transpose(1, 2), lo, hi, centre, cos_reach, r2)


def _block_step_acceptance(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor, saw_nan: Tensor,
    x: Tensor, u: Tensor, inverse_energy: Tensor, table: Tensor, scale: Tensor, query_density: Tensor,
    pair_query: Tensor, pair_block: Tensor, num_blocks: int, log_w_max: Tensor, delta_p: float, delta_q: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The rest of that step (fused): the proposals' log densities over their (query, block) pairs and the
    Metropolis test. ``log_w_max (D, 1)`` is each density's largest log weight (the table's are relative)."""
    total = block_sums(x.reshape(-1, 7), table, scale, query_density, pair_query, pair_block, num_blocks,
                        delta_p, delta_q)
    prop_lp = torch.log(total.reshape(lp.shape)) + log_w_max
    return metropolis_update(p, q, lp, best_p, best_q, best_lp, x[..., :3], x[..., 3:], prop_lp, u,
                             inverse_energy, saw_nan)
