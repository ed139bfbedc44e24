"""The weighted kernel density over SE(3) (× descriptors), :class:`PoseKDE`: its construction and stacking, its
evaluation by either path (:class:`~pushtorch.kde.Evaluation`), mean shift, trial rounds, sampling, and its own
annealing on the fast path (:meth:`PoseKDE.fused_anneal`).

Paper, Background → Kernel Density Estimation: the kernel of Eq. surface_feature_kernel with its cut-offs and
trial rounds, and the weighted kernel sum of Eq. surface_feature_probability; Query Density: its simulated
annealing. The class holds the kernels and dispatches; the parts live beside it: the dense reference in
:mod:`pushtorch.kde.dense`, query checks and chunks in :mod:`pushtorch.kde.queries`, the fast path in
:mod:`pushtorch.kde.fast_index`, :mod:`pushtorch.kde.kernel_sums` and :mod:`pushtorch.kde.fused`, the textbook
evaluation in :mod:`pushtorch.kde.straightforward`, the trial-round search in :mod:`pushtorch.kde.rounds`, the
draws in :mod:`pushtorch.kde.sampling` and the annealing steps in :mod:`pushtorch.kde.annealing`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.kde.annealing import AnnealInputs, AnnealOutcome, anneal_chains
from pushtorch.kde.bandwidth import KernelBandwidth, TrialRounds, trial_rounds_tensor
from pushtorch.kde.dense import DenseKernels
from pushtorch.kde.fast_index import DescriptorTable, FastIndex
from pushtorch.kde.fused import fast_path_compiled
from pushtorch.kde.method import Evaluation
from pushtorch.kde.queries import prepare_queries, query_chunks
from pushtorch.kde.reductions import logsumexp_last, needs_grad
from pushtorch.kde.rounds import fit_trial_rounds
from pushtorch.kde.sampling import sample_kernel_offsets
from pushtorch.kde.straightforward import straightforward_active, straightforward_log_prob
from pushtorch.se3 import Pose, check_unit_quaternion, multinomial

Tensor = torch.Tensor

__all__ = ["PoseKDE"]

# --------------------------------------------------------------------------------------------------
# The density
# --------------------------------------------------------------------------------------------------


class PoseKDE:
    """A weighted kernel density over SE(3) (× R^k descriptors) with the paper's cut-off kernels.

    ``P(x) ≈ Σ_i w_i K(x | μ_i)`` with ``K = N3(p) Θ(q) N2(r)`` (Eq. surface_feature_kernel, its
    approximations and Eq. surface_feature_probability), batched: the kernel tensors carry leading batch
    dims ``*B`` (e.g. one density per problem, or one per expert of a product of experts) and a kernel dim
    ``N``. Kernels with weight ``-inf`` are padding, so densities with different kernel counts stack
    into one tensor (:meth:`stack`). Trial rounds are per batch element: ``trial_rounds (*B, 3)``.

    Args:
        means: kernel means, a Pose with ``p (*B, N, 3)`` and ``q (*B, N, 4)`` (unit, w,x,y,z).
        bandwidth: the shared :class:`KernelBandwidth`.
        log_weights: ``(*B, N)`` unnormalised log-weights (normalised here with logsumexp over N);
            ``-inf`` marks padding. Default: uniform.
        descriptors: kernel descriptors ``(*B, N, k)``; required iff ``bandwidth.r_std`` is set (k each).
        trial_rounds: initial T, a :class:`TrialRounds` for all batch elements or an int tensor
            ``(*B, 3)``/``(3,)``. Default (0, 0, 0).
        validate_args: check the queries of every call (unit quaternions, finite values). The kernel
            arguments are always checked.

    Raises:
        InvalidPoseError: malformed means.
        InvalidParameterError: shapes that do not match, NaN/+inf weights, a batch element whose weights
            are all ``-inf``, descriptors missing or of the wrong size.

    Example:
        >>> bw = KernelBandwidth(p_std=0.01, rot_std=0.1)
        >>> kde = PoseKDE(Pose(torch.zeros(5, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(5, 4)), bw)
        >>> kde.log_prob(Pose(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(2, 4))).shape
        torch.Size([2])
    """

    def __init__(
        self,
        means: Pose,
        bandwidth: KernelBandwidth,
        log_weights: Tensor | None = None,
        descriptors: Tensor | None = None,
        trial_rounds: TrialRounds | Tensor | None = None,
        validate_args: bool = True,
    ) -> None:
        if not isinstance(bandwidth, KernelBandwidth):
            raise InvalidParameterError(
                f"bandwidth must be a KernelBandwidth, got {type(bandwidth).__name__}"
            )
        p, q = means
        if p.dim() < 2 or p.shape[-1] != 3:
            raise InvalidPoseError(f"kernel means p must have shape (*B, N, 3), got {tuple(p.shape)}")
        if q.dim() < 2 or q.shape[-1] != 4:
            raise InvalidPoseError(f"kernel means q must have shape (*B, N, 4) w,x,y,z, got {tuple(q.shape)}")
        if not p.is_floating_point():
            raise InvalidPoseError(f"kernel means must be floating point, got {p.dtype}")
        if not torch.isfinite(p).all():
            raise InvalidPoseError("kernel means p hold NaN or infinite values")
        check_unit_quaternion(q, name="kernel means q")
        dtype, device = p.dtype, p.device
        q = q.to(dtype)
        shapes = [p.shape[:-1], q.shape[:-1]]
        if log_weights is not None:
            log_weights = torch.as_tensor(log_weights, device=device).to(dtype)
            shapes.append(log_weights.shape)
        if (descriptors is None) != (bandwidth.r_std is None):
            raise InvalidParameterError(
                "kernel descriptors and bandwidth.r_std must be given together"
                f" (descriptors {'missing' if descriptors is None else 'given'},"
                f" r_std {'missing' if bandwidth.r_std is None else 'given'})"
            )
        if descriptors is not None:
            descriptors = torch.as_tensor(descriptors, device=device).to(dtype)
            if descriptors.dim() < 2 or descriptors.shape[-1] != bandwidth.descriptor_dim:
                raise InvalidParameterError(
                    f"kernel descriptors must have shape (*B, N, {bandwidth.descriptor_dim}) to match r_std,"
                    f" got {tuple(descriptors.shape)}"
                )
            if not torch.isfinite(descriptors).all():
                raise InvalidParameterError("kernel descriptors hold NaN or infinite values")
            shapes.append(descriptors.shape[:-1])
        try:
            full = torch.broadcast_shapes(*shapes)
        except RuntimeError as exc:
            raise InvalidParameterError(
                f"kernel tensors do not broadcast to one (*B, N): {[tuple(s) for s in shapes]}"
            ) from exc
        if full[-1] == 0:
            raise InvalidParameterError("a kernel density needs at least one kernel (N = 0)")
        if log_weights is None:
            log_weights = torch.zeros(full, dtype=dtype, device=device)
        if torch.isnan(log_weights).any() or (log_weights == math.inf).any():
            raise InvalidParameterError("kernel log-weights hold NaN or +inf (use -inf for padding)")
        log_weights = log_weights.expand(full)
        total = torch.logsumexp(log_weights, -1, keepdim=True)
        if (total == -math.inf).any():
            raise InvalidParameterError("every kernel weight of some batch element is zero (-inf log-weight)")
        batch = full[:-1]
        self._p = p.expand(*full, 3).contiguous()
        self._q = q.expand(*full, 4).contiguous()
        self._r = None
        if descriptors is not None:
            self._r = descriptors.expand(*full, descriptors.shape[-1]).contiguous()
        self._log_w = (log_weights - total).contiguous()
        self.bandwidth = bandwidth
        self.validate_args = validate_args
        self._trial_rounds = trial_rounds_tensor(trial_rounds, batch, device)
        self._precompute()

    # -- construction helpers ------------------------------------------------------------------

    def _precompute(self) -> None:
        """The bandwidth multipliers β = α_T^(−T) and the kernels scaled for the dense reference."""
        bw = self.bandwidth
        dtype = self._p.dtype
        self._beta = torch.pow(
            torch.tensor(bw.alpha_t, dtype=torch.float64, device=self._p.device), -self._trial_rounds.double()
        ).to(dtype)  # (*B, 3)
        self._dense = DenseKernels.build(self._p, self._q, self._r, self._log_w, self._beta, bw)

    def _replace(self, **changes) -> PoseKDE:
        new = object.__new__(PoseKDE)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        new.__dict__.pop("_fast_index", None)  # built from the old kernels / trial rounds
        new.__dict__.pop("_fast_descriptor_table", None)
        new._precompute()
        return new

    # -- properties ----------------------------------------------------------------------------

    @property
    def means(self) -> Pose:
        """Kernel means, ``p (*B, N, 3)``, ``q (*B, N, 4)``."""
        return Pose.unchecked(self._p, self._q)

    @property
    def descriptors(self) -> Tensor | None:
        """Kernel descriptors ``(*B, N, k)`` or None."""
        return self._r

    @property
    def log_weights(self) -> Tensor:
        """Normalised log-weights ``(*B, N)`` (logsumexp over N is 0; padding is -inf)."""
        return self._log_w

    @property
    def trial_rounds(self) -> Tensor:
        """``(*B, 3)`` int64 trial rounds (T_p, T_q, T_r) of each batch element."""
        return self._trial_rounds

    @property
    def beta(self) -> Tensor:
        """``(*B, 3)`` bandwidth multipliers (β_p, β_q, β_r) = α_T^(−T)."""
        return self._beta

    @property
    def dense_kernels(self) -> DenseKernels:
        """The kernels scaled for the dense reference (:class:`~pushtorch.kde.dense.DenseKernels`, read-only):
        what :meth:`log_prob` evaluates ``method="dense"`` and the trial-round search its chunks with."""
        return self._dense

    @property
    def batch_shape(self) -> torch.Size:
        return self._log_w.shape[:-1]

    @property
    def num_kernels(self) -> int:
        """N, the size of the kernel dim (padding included)."""
        return self._log_w.shape[-1]

    @property
    def descriptor_dim(self) -> int:
        return 0 if self._r is None else self._r.shape[-1]

    @property
    def dtype(self) -> torch.dtype:
        return self._p.dtype

    @property
    def device(self) -> torch.device:
        return self._p.device

    def __repr__(self) -> str:
        return (
            f"PoseKDE(batch_shape={tuple(self.batch_shape)}, num_kernels={self.num_kernels},"
            f" descriptor_dim={self.descriptor_dim}, bandwidth={self.bandwidth})"
        )

    def to(self, *args, **kwargs) -> PoseKDE:
        """Move/cast like ``Tensor.to``; a floating dtype applies to every floating tensor."""
        moved = {
            "_p": self._p.to(*args, **kwargs),
            "_q": self._q.to(*args, **kwargs),
            "_log_w": self._log_w.to(*args, **kwargs),
            "_r": None if self._r is None else self._r.to(*args, **kwargs),
        }
        moved["_trial_rounds"] = self._trial_rounds.to(moved["_p"].device)
        return self._replace(**moved)

    def with_trial_rounds(self, rounds: TrialRounds | Tensor) -> PoseKDE:
        """The same kernels with other trial rounds (a TrialRounds for all, or ``(*B, 3)``/``(3,)``)."""
        return self._replace(_trial_rounds=trial_rounds_tensor(rounds, self.batch_shape, self.device))

    @staticmethod
    def stack(kdes: Sequence[PoseKDE]) -> PoseKDE:
        """Stack densities along a new leading batch dim, padding kernel counts with -inf weights.

        Args:
            kdes: densities with equal bandwidth, batch shape, descriptor dim, dtype and device.

        Returns:
            A PoseKDE of batch shape ``(len(kdes), *B)`` and ``max N`` kernels; each keeps its trial rounds.

        Raises:
            InvalidParameterError: an empty list or densities that differ in any of the above.
        """
        if len(kdes) == 0:
            raise InvalidParameterError("stack needs at least one PoseKDE")
        first = kdes[0]
        for i, k in enumerate(kdes):
            if (k.bandwidth, k.batch_shape, k.descriptor_dim, k.dtype, k.device) != (
                first.bandwidth,
                first.batch_shape,
                first.descriptor_dim,
                first.dtype,
                first.device,
            ):
                raise InvalidParameterError(
                    f"cannot stack PoseKDE {i}: bandwidth, batch shape, descriptor dim, dtype and device"
                    " must match the first one"
                )
        n_max = max(k.num_kernels for k in kdes)

        def pad(t: Tensor, n: int, value: float) -> Tensor:
            extra = n_max - n
            if extra == 0:
                return t
            filler = torch.full((*t.shape[:-2], extra, t.shape[-1]), value, dtype=t.dtype, device=t.device)
            return torch.cat([t, filler], -2)

        p = torch.stack([pad(k.means.p, k.num_kernels, 0.0) for k in kdes])
        q_parts = []
        for k in kdes:
            qk = pad(k.means.q, k.num_kernels, 0.0)
            qk[..., k.num_kernels :, 0] = 1.0
            q_parts.append(qk)
        log_w = torch.stack([pad(k.log_weights.unsqueeze(-1), k.num_kernels, -math.inf).squeeze(-1) for k in kdes])
        r = None if first.descriptors is None else torch.stack([pad(k.descriptors, k.num_kernels, 0.0) for k in kdes])
        return PoseKDE(
            Pose.unchecked(p, torch.stack(q_parts)),
            first.bandwidth,
            log_w,
            r,
            torch.stack([k.trial_rounds for k in kdes]),
            validate_args=first.validate_args,
        )

    # -- evaluation ----------------------------------------------------------------------------

    def log_prob(
        self,
        pose: Pose,
        descriptors: Tensor | None = None,
        chunk_size: int | None = None,
        method: Evaluation | str = Evaluation.DENSE,
    ) -> Tensor:
        """log P(x) = log Σ_i w_i K(x | μ_i) with the hard cut-offs (Eq. surface_feature_probability).

        Args:
            pose: query poses, ``p (*B', M, 3)``, ``q (*B', M, 4)``; ``*B'`` broadcasts with ``batch_shape``.
            descriptors: query descriptors ``(*B', M, k)``; None evaluates the density over SE(3) alone
                (marginal over descriptors, see the module docstring).
            chunk_size: queries per dense ``(chunk, N)`` block; None picks one bounded in memory.
            method: :class:`~pushtorch.kde.Evaluation` or its string: ``"dense"`` (the reference: every
                query against every kernel) or ``"fast"``:
                exact distances evaluated in fused passes (compiled, see :func:`fast_path_compiled`),
                for more than ``FAST_DENSE_KERNELS`` kernels only on the leaf blocks the cut-offs let
                reach a query. Same values up to float rounding; the kernel layout is built on first
                use and cached. Queries with descriptors are fused without pruning (one density, batch
                shape ``()``); weights spanning more than ~e^60, descriptors on a batched density and
                small densities without a compiler take the dense path.

        Returns:
            ``(*broadcast(B, B'), M)`` log densities (unnormalised kernels, ``K(μ|μ) = 1``); ``-inf``
            where every kernel is cut off.

        Raises:
            InvalidPoseError / InvalidParameterError: malformed queries.

        Precision (both paths, any CPU): position and descriptor distances are exact differences, so β d_p
        has a relative error of a few float ulps, and is 0 at a kernel's own mean wherever it lies (checked
        up to 100 m from the origin); the rotation term 1 − |<q, μ>| has an absolute error of ~1.2e-7 · κ
        (κ = β_q / σ_q = 4 β_q / rot_std²), so ``log_prob`` at a kernel's mean is within 1e-3 of its log
        weight for rot_std ≥ 0.025 rad in float32 (use float64 densities for narrower ones).
        """
        method = Evaluation.of(method)
        if method == Evaluation.FAST and descriptors is None:
            index = self.fast_index()
            # uncompiled, the dense reference is as fast as an eager fused pass for small densities
            if index.linear and (index.blocks or fast_path_compiled(self.device)):
                p, q, _ = prepare_queries(self, pose, None)
                return index.log_prob(p, q)
        if method == Evaluation.FAST and descriptors is not None and len(self.batch_shape) == 0:
            table = self._descriptor_table()
            if table is not None:
                p, q, r = prepare_queries(self, pose, descriptors)
                return table.log_prob(p, q, r)
        if straightforward_active():
            return straightforward_log_prob(self, *prepare_queries(self, pose, descriptors))
        inplace = not needs_grad(pose, descriptors)
        out = [
            logsumexp_last(self._dense.log_kernels(p, q, r, with_weights=True, inplace=inplace), inplace)
            for p, q, r in query_chunks(self, pose, descriptors, chunk_size)
        ]
        if not out:  # M = 0
            p, _, _ = prepare_queries(self, pose, descriptors)
            shape = torch.broadcast_shapes(p.shape[:-2], self.batch_shape) + (0,)
            return torch.empty(shape, dtype=self.dtype, device=self.device)
        return torch.cat(out, -1)

    def mean_shift(self, pose: Pose, chunk_size: int | None = None, method: Evaluation | str = Evaluation.DENSE
                   ) -> Pose:
        """One mean-shift step of every query towards a local mode of the density over SE(3).

        With responsibilities ``a_i ∝ w_i K(x | μ_i)`` (cut-offs included) the step is
        ``p ← Σ a_i μ_p,i`` and ``q ← normalise(Σ a_i s_i μ_q,i)``, ``s_i = sign<q, μ_q,i>``: the
        fixed-point equations of a maximum of ``Σ w_i K(x | μ_i)`` (the Gaussian's and the vMF's
        stationarity conditions), so a mode is a fixed point. A query of zero density stays where it is.
        ``method="fast"`` sums the moments over the leaf blocks in reach (large densities only);
        ``"dense"`` forms every query's responsibilities. Poses ``(*B', M)`` → ``(*broadcast, M)``.
        """
        method = Evaluation.of(method)
        if method == Evaluation.FAST and self._r is None:
            index = self.fast_index()
            if index.linear and index.blocks:
                p, q, _ = prepare_queries(self, pose, None)
                return index.mean_shift(p, q)
        new_p, new_q = [], []
        for p, q, _ in query_chunks(self, pose, None, chunk_size):
            logits = self._dense.log_kernels(p, q, None, with_weights=True)  # (*BB, m, N)
            alive = torch.isfinite(logits).any(-1, keepdim=True)
            a = torch.softmax(torch.where(alive, logits, torch.zeros_like(logits)), -1) * alive
            sign = torch.where(q @ self._q.transpose(-1, -2) < 0, -1.0, 1.0).to(a.dtype)
            moved_p = a @ self._p
            moved_q = (a * sign) @ self._q
            moved_q = moved_q / moved_q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
            new_p.append(torch.where(alive, moved_p, p.expand_as(moved_p)))
            new_q.append(torch.where(alive, moved_q, q.expand_as(moved_q)))
        return Pose.unchecked(torch.cat(new_p, -2), torch.cat(new_q, -2))

    def _descriptor_table(self) -> DescriptorTable | None:
        """The fast path's kernel rows with descriptors (:class:`DescriptorTable`; None when the weights cannot
        be summed in the linear domain). Built on first use and cached."""
        if "_fast_descriptor_table" not in self.__dict__:
            self._fast_descriptor_table = DescriptorTable.of(self)
        return self._fast_descriptor_table

    def fast_index(self) -> FastIndex:
        """The fast path's leaf blocks of this density (built on first use, then cached)."""
        index = self.__dict__.get("_fast_index")
        if index is None:
            index = FastIndex(self)
            self._fast_index = index
        return index

    def fused_anneal(self, inputs: AnnealInputs) -> AnnealOutcome:
        """Anneal on the fast path (:class:`~pushtorch.kde.annealing.FusedAnnealing`): over this density's
        fast evaluation, ``log_prob(..., method="fast")``. The poses of its own batch on compiled leaf blocks
        run in steps fused with the evaluation (:meth:`FastIndex.anneal_blocks`); otherwise, or with a
        history, the generic loop (:func:`~pushtorch.kde.annealing.anneal_chains`) — eagerly the fused step
        would not chunk its pair sums in memory as ``log_prob`` does."""
        evaluate = functools.partial(self.log_prob, method=Evaluation.FAST)
        with torch.no_grad():
            start_log_prob = evaluate(inputs.start)
        index = self.fast_index()
        own = inputs.start.batch_shape[:-1] == self.batch_shape
        if (index.blocks and index.linear and own and not inputs.record_history
                and fast_path_compiled(inputs.start.p.device)):
            return index.anneal_blocks(inputs, start_log_prob)
        return anneal_chains(evaluate, inputs, start_log_prob)

    def __call__(self, pose: Pose, descriptors: Tensor | None = None) -> Tensor:
        """Alias of :meth:`log_prob`, so a PoseKDE is itself a ``log_prob_fn`` for annealing."""
        return self.log_prob(pose, descriptors)

    def log_kernels(self, pose: Pose, descriptors: Tensor | None = None) -> Tensor:
        """Per-kernel log K(x | μ_i) (weights not included): dense ``(*BB, M, N)``, -inf at cut-offs.

        Use it for the contact-frame terms of Eq. pdf_motion; memory is ``M × N`` per batch element.
        """
        p, q, r = prepare_queries(self, pose, descriptors)
        return self._dense.log_kernels(p, q, r, with_weights=False)

    def fitted_log_kernels(self, pose: Pose, descriptors: Tensor | None = None) -> tuple[PoseKDE, Tensor]:
        """:meth:`fit_trial_rounds` then :meth:`log_kernels`: ``(fitted density, (*BB, M, N))``.

        The log kernels are computed first; only if some batch element has no surviving (query, kernel)
        pair are the trial rounds fitted and the kernels evaluated again, so the common, covered case
        costs one pass instead of a coverage pass and an evaluation.
        """
        log_k = self.log_kernels(pose, descriptors)
        survivors = torch.isfinite(log_k).any(-1).any(-1).to(torch.int64)  # (*BB)
        if survivors.dim() > len(self.batch_shape):
            survivors = survivors.sum(tuple(range(survivors.dim() - len(self.batch_shape))))
        if bool((survivors.sum_to_size(self.batch_shape) > 0).all()):
            return self, log_k
        fitted = self.fit_trial_rounds(pose, descriptors)
        return fitted, fitted.log_kernels(pose, descriptors)

    def log_kernel_terms(self, pose: Pose, descriptors: Tensor | None = None) -> Tensor:
        """The scaled distances β·d of each factor, dense ``(*BB, M, N, 3)`` in order (p, q, r).

        The r column is 0 when no descriptors take part. A factor is cut off where its value is ≥ the
        matching ``bandwidth.delta``; the trial-round search counts exactly these.
        """
        p, q, r = prepare_queries(self, pose, descriptors)
        bd_p, bd_q, bd_r = self._dense.scaled_terms(p, q, r)
        if bd_r is None:
            bd_r = torch.zeros_like(bd_p)
        return torch.stack(torch.broadcast_tensors(bd_p, bd_q, bd_r), -1)

    # -- trial rounds --------------------------------------------------------------------------

    def fit_trial_rounds(
        self, pose: Pose, descriptors: Tensor | None = None, chunk_size: int | None = None
    ) -> PoseKDE:
        """Widen the kernels by trial rounds until some (query, kernel) pair survives the cut-offs
        (:func:`pushtorch.kde.rounds.fit_trial_rounds`)."""
        return fit_trial_rounds(self, pose, descriptors, chunk_size)

    # -- sampling ------------------------------------------------------------------------------

    def sample_kernels(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """Kernel indices ``(*B, n)`` drawn with probability w_i (padding is never drawn)."""
        if isinstance(n, bool) or int(n) != n or n < 0:
            raise InvalidParameterError(f"number of samples must be an integer >= 0, got {n!r}")
        n = int(n)
        flat = self._log_w.reshape(-1, self.num_kernels).double().exp()
        if n == 0:
            return torch.zeros(*self.batch_shape, 0, dtype=torch.int64, device=self.device)
        idx = multinomial(flat, n, generator)
        return idx.reshape(*self.batch_shape, n)

    def kernel_means(self, index: Tensor) -> Pose:
        """Gather kernel means at ``index (*B, n)`` → Pose ``(*B, n)``."""
        p = torch.gather(self._p, -2, index.unsqueeze(-1).expand(*index.shape, 3))
        q = torch.gather(self._q, -2, index.unsqueeze(-1).expand(*index.shape, 4))
        return Pose.unchecked(p, q)

    def sample(self, n: int, generator: torch.Generator | None = None) -> tuple[Pose, Tensor]:
        """Draw ``n`` poses per batch element from the (cut-off) density over SE(3).

        A kernel is chosen with probability w_i; the translation is the Gaussian of per-axis std
        ``p_std / sqrt(β_p)`` around μ_p and the rotation the vMF pair of concentration
        ``κ = β_q / σ_q`` around μ_q (rotation-vector std ``rot_std / sqrt(β_q)`` per axis), each
        truncated at its cut-off exactly as :meth:`log_prob` evaluates it — every sample has a finite
        log-density (up to float rounding on the cut-off boundary itself). All kernels share bandwidth
        and cut-offs, so this samples exactly the normalised density. Descriptors are not sampled
        (gather ``descriptors`` with the returned indices if needed).

        Args:
            n: samples per batch element; generator: a seeded torch.Generator for reproducibility.

        Returns:
            ``(Pose (*B, n), kernel index (*B, n))``; quaternions are on the kernel mean's hemisphere.
        """
        index = self.sample_kernels(n, generator)
        mean = self.kernel_means(index)
        delta_p, delta_q, _ = self.bandwidth.delta
        beta = self._beta.double().unsqueeze(-2).expand(*index.shape, 3)
        std = self.bandwidth.p_std / torch.sqrt(beta[..., 0])
        offset, around_identity = sample_kernel_offsets(std, beta[..., 1] / self.bandwidth.sigma_q, delta_p, delta_q,
                                                        generator)
        p = mean.p + offset.to(self.dtype)
        q = pkt.quaternion_raw_multiply(mean.q.double(), around_identity)
        q = q / q.norm(dim=-1, keepdim=True)
        return Pose.unchecked(p, q.to(self.dtype)), index
