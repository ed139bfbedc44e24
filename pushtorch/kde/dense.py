"""The dense reference evaluation of a kernel density: :class:`DenseKernels`, a density's kernels scaled once so
that every chunk of queries needs one pass per factor (exact differences for positions and descriptors, one
matmul for the quaternion dot), and the cut-off log kernels of such a chunk.

Paper, Background → Kernel Density Estimation: the distances d_p, d_q, d_r of the kernel of Eq.
surface_feature_kernel scaled by the bandwidth multipliers β = α_T^(−T), the cut-offs ``β d < δ`` and the terms
``log(w_i K(x | μ_i))`` of the weighted sum of Eq. surface_feature_probability. It is the reference the fast
path agrees with: :class:`~pushtorch.kde.PoseKDE` evaluates ``method="dense"``, its dense mean shift, its log
kernels and the trial-round search (:mod:`pushtorch.kde.rounds`) with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pushtorch.kde.bandwidth import KernelBandwidth
from pushtorch.kde.reductions import neg_scaled_squared_distances

Tensor = torch.Tensor

__all__ = ["DenseKernels"]


@dataclass(frozen=True, eq=False)
class DenseKernels:
    """A density's kernels scaled for the dense reference (built by :meth:`build`; read-only).

    Positions and descriptors are centred on the weighted kernel mean, so the differences are taken between
    small numbers, exact for kernels and queries far from the origin (float32 resolves 8 µm at 100 m, not
    below), and carry ``√(β/σ)``, so the distance of scaled positions is ``β d`` directly.

    Attributes:
        log_w: normalised log-weights ``(*B, N)`` (padding ``-inf``).
        delta: the cut-offs ``(δ_p, δ_q, δ_r)``.
        p_centre: the weighted kernel mean ``(*B, 1, 3)``; p_root_scale: ``√(β_p/σ_p)`` ``(*B, 1, 1)``;
            p_scaled: the centred, scaled kernel positions ``(*B, N, 3)``.
        kappa: ``κ = β_q/σ_q`` ``(*B, 1, 1)``; q_kappa_t: ``κ μ_q`` transposed ``(*B, 4, N)``.
        r_inv_sqrt_sigma, r_centre, r_root_scale, r_scaled: the same for descriptors (``1/√σ_r`` ``(k,)``,
            ``√β_r``); None without descriptors.
    """

    log_w: Tensor
    delta: tuple[float, float, float]
    p_centre: Tensor
    p_root_scale: Tensor
    p_scaled: Tensor
    kappa: Tensor
    q_kappa_t: Tensor
    r_inv_sqrt_sigma: Tensor | None = None
    r_centre: Tensor | None = None
    r_root_scale: Tensor | None = None
    r_scaled: Tensor | None = None

    @staticmethod
    def build(p: Tensor, q: Tensor, r: Tensor | None, log_w: Tensor, beta: Tensor, bandwidth: KernelBandwidth
              ) -> DenseKernels:
        """Scaled kernel matrices of kernels ``p (*B, N, 3)``, ``q (*B, N, 4)``, ``r (*B, N, k)`` or None,
        weights ``log_w (*B, N)`` and multipliers ``beta (*B, 3)``, so that every chunk needs one matmul per
        factor."""
        bw = bandwidth
        dtype = p.dtype
        weights = log_w.exp().unsqueeze(-1)  # padding kernels get 0 weight in the centre
        p_centre = (weights * p).sum(-2, keepdim=True)
        p_root_scale = (beta[..., 0] / bw.sigma_p).sqrt()[..., None, None]  # (*B, 1, 1)
        p_scaled = ((p - p_centre) * p_root_scale).contiguous()
        kappa = (beta[..., 1] / bw.sigma_q)[..., None, None]  # κ = β_q / σ_q, (*B, 1, 1)
        q_kappa_t = (q * kappa).transpose(-1, -2).contiguous()
        if r is None:
            return DenseKernels(log_w, bw.delta, p_centre, p_root_scale, p_scaled, kappa, q_kappa_t)
        sigma_r = torch.tensor(bw.sigma_r, dtype=torch.float64)
        inv_sqrt_sigma = sigma_r.rsqrt().to(dtype=dtype, device=r.device)
        r_centre = (weights * r).sum(-2, keepdim=True)
        r_root_scale = beta[..., 2].sqrt()[..., None, None]
        r_scaled = ((r - r_centre) * inv_sqrt_sigma * r_root_scale).contiguous()
        return DenseKernels(log_w, bw.delta, p_centre, p_root_scale, p_scaled, kappa, q_kappa_t, inv_sqrt_sigma,
                            r_centre, r_root_scale, r_scaled)

    def neg_terms(self, p: Tensor, q: Tensor, r: Tensor | None, inplace: bool = True
                  ) -> tuple[Tensor, Tensor, Tensor | None]:
        """−β·d of each factor for a chunk of queries: ``(*BB, m, N)`` tensors (r: None if unused).

        One pass per factor (exact differences for positions and descriptors, one matmul for the quaternion
        dot) plus in-place element-wise passes: this is the hot path of every density evaluation, so it
        avoids boolean masks and ``where`` (several times slower on CPU). ``inplace=False``
        does the same out of place, for queries autograd follows (in place, it would overwrite what the
        backward pass needs).
        """
        clamp = torch.Tensor.clamp_max_ if inplace else torch.Tensor.clamp_max
        dot = torch.matmul(q, self.q_kappa_t)
        neg_p = neg_scaled_squared_distances(p - self.p_centre, self.p_scaled, self.p_root_scale)
        neg_q = clamp(dot.abs_().sub_(self.kappa) if inplace else dot.abs() - self.kappa, 0.0)
        neg_r = None
        if r is not None:
            x = (r - self.r_centre) * self.r_inv_sqrt_sigma
            neg_r = neg_scaled_squared_distances(x, self.r_scaled, self.r_root_scale)
        return neg_p, neg_q, neg_r

    def scaled_terms(self, p: Tensor, q: Tensor, r: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
        """β·d of each factor, computed exactly as in :meth:`log_kernels` (negation is exact)."""
        neg_p, neg_q, neg_r = self.neg_terms(p, q, r)
        return neg_p.neg_(), neg_q.neg_(), (None if neg_r is None else neg_r.neg_())

    def log_kernels(self, p: Tensor, q: Tensor, r: Tensor | None, with_weights: bool, inplace: bool = True
                    ) -> Tensor:
        """log(w_i K(x|μ_i)) (or log K) for a chunk: ``(*BB, m, N)``, -inf where a factor is cut off
        (``inplace`` as :meth:`neg_terms`)."""
        terms = self.neg_terms(p, q, r, inplace)
        total = None
        for neg, delta in zip(terms, self.delta, strict=True):
            if neg is None:
                continue
            # keeps x where x > −δ (β d < δ) and writes −inf elsewhere: the paper's cut-off
            if inplace:
                torch.nn.functional.threshold_(neg, -delta, -math.inf)
            else:
                neg = torch.where(neg > -delta, neg, torch.full_like(neg, -math.inf))
            total = neg if total is None else (total.add_(neg) if inplace else total + neg)
        assert total is not None
        if with_weights:
            total = total.add_(self.log_w.unsqueeze(-2)) if inplace else total + self.log_w.unsqueeze(-2)
        return total
