"""The textbook evaluation of a kernel density: every query against every kernel, the cut-offs as masks,
logsumexp (:func:`straightforward_evaluation`, :func:`straightforward_log_prob`); the benchmark's baseline and
an independent check of the dense and fast paths.

Paper, Background → Kernel Density Estimation: the kernel of Eq. surface_feature_kernel and the weighted sum of
Eq. surface_feature_probability, written as plainly as they read.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Iterator
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from pushtorch.kde.density import PoseKDE

Tensor = torch.Tensor

__all__ = ["straightforward_active", "straightforward_evaluation", "straightforward_log_prob"]

_STRAIGHTFORWARD = contextvars.ContextVar("pushtorch_straightforward_evaluation", default=False)


@contextlib.contextmanager
def straightforward_evaluation() -> Iterator[None]:
    """Within this block, ``method="dense"`` log densities are evaluated the straightforward way.

    Every query against every kernel in one block per density (no chunking, no expansion around the
    kernel centre, no in-place passes): ``d_p`` from ``torch.cdist``, ``d_q`` from the quaternion dot
    product, the cut-offs as masks, ``logsumexp`` over the kernels; a stacked density (e.g. the experts
    of a product) is evaluated one element at a time on its own kernels, padding left out. The values
    are those of the dense reference up to float rounding. It is the baseline issue 6 sized (timed by
    ``tools/bench_predict.py`` beside the dense reference) and an independent check of the dense and
    fast paths. Memory is a whole ``(queries, kernels)`` block per density, not bounded by chunks, so
    the library itself never evaluates this way. Scoped to the current thread or task (a context
    variable), like ``torch.no_grad``.

    Example:
        >>> with straightforward_evaluation():
        ...     prediction = predict(model, cloud, action, generator, method="dense")  # doctest: +SKIP
    """
    token = _STRAIGHTFORWARD.set(True)
    try:
        yield
    finally:
        _STRAIGHTFORWARD.reset(token)


def straightforward_active() -> bool:
    """Whether the current thread or task is inside :func:`straightforward_evaluation`."""
    return _STRAIGHTFORWARD.get()


def straightforward_log_prob(kde: PoseKDE, p: Tensor, q: Tensor, r: Tensor | None) -> Tensor:
    """``kde.log_prob`` the textbook way (see :func:`straightforward_evaluation`): ``(*BB, M)``."""
    batch = torch.broadcast_shapes(p.shape[:-2], kde.batch_shape)
    m, n = p.shape[-2], kde.num_kernels
    flat = batch.numel()
    p = p.expand(*batch, m, 3).reshape(flat, m, 3)
    q = q.expand(*batch, m, 4).reshape(flat, m, 4)
    kernel_p = kde.means.p.expand(*batch, n, 3).reshape(flat, n, 3)
    kernel_q = kde.means.q.expand(*batch, n, 4).reshape(flat, n, 4)
    log_w = kde.log_weights.expand(*batch, n).reshape(flat, n)
    beta = kde.beta.expand(*batch, 3).reshape(flat, 3)
    bw = kde.bandwidth
    delta_p, delta_q, delta_r = bw.delta
    if r is not None:
        inv_sqrt_sigma = torch.tensor(bw.sigma_r, dtype=torch.float64).rsqrt().to(kde.device, kde.dtype)
        k = r.shape[-1]
        r = (r * inv_sqrt_sigma).expand(*batch, m, k).reshape(flat, m, k)
        kernel_r = (kde.descriptors * inv_sqrt_sigma).expand(*batch, n, k).reshape(flat, n, k)
    out = []
    for b in range(flat):
        keep = log_w[b] > -math.inf  # padding kernels of a stacked density are not kernels
        d_p = torch.cdist(p[b], kernel_p[b][keep]).square() * (beta[b, 0] / bw.sigma_p)
        d_q = (1.0 - (q[b] @ kernel_q[b][keep].T).abs().clamp(max=1.0)) * (beta[b, 1] / bw.sigma_q)
        inside = (d_p < delta_p) & (d_q < delta_q)
        distance = d_p + d_q
        if r is not None:
            d_r = torch.cdist(r[b], kernel_r[b][keep]).square() * beta[b, 2]
            inside &= d_r < delta_r
            distance = distance + d_r
        log_kernels = torch.where(inside, log_w[b][keep] - distance, -math.inf)
        out.append(torch.logsumexp(log_kernels, -1))
    return torch.stack(out).reshape(*batch, m) if out else p.new_empty(*batch, m)

