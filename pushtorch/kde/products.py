"""The product of experts in log space: :func:`product_log_prob` / :class:`ProductOfExperts` over stacked
densities, and :class:`SharedKernelProduct` for experts that weigh one shared set of kernels (the motion model's
fast path), which anneals itself in steps fused with its evaluation (:meth:`SharedKernelProduct.fused_anneal`).

Paper, Background → Kernel Density Estimation: the product of experts (Eq. poe) over kernel densities of Eq.
surface_feature_probability; Motion Model: its simulated annealing.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.kde.annealing import AnnealInputs, AnnealOutcome, chain_state, metropolis_update, propose_from_offsets
from pushtorch.kde.bandwidth import KernelBandwidth, TrialRounds, trial_rounds_tensor
from pushtorch.kde.density import PoseKDE
from pushtorch.kde.fused import DEFAULT_BLOCK_ELEMENTS, chunk_bounds, fused_function
from pushtorch.kde.kernel_sums import pose_distances
from pushtorch.kde.method import Evaluation
from pushtorch.se3 import Pose, check_unit_quaternion

Tensor = torch.Tensor

# --------------------------------------------------------------------------------------------------
# Product of experts
# --------------------------------------------------------------------------------------------------


def product_log_prob(
    experts: PoseKDE,
    pose: Pose,
    expert_log_weight: Tensor | None = None,
    expert_mask: Tensor | None = None,
    chunk_size: int | None = None,
    method: Evaluation | str = Evaluation.DENSE,
    expert_exponent: Tensor | None = None,
) -> Tensor:
    """log of the product of experts, Σ_e (log w^P_e + γ_e log P_e(m)) (Eq. poe in log space, each expert
    raised to the power ``γ_e``; the paper's product has every ``γ_e = 1``).

    Args:
        experts: one PoseKDE whose leading batch dim is the expert dim E: batch shape ``(E, *B)``
            (stack densities with different kernel counts using :meth:`PoseKDE.stack`).
        pose: query poses ``(*B', M)`` with ``*B'`` broadcastable to ``*B`` (no expert dim).
        expert_log_weight: log w^P_e, shape ``(E,)`` or ``(E, *B)``; default 0 (w^P = 1).
        expert_mask: bool ``(E,)`` or ``(E, *B)``; False marks a padding expert that contributes nothing
            (so problems with different expert counts stack). Default: all experts count.
        chunk_size, method: as :meth:`PoseKDE.log_prob` (``"fast"`` prunes and fuses every expert).
        expert_exponent: ``γ_e >= 0``, shape ``(E,)`` or ``(E, *B)``; default 1. An expert with ``γ_e = 0``
            contributes nothing (not even a veto).

    Returns:
        ``(*broadcast(B, B'), M)``; ``-inf`` where any counted expert vetoes the pose (density 0).

    Raises:
        InvalidParameterError: experts without a batch dim, misshaped weights/mask, or a pose with more
            batch dims than the experts.
    """
    if len(experts.batch_shape) == 0:
        raise InvalidParameterError("experts must have a leading expert batch dim, got batch shape ()")
    inner = len(experts.batch_shape) - 1
    query_batch = pose.batch_shape[:-1] if len(pose.batch_shape) else pose.batch_shape
    if len(query_batch) > inner:
        raise InvalidParameterError(
            f"query batch dims {tuple(query_batch)} exceed the experts' batch dims"
            f" {tuple(experts.batch_shape[1:])} (the expert dim must not appear in the queries)"
        )
    # Batch dims align from the right, so queries with at most len(B) batch dims meet (E, *B) as (*B).
    per_expert = experts.log_prob(pose, chunk_size=chunk_size, method=method)  # (E, *BB, M)
    n_experts, batch = experts.batch_shape[0], experts.batch_shape[1:]
    dtype, device = per_expert.dtype, per_expert.device
    exponent = _expert_exponents(expert_exponent, expert_mask, n_experts, batch, dtype, device).unsqueeze(-1)
    per_expert = torch.where(exponent > 0, exponent * per_expert, torch.zeros_like(per_expert))
    if expert_log_weight is not None:
        log_wp = _per_expert(expert_log_weight, "expert_log_weight", n_experts, batch, dtype, device, 0.0)
        per_expert = per_expert + torch.where(exponent > 0, log_wp.unsqueeze(-1), torch.zeros_like(exponent))
    return per_expert.sum(0)


def _expert_exponents(expert_exponent, expert_mask, n_experts: int, batch: torch.Size, dtype, device) -> Tensor:
    """``(E, *B)`` the experts' exponents ``γ_e``, 0 where the mask leaves an expert out.

    Raises:
        InvalidParameterError: a negative exponent, or a misshaped exponent or mask.
    """
    exponent = _per_expert(expert_exponent, "expert_exponent", n_experts, batch, dtype, device, 1.0)
    if (exponent < 0).any():
        raise InvalidParameterError(f"expert_exponent must be >= 0, got {exponent.min().item()}")
    mask = _per_expert(expert_mask, "expert_mask", n_experts, batch, torch.bool, device, True)
    return torch.where(mask, exponent, torch.zeros_like(exponent))


class ProductOfExperts:
    """The density of Eq. poe as an object: ``log_prob(pose)`` sums the experts' log densities.

    Args: as :func:`product_log_prob`. Callable, so it can be handed to :func:`pushtorch.anneal.anneal`.
    """

    def __init__(
        self,
        experts: PoseKDE,
        expert_log_weight: Tensor | None = None,
        expert_mask: Tensor | None = None,
        expert_exponent: Tensor | None = None,
    ) -> None:
        if len(experts.batch_shape) == 0:
            raise InvalidParameterError("experts must have a leading expert batch dim, got batch shape ()")
        self.experts = experts
        self.expert_log_weight = expert_log_weight
        self.expert_mask = expert_mask
        self.expert_exponent = expert_exponent

    @property
    def batch_shape(self) -> torch.Size:
        return self.experts.batch_shape[1:]

    @property
    def num_experts(self) -> int:
        return self.experts.batch_shape[0]

    def log_prob(self, pose: Pose, chunk_size: int | None = None, method: Evaluation | str = Evaluation.DENSE
                 ) -> Tensor:
        """Σ_e (log w^P_e + γ_e log P_e(pose)), see :func:`product_log_prob`."""
        return product_log_prob(
            self.experts, pose, self.expert_log_weight, self.expert_mask, chunk_size, method, self.expert_exponent
        )

    def __call__(self, pose: Pose) -> Tensor:
        return self.log_prob(pose)


def _per_expert(value, name: str, n_experts: int, batch: torch.Size, dtype, device, default) -> Tensor:
    """Per-expert weights or mask, ``(E,)`` or ``(E, *B)`` (size-1 dims broadcast) → ``(E, *B)``;
    None → ``default`` everywhere. Refuses a mask that is not boolean, weights that are, and NaN or +inf
    weights (−inf is an expert that vetoes everything)."""
    if value is None:
        return torch.full((n_experts, *batch), default, dtype=dtype, device=device)
    t = torch.as_tensor(value, device=device)
    if t.dtype != dtype and (dtype == torch.bool or t.dtype == torch.bool):
        raise InvalidParameterError(f"{name} must be {'boolean' if dtype == torch.bool else 'floating'}, got {t.dtype}")
    t = t.to(dtype)
    if dtype != torch.bool and (torch.isnan(t).any() or (t == math.inf).any()):
        raise InvalidParameterError(f"{name} holds NaN or +inf")
    wrong = InvalidParameterError(f"{name} must have shape ({n_experts},) or {(n_experts, *batch)} "
                                  f"(experts first), got {tuple(t.shape)}")
    # experts first and never broadcast into: a (B,) tensor must not pass for per-expert values
    if t.dim() == 0 or t.dim() > len(batch) + 1 or t.shape[0] != n_experts:
        raise wrong
    t = t.reshape(*t.shape, *([1] * (len(batch) + 1 - t.dim())))
    try:
        return t.expand(n_experts, *batch)
    except RuntimeError as exc:
        raise wrong from exc


def _shared_kernels(x: Tensor, table: Tensor, scale: Tensor, delta_p: float, delta_q: float
                    ) -> tuple[Tensor, Tensor]:
    """``K(x | μ_k)`` with the cut-offs ``(B, K, M)`` and the quaternion dot products ``(B, K, M)``;
    arguments as :func:`_shared_kernel_product`."""
    xs = x.unsqueeze(1)  # (B, 1, 7, M)
    t = table.unsqueeze(-1)  # (B, K, 7, 1)
    sc = scale[:, None, :, None]  # (B, 1, 2, 1)
    d_p, dot, d_q = pose_distances(xs.unbind(2), t.unbind(2), sc[:, :, 0], sc[:, :, 1])
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(-d_p - d_q), torch.zeros_like(d_p)), dot


def _shared_kernel_product(x: Tensor, table: Tensor, weights: Tensor, scale: Tensor, offset: Tensor,
                           exponent: Tensor, delta_p: float, delta_q: float) -> Tensor:
    """Σ_e γ_e log Σ_k w_ek K(x | μ_k) + offset_e over the counted experts (``γ_e > 0``): ``(B, M)`` (fused).

    x: queries ``(B, 7, M)`` (rows p, q); table: shared kernels ``(B, K, 7)``; weights ``(B, E, K)``
    linear, relative to each expert's largest; scale ``(B, 2)`` (β_p/σ_p, β_q/σ_q); offset ``(B, E, 1)``
    (log w^P_e plus γ_e times the expert's largest log weight); exponent ``(B, E, 1)`` (0: a padding
    expert). Exact distances and the
    cut-offs of :meth:`PoseKDE.log_prob`; one kernel evaluation serves every expert through one matmul,
    laid out ``(E, K) @ (K, M)`` (with few experts ~4× faster than ``(M, K) @ (K, E)``, measured).
    """
    kernels, _ = _shared_kernels(x, table, scale, delta_p, delta_q)
    sums = torch.bmm(weights, kernels)  # (B, E, M)
    # log of a zero sum is -inf; taken of 1 instead and masked, so its gradient is 0, not 0 · inf = NaN
    reached = sums > 0
    log_sums = torch.where(reached, torch.log(torch.where(reached, sums, torch.ones_like(sums))), -math.inf)
    per_expert = exponent * log_sums + offset
    return torch.where(exponent > 0, per_expert, torch.zeros_like(per_expert)).sum(1)


def _shared_kernel_shift(x: Tensor, table: Tensor, weights: Tensor, scale: Tensor, exponent: Tensor,
                         delta_p: float, delta_q: float) -> Tensor:
    """One mean-shift step of the product of experts for queries ``x (B, 7, M)`` → ``(B, 7, M)``
    (fused); arguments as :func:`_shared_kernel_product`.

    With every kernel on one bandwidth, the stationarity conditions of ``Σ_e γ_e log P_e`` weigh kernel
    ``k`` by ``a_k = K_k Σ_e γ_e w_ek / P_e``: ``p ← Σ a_k μ_p,k / Σ a_k``, ``q ← normalise(Σ a_k s_k μ_q,k)``.
    A query where a counted expert is zero (the product is) stays.
    """
    kernels, dot = _shared_kernels(x, table, scale, delta_p, delta_q)
    sums = torch.bmm(weights, kernels)  # (B, E, M)
    counted = exponent > 0
    alive = ((sums > 0) | ~counted).all(1, keepdim=True)  # (B, 1, M)
    inverse = torch.where(counted & (sums > 0), exponent / sums.clamp_min(1e-30), torch.zeros_like(sums))
    a = torch.bmm(weights.transpose(1, 2), inverse) * kernels  # (B, K, M)
    moved_p = torch.bmm(table[:, :, :3].transpose(1, 2), a) / a.sum(1, keepdim=True).clamp_min(1e-30)
    moved_q = torch.bmm(table[:, :, 3:].transpose(1, 2), torch.where(dot < 0, -a, a))
    moved_q = moved_q / moved_q.norm(dim=1, keepdim=True).clamp_min(1e-30)
    return torch.where(alive, torch.cat([moved_p, moved_q], 1), x)


class SharedKernelProduct:
    """A product of experts (Eq. poe) whose experts weigh one shared set of kernels differently.

    Expert ``e`` is ``P_e(x) = Σ_k w_ek K(x | μ_k)`` over kernels ``μ`` shared by every expert, and the
    product is ``Σ_e (log w^P_e + γ_e log P_e(x))``. Where experts share their kernel means — the motion
    model's environment experts all transfer the same training motions and differ only in their contact
    weights — the kernels are evaluated once per query and a ``(K × E)`` matmul gives every expert's sum,
    instead of one evaluation per expert. Values equal :class:`ProductOfExperts` over the same experts
    up to float rounding, except that a weight below float precision relative to its expert's largest
    (``e^-87`` in float32) counts as zero.

    Args:
        means: shared kernel means ``p (*B, K, 3)``, ``q (*B, K, 4)``.
        log_weights: ``(E, *B, K)`` each expert's log weights (``-inf``: the kernel is not in it);
            each expert's row is normalised like :class:`PoseKDE`'s.
        bandwidth: kernel bandwidth (no descriptors) shared by every expert.
        trial_rounds: ``(*B, 3)`` or ``(3,)``, the same for every expert of a problem.
        expert_log_weight, expert_mask, expert_exponent: as :func:`product_log_prob`, shape ``(E,)`` or
            ``(E, *B)``.
        validate_args: check the queries of every call as :class:`PoseKDE` does (finite, unit
            quaternions, shapes); the annealing turns it off for its own normalised proposals.

    Raises:
        InvalidParameterError: misshaped tensors, descriptor dims in the bandwidth, or a counted expert
            without a kernel.
    """

    def __init__(
        self,
        means: Pose,
        log_weights: Tensor,
        bandwidth: KernelBandwidth,
        trial_rounds: TrialRounds | Tensor | None = None,
        expert_log_weight: Tensor | None = None,
        expert_mask: Tensor | None = None,
        validate_args: bool = True,
        expert_exponent: Tensor | None = None,
    ) -> None:
        if bandwidth.descriptor_dim:
            raise InvalidParameterError("a shared-kernel product is over SE(3) alone: no descriptor stds")
        self.validate_args = validate_args
        batch = means.batch_shape[:-1]
        if log_weights.dim() < 2 or log_weights.shape[1:] != means.batch_shape:
            raise InvalidParameterError(
                f"log_weights must have shape (E, {', '.join(map(str, means.batch_shape))}), "
                f"got {tuple(log_weights.shape)}"
            )
        n_experts = log_weights.shape[0]
        dtype, device = means.p.dtype, means.p.device
        if torch.isnan(log_weights).any() or (log_weights == math.inf).any():
            raise InvalidParameterError("log_weights hold NaN or +inf (use -inf for a kernel outside an expert)")
        exponent = _expert_exponents(expert_exponent, expert_mask, n_experts, batch, dtype, device)
        mask = exponent > 0
        log_wp = _per_expert(expert_log_weight, "expert_log_weight", n_experts, batch, dtype, device, 0.0)
        total = torch.logsumexp(log_weights, -1)  # (E, *B)
        empty = total == -math.inf
        if (empty & mask).any():
            raise InvalidParameterError("a counted expert has no kernel with non-zero weight")
        top = log_weights.amax(-1)
        relative = log_weights - torch.where(empty, torch.zeros_like(top), top).unsqueeze(-1)
        # log P_e = log Σ_k e^relative_k K_k + (largest − logsumexp): each row normalised as PoseKDE's
        offset = exponent * torch.where(empty, torch.zeros_like(top), top - total) + log_wp
        d, k = max(1, batch.numel()), means.batch_shape[-1]
        self.batch_shape = batch
        self.num_experts = n_experts
        self.bandwidth = bandwidth
        self.rounds = trial_rounds_tensor(trial_rounds, batch, device)
        beta = torch.pow(torch.tensor(bandwidth.alpha_t, dtype=torch.float64), -self.rounds.double()).reshape(d, 3)
        self.scale = torch.stack([beta[:, 0] / bandwidth.sigma_p, beta[:, 1] / bandwidth.sigma_q], -1).to(dtype)
        self.table = torch.cat([means.p, means.q], -1).reshape(d, k, 7).contiguous()  # (D, K, 7)
        self.weights = relative.exp().reshape(n_experts, d, k).transpose(0, 1).contiguous()  # (D, E, K)
        self.offset = offset.reshape(n_experts, d, 1).transpose(0, 1).contiguous()  # (D, E, 1)
        self.exponent = exponent.reshape(n_experts, d, 1).transpose(0, 1).contiguous()  # (D, E, 1), 0: left out
        self.delta_p, self.delta_q, _ = bandwidth.delta
        # each problem's kernels up to its last weighted one: past it a stacked batch holds only padding
        weighted = (self.weights > 0).any(1) * torch.arange(1, k + 1, device=device)  # (D, K)
        self.kernel_counts: list[int] = weighted.amax(-1).tolist() if k else [0] * d
        self._chunk_layouts: dict[tuple[int, int], tuple[Tensor, ...]] = {}

    def log_prob(self, pose: Pose) -> Tensor:
        """``Σ_e (log w^P_e + γ_e log P_e(pose))`` for poses ``(*B, M)`` → ``(*B, M)``; ``-inf`` where a counted
        expert has no kernel within its cut-offs.

        Raises:
            InvalidPoseError: (``validate_args``) misshaped, non-finite or non-unit queries.
        """
        self._check_queries(pose)
        out = self._per_problem("shared_kernel_product", _shared_kernel_product, pose, with_offset=True)
        return out.reshape(*self.batch_shape, pose.p.shape[-2])

    def mean_shift(self, pose: Pose) -> Pose:
        """One mean-shift step of every query towards a local mode of the product (see
        :meth:`PoseKDE.mean_shift`; the experts' weights w^P do not move a mode): poses ``(*B, M)``."""
        self._check_queries(pose)
        out = self._per_problem("shared_kernel_shift", _shared_kernel_shift, pose, with_offset=False)
        out = out.transpose(1, 2).reshape(*self.batch_shape, pose.p.shape[-2], 7)
        return Pose.unchecked(out[..., :3], out[..., 3:])

    def _check_queries(self, pose: Pose) -> None:
        """The checks :meth:`PoseKDE.log_prob` makes of its queries (when ``validate_args``)."""
        if not self.validate_args:
            return
        p, q = pose
        if p.dim() < 1 or p.shape[-1] != 3 or q.dim() < 1 or q.shape[-1] != 4:
            raise InvalidPoseError(
                f"query poses need p (..., M, 3) and q (..., M, 4); got {tuple(p.shape)} and {tuple(q.shape)}"
            )
        try:
            torch.broadcast_shapes(p.shape[:-1], q.shape[:-1], (*self.batch_shape, 1))
        except RuntimeError as exc:
            raise InvalidPoseError(
                f"query poses p {tuple(p.shape)}, q {tuple(q.shape)} do not fit the batch shape"
                f" {tuple(self.batch_shape)} (queries are (*B, M))"
            ) from exc
        if not torch.isfinite(p).all():
            raise InvalidPoseError("query positions hold NaN or infinite values")
        check_unit_quaternion(q, name="query q")

    def _per_problem(self, name: str, fn: Callable, pose: Pose, with_offset: bool) -> Tensor:
        """``fn`` (fused) over the queries ``(D, 7, M)`` and each chunk's :meth:`chunk_layout` (without the
        offsets unless ``with_offset``), in chunks of problems that keep the ``(problems × K × M)`` kernel
        values cache-sized (~8 MB)."""
        d, m = self.table.shape[0], pose.p.shape[-2]
        x = torch.cat([pose.p, pose.q], -1).expand(*self.batch_shape, m, 7).reshape(d, m, 7)
        x = x.transpose(1, 2).contiguous()  # (D, 7, M): a strided view compiles ~6x slower (measured)
        evaluate = fused_function(name, fn, x.device)
        out = []
        for a, b in self.problem_chunks(m):
            layout = self.chunk_layout(a, b)
            if not with_offset:  # the mean shift does not take the offsets
                layout = layout[:3] + layout[4:]
            out.append(evaluate(x[a:b], *layout, self.delta_p, self.delta_q))
        return torch.cat(out, 0)

    def chunk_layout(self, start: int, end: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The table, weights, scale, offset and exponent of problems ``[start, end)``, their kernels cut
        after the chunk's last weighted one: problems of a stacked batch are padded to the batch's largest
        kernel count (1.4x the mean at the paper's sizes, measured), a chunk evaluates its own. Cut once per
        chunk: the annealing's steps, polish and scoring evaluate the same chunks again and again."""
        if (start, end) not in self._chunk_layouts:
            table, weights = self.table[start:end], self.weights[start:end]
            kept = max(1, max(self.kernel_counts[start:end]))
            if kept < table.shape[1]:  # contiguous: a strided slice would fail the compiled call's stride guard
                table, weights = table[:, :kept].contiguous(), weights[..., :kept].contiguous()
            self._chunk_layouts[start, end] = (table, weights, self.scale[start:end], self.offset[start:end],
                                               self.exponent[start:end])
        return self._chunk_layouts[start, end]  # type: ignore[return-value]

    def problem_chunks(self, queries: int) -> list[tuple[int, int]]:
        """``[start, end)`` chunks of the flattened problems whose ``(problems × K × queries)`` kernel values
        stay cache-sized (~8 MB) when each problem has ``queries`` queries."""
        step = max(1, DEFAULT_BLOCK_ELEMENTS // max(1, queries * self.table.shape[1]))
        return chunk_bounds(self.table.shape[0], step)

    def fused_anneal(self, inputs: AnnealInputs) -> AnnealOutcome | None:
        """Anneal on the fast path (:class:`~pushtorch.kde.annealing.FusedAnnealing`): each step — proposal,
        the product's log-likelihood and the Metropolis test — one fused call per cache-sized chunk of
        problems (:meth:`problem_chunks`), the same values as the generic loop over :meth:`log_prob`. None
        (nothing drawn) for poses that are not this product's own batch ``(*B, C)`` or with a history."""
        start = inputs.start
        shape = start.batch_shape
        if inputs.record_history or shape[:-1] != self.batch_shape:
            return None
        with torch.no_grad():
            start_log_prob = self.log_prob(start)
        d, c = self.table.shape[0], shape[-1]
        step = fused_function("anneal_shared_product_step", _shared_product_step, start.p.device)
        chunks = self.problem_chunks(c)
        layouts = [self.chunk_layout(a, b) for a, b in chunks]

        def rows(t: Tensor, width: int) -> Tensor:  # (…, D·C, width) → (…, D, width, C), contiguous
            return t.reshape(*t.shape[: t.dim() - len(shape) - 1], d, c, width).transpose(-1, -2).contiguous()

        states = []
        for a, b in chunks:
            p, q, lp = rows(start.p, 3)[a:b], rows(start.q, 4)[a:b], start_log_prob.reshape(d, c)[a:b]
            states.append(chain_state(p, q, lp))
        for chunk, step_p, left, right, accept_u in inputs.steps:
            step_p, left, right = rows(step_p, 3), rows(left, 4), rows(right, 4)
            accept_u = accept_u.reshape(len(chunk), d, c)
            inverse_energy = [inputs.inverse_energy(t) for t in chunk]
            for i, (a, b) in enumerate(chunks):
                state = states[i]
                for k in range(len(chunk)):
                    state = step(*state, step_p[k, a:b], left[k, a:b], right[k, a:b], accept_u[k, a:b],
                                 inverse_energy[k], *layouts[i], self.delta_p, self.delta_q)
                states[i] = state
        best_p = torch.cat([s[3] for s in states]).transpose(1, 2).reshape(*shape, 3)
        best_q = torch.cat([s[4] for s in states]).transpose(1, 2).reshape(*shape, 4)
        best_lp = torch.cat([s[5] for s in states]).reshape(shape)
        saw_nan = torch.stack([s[6] for s in states]).any()
        return AnnealOutcome(start_log_prob, Pose.unchecked(best_p, best_q), best_lp, saw_nan)

    def __call__(self, pose: Pose) -> Tensor:
        return self.log_prob(pose)


def _shared_product_step(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor, saw_nan: Tensor,
    step_p: Tensor, left: Tensor, right: Tensor, u: Tensor, inverse_energy: Tensor,
    table: Tensor, weights: Tensor, scale: Tensor, offset: Tensor, exponent: Tensor, delta_p: float, delta_q: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A whole annealing step against a :class:`SharedKernelProduct`'s problems: proposal, the product's
    log-likelihood and the Metropolis test in one fused call (one compiled call per step instead of three,
    and none of the eager glue between them).

    Poses and offsets are rows, ``p (D, 3, C)``, ``q``, ``left``, ``right (D, 4, C)``; ``lp``, ``u (D, C)``:
    the compiled kernel loop then reads every query component at unit stride and vectorises (laid out
    ``(D, C, 7)`` it ran scalar and the fused step was 2.7x slower than three calls, measured). Other
    arguments as :func:`~pushtorch.kde.annealing.metropolis_update` and :func:`_shared_kernel_product`.
    """
    prop_p, prop_q = propose_from_offsets(p, q, step_p, left, right, component_dim=-2)
    prop_lp = _shared_kernel_product(torch.cat([prop_p, prop_q], 1), table, weights, scale, offset, exponent,
                                     delta_p, delta_q)
    p, q, lp, best_p, best_q, best_lp, saw_nan = metropolis_update(
        p, q, lp, best_p, best_q, best_lp, prop_p, prop_q, prop_lp, u, inverse_energy, saw_nan, component_dim=-2)
    # rows out as rows in: an input laid out otherwise fails the compiled step's stride guard and recompiles
    return p.contiguous(), q.contiguous(), lp, best_p.contiguous(), best_q.contiguous(), best_lp, saw_nan

