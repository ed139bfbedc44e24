"""The dense reference's building blocks (paper, Kernel Density Estimation: the distances of Eq.
surface_feature_kernel and the weighted sum of Eq. surface_feature_probability): scaled squared distances as
exact differences, logsumexp over kernels, and the small reductions of the trial-round fitting."""

from __future__ import annotations

import math

import torch

from pushtorch.se3 import Pose

Tensor = torch.Tensor

__all__ = ["amin_to_size", "logsumexp_last", "needs_grad", "neg_scaled_squared_distances"]


def neg_scaled_squared_distances(x: Tensor, mu_t: Tensor, root_scale: Tensor) -> Tensor:
    """``−s |x − μ|²`` for queries ``x (*BB, m, k)`` and kernels ``μ (*B, N, k)``, with ``root_scale = √s``
    ``(*B, 1, 1)`` already applied to ``mu_t``: ``(*BB, m, N)``.

    The differences are taken directly (``cdist`` without the matmul expansion), so the value has a small
    *relative* error: exactly 0 at a kernel's own mean, wherever that lies. The expansion
    ``|x|² − 2x·μ + |μ|²`` it replaces cancelled to an absolute error of ~1e-7 · |x|² in float32, which a
    narrow bandwidth turns into percent-sized errors (kernels 0.6 m apart, p_std 1 mm: up to 6 %), and whose
    size depended on the CPU's matmul path.
    """
    xs = x * root_scale
    batch = torch.broadcast_shapes(xs.shape[:-2], mu_t.shape[:-2])
    d = torch.cdist(xs.expand(*batch, *xs.shape[-2:]), mu_t.expand(*batch, *mu_t.shape[-2:]),
                    compute_mode="donot_use_mm_for_euclid_dist")
    return d.square_().neg_() if not d.requires_grad else -d.square()


def needs_grad(pose: Pose, descriptors: Tensor | None) -> bool:
    """Whether autograd records a density evaluation of these queries."""
    tensors = [pose.p, pose.q] + ([] if descriptors is None else [descriptors])
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def logsumexp_last(x: Tensor, inplace: bool = True) -> Tensor:
    """logsumexp over the last dim; all ``-inf`` gives ``-inf``. In place (``x`` is consumed) unless
    autograd follows ``x``.

    ``torch.logsumexp`` over a long last dim is several times slower on CPU than these four passes. Out of
    place, a row without a finite entry is taken as zeros and masked, so its gradient is 0, not the NaN of
    exp(−inf + inf).
    """
    if not inplace:
        reached = torch.isfinite(x).any(-1, keepdim=True)
        safe = torch.logsumexp(torch.where(reached, x, torch.zeros_like(x)), -1)
        return torch.where(reached.squeeze(-1), safe, torch.full_like(safe, -math.inf))
    peak = x.amax(-1, keepdim=True)
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))  # small: (*BB, m, 1)
    return x.sub_(peak).exp_().sum(-1).log_().add_(peak.squeeze(-1))


def amin_to_size(x: Tensor, size: torch.Size) -> Tensor:
    """Min-reduce broadcast dims of ``x`` down to ``size`` (the min analogue of ``sum_to_size``)."""
    for dim, (have, want) in enumerate(zip(x.shape, size, strict=False)):
        if want == 1 and have != 1:
            x = x.amin(dim, keepdim=True)
    return x.expand(size) if x.shape != size else x
