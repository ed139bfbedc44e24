"""Normalising constants of kernel densities and of products of experts over SE(3) (paper, §KDE, Eq. poe).

The paper's kernels are unnormalised (``K(μ|μ) = 1``) and its product of experts is used only through its
arg-max. Scoring a density by likelihood, or offering it as a ``torch.distributions.Distribution``, needs the
constants: a kernel's integral (:func:`log_kernel_normaliser`: the Gaussian's mass inside its cut-off times
the folded vMF's integral, :func:`log_rotation_normaliser`) and the integral of a product of normalised
experts raised to their exponents (:func:`log_normaliser`, by importance sampling). Base measure: Lebesgue
on positions (m³) times the uniform probability measure on SO(3), q and −q one rotation.
"""

from __future__ import annotations

import math

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.kde.bandwidth import KernelBandwidth
from pushtorch.kde.density import PoseKDE
from pushtorch.kde.sampling import sample_kernel_offsets
from pushtorch.streams import KeyedStream, is_keyed

Tensor = torch.Tensor

__all__ = [
    "IMPORTANCE_SAMPLES",
    "NO_CUTOFF",
    "expert_exponents",
    "expert_log_probs",
    "log_kernel_integral",
    "log_kernel_normaliser",
    "log_normaliser",
    "log_normalisers",
    "log_rotation_normaliser",
    "unit_quaternions",
]

#: Proposals per expert and part of the importance-sampled normaliser: on a paper-size cube prediction (6
#: experts, ~1,000 kernels) log Z varies by 0.009 nats between seeds with 64 (0.08 s on one core) and by
#: 0.003 with 512 (1.3 s).
IMPORTANCE_SAMPLES = 64
#: Cut-off std multiples of a kernel that is never cut off (the exact Gaussian × folded vMF).
NO_CUTOFF = (math.inf, math.inf, math.inf)


def log_rotation_normaliser(kappa: Tensor, delta_q: float = math.inf) -> Tensor:
    """``log ∫ exp(−κ (1 − |<q, μ>|)) dq`` over SO(3) with its uniform probability measure, ``(...)``, over the
    rotations where ``κ (1 − |<q, μ>|) < delta_q`` (a kernel's cut-off; inf: everywhere).

    With ``s = 1 − |<q, μ>|`` the integral is ``(4/π) ∫_0^1 √(s (2 − s)) e^(−κ s) ds`` (1 at κ = 0); with
    ``κ s = v²`` it is ``(4/π) κ^(−3/2) ∫ 2 v² √(2 − v²/κ) e^(−v²) dv`` over ``v < min(√κ, √delta_q)``,
    integrated by Simpson's rule on 2,001 points up to that bound or 9 (beyond, e^(−81) is nothing in
    float64).
    """
    kappa = torch.as_tensor(kappa, dtype=torch.float64).clamp_min(1e-6)
    upper = torch.sqrt(kappa).clamp(max=min(9.0, math.sqrt(delta_q)))
    u = torch.linspace(0.0, 1.0, 2001, dtype=torch.float64, device=kappa.device)
    v = upper.unsqueeze(-1) * u
    f = 2.0 * v * v * torch.sqrt((2.0 - v * v / kappa.unsqueeze(-1)).clamp_min(0.0)) * torch.exp(-v * v)
    weights = torch.ones_like(u)
    weights[1:-1:2], weights[2:-1:2] = 4.0, 2.0
    integral = (f * weights).sum(-1) * upper / (3.0 * (u.numel() - 1))
    return math.log(4.0 / math.pi) - 1.5 * torch.log(kappa) + torch.log(integral)


def log_kernel_normaliser(kde: PoseKDE) -> Tensor:
    """``(*B,)`` log of the integral of one kernel of ``kde`` (all kernels of a batch element share it),
    cut off as the kde's bandwidth says (:func:`log_kernel_integral` of its β)."""
    return log_kernel_integral(kde.bandwidth, kde.beta.double())


def log_kernel_integral(bandwidth: KernelBandwidth, beta: Tensor) -> Tensor:
    """``(*B,)`` log of the integral of one kernel of ``bandwidth`` at multipliers ``beta (*B, 3)`` (float64): the
    Gaussian's mass inside ``β d_p < δ_p`` is the regularised incomplete gamma ``P(3/2, δ_p)`` (``β d_p`` of a 3-D
    Gaussian is Gamma(3/2)), the rotation's is integrated by :func:`log_rotation_normaliser`."""
    std_p = bandwidth.p_std / torch.sqrt(beta[..., 0])
    kappa = beta[..., 1] / bandwidth.sigma_q
    delta_p, delta_q, _ = bandwidth.delta
    inside_p = 0.0 if math.isinf(delta_p) else math.log(torch.special.gammainc(
        torch.tensor(1.5, dtype=torch.float64), torch.tensor(delta_p, dtype=torch.float64)).item())
    return 1.5 * torch.log(2.0 * math.pi * std_p**2) + inside_p + log_rotation_normaliser(kappa, delta_q)


def expert_exponents(kde: PoseKDE, exponent: Tensor | None) -> Tensor:
    """``(E,)`` float64 exponents ``γ_e`` of the experts (1 each by default)."""
    n_experts = int(kde.batch_shape[0])
    if exponent is None:
        return torch.ones(n_experts, dtype=torch.float64)
    g = torch.as_tensor(exponent, dtype=torch.float64).reshape(-1)
    if g.shape[0] != n_experts or not torch.isfinite(g).all() or (g < 0).any():
        raise InvalidParameterError(f"expert exponents must be {n_experts} finite numbers >= 0, got {g.tolist()}")
    return g


def log_normaliser(kde: PoseKDE, generator: torch.Generator | None = None, samples: int = IMPORTANCE_SAMPLES,
                   centres: se3.Pose | None = None, exponent: Tensor | None = None) -> Tensor:
    """``log ∫ Π_e p_e(x)^γ_e dx`` of the experts ``kde`` (batch ``(E,)``, each normalised; exponents
    ``γ_e``, default 1), estimated by importance sampling; 0 for a single expert of exponent 1.

    The proposal is an equal mixture of three parts, ``samples`` draws per expert each: the experts at their
    own bandwidth, the experts two trial rounds wider (the tails), and kernels ``√Σγ`` times narrower — the
    width of the product of E kernels raised to ``γ_e`` — at ``centres`` (a prediction's annealed
    candidates, which sit at the product's modes; by default points drawn from the experts). The
    deterministic-mixture estimator is unbiased given the centres; on a cube prediction's six experts its
    log varies by about 0.01 nats between seeds.
    """
    n_experts = int(kde.batch_shape[0])
    gamma = expert_exponents(kde, exponent)
    if n_experts == 1 and float(gamma[0]) == 1.0:
        return torch.zeros((), dtype=torch.float64)
    sharpness = max(float(gamma.sum()), 1e-6)
    wide = kde.with_trial_rounds(kde.trial_rounds + torch.tensor([2, 2, 0], device=kde.device))
    if centres is None:
        centres = kde.sample(samples, generator)[0]
    beta = kde.beta.double()[0]
    narrow_bandwidth = KernelBandwidth(
        p_std=kde.bandwidth.p_std / math.sqrt(float(beta[0]) * sharpness),
        rot_std=kde.bandwidth.rot_std / math.sqrt(float(beta[1]) * sharpness), cutoff_std=NO_CUTOFF)
    flat_centres = se3.Pose.unchecked(centres.p.to(kde.dtype).reshape(1, -1, 3),
                                      unit_quaternions(centres.q.to(kde.dtype).reshape(1, -1, 4)))
    narrow = PoseKDE(flat_centres, narrow_bandwidth)
    draws = [kde.sample(samples, generator)[0], wide.sample(samples, generator)[0],
             narrow.sample(samples * n_experts, generator)[0]]
    flat = se3.Pose.unchecked(torch.cat([d.p.reshape(-1, 3) for d in draws]),
                              torch.cat([d.q.reshape(-1, 4) for d in draws]))
    own = expert_log_probs(kde, flat)  # (E, M)
    parts = [torch.logsumexp(own, 0) - math.log(n_experts),
             torch.logsumexp(expert_log_probs(wide, flat), 0) - math.log(n_experts),
             expert_log_probs(narrow, flat)[0]]
    log_proposal = torch.logsumexp(torch.stack(parts), 0) - math.log(3.0)
    return torch.logsumexp((gamma.unsqueeze(-1) * own).sum(0) - log_proposal, 0) - math.log(flat.p.shape[0])


def unit_quaternions(q: Tensor) -> Tensor:
    """``q (..., 4)`` scaled to unit length (float products drift off it)."""
    return q / q.norm(dim=-1, keepdim=True)


def expert_log_probs(kde: PoseKDE, pose: se3.Pose) -> Tensor:
    """``(E, M)`` normalised log densities (float64) of every expert of ``kde`` (batch ``(E,)``) at poses
    ``(M,)``."""
    query = se3.Pose.unchecked(pose.p.to(kde.dtype).unsqueeze(0), unit_quaternions(pose.q.to(kde.dtype)).unsqueeze(0))
    unnormalised = kde.log_prob(query)
    return unnormalised.double() - log_kernel_normaliser(kde).unsqueeze(-1)


#: Kernel values per block of :func:`log_normalisers` (problems × kernels × queries, float64: ~32 MB).
_BLOCK_VALUES = 4_000_000


def _draw_kernels(log_weights: Tensor, n: int, stream: KeyedStream) -> Tensor:
    """``(B, E, n)`` kernel indices, ``n`` per expert, each with its normalised weight (``log_weights (B, E, K)``)."""
    cumulative = torch.softmax(log_weights.double(), -1).cumsum(-1)
    u = stream.uniform((log_weights.shape[0], log_weights.shape[1], n), torch.float64).to(cumulative.device)
    index = torch.searchsorted(cumulative, (u * cumulative[..., -1:]).contiguous(), right=True)
    return index.clamp_max(log_weights.shape[-1] - 1)


def _offset_draws(p: Tensor, q: Tensor, std: Tensor, kappa: Tensor, delta_p: float, delta_q: float,
                  stream: KeyedStream) -> tuple[Tensor, Tensor]:
    """Kernel draws around means ``p (B, M, 3)``, ``q (B, M, 4)`` (float64) of per-problem translation stds and
    rotation concentrations ``(B,)``, truncated at the cut-offs (:meth:`PoseKDE.sample`'s exact draws)."""
    shape = p.shape[:-1]
    offset, turn = sample_kernel_offsets(std.unsqueeze(-1).expand(shape), kappa.unsqueeze(-1).expand(shape), delta_p,
                                         delta_q, stream)
    return p + offset, unit_quaternions(pkt.quaternion_raw_multiply(q, turn))


def _kernel_log_sums(x_p: Tensor, x_q: Tensor, mu_p: Tensor, mu_q: Tensor, relative: Tensor, top: Tensor,
                     scale_p: Tensor, scale_q: Tensor, delta_p: float, delta_q: float) -> Tensor:
    """``(B, E, M)`` ``log Σ_k w_ek K(x | μ_k)`` (kernels 1 at their means; float64) of queries ``x (B, M)`` against
    kernels ``μ (B, K)`` shared by every expert, ``relative (B, E, K)`` each expert's weights over its largest
    ``top (B, E, 1)``, scales ``(B,)``: the exact distances and cut-offs of :meth:`PoseKDE.log_prob`, each kernel
    evaluated once for all experts and their sums one batched product, in blocks of problems and queries."""
    count, m = x_p.shape[:2]
    block = max(1, _BLOCK_VALUES // max(1, mu_p.shape[1]))
    per = max(1, block // max(1, m))  # whole problems per block when they fit, else one and a block of queries
    out = []
    for a in range(0, count, per):
        b = min(count, a + per)
        norms = (mu_p[a:b] * mu_p[a:b]).sum(-1, keepdim=True)  # |μ − x|² expanded: exact enough in float64
        rows = []
        for start in range(0, m, block):
            xp, xq = x_p[a:b, start:start + block], x_q[a:b, start:start + block]
            d_p = (norms + (xp * xp).sum(-1).unsqueeze(1) - 2.0 * torch.bmm(mu_p[a:b], xp.transpose(1, 2)))
            d_p = d_p.clamp_min(0.0) * scale_p[a:b, None, None]
            d_q = (1.0 - torch.bmm(mu_q[a:b], xq.transpose(1, 2)).abs()).clamp_min(0.0) * scale_q[a:b, None, None]
            values = torch.where((d_p < delta_p) & (d_q < delta_q), torch.exp(-d_p - d_q), torch.zeros_like(d_p))
            sums = torch.bmm(relative[a:b], values)  # (b, E, m)
            reached = sums > 0
            rows.append(torch.where(reached, torch.log(torch.where(reached, sums, torch.ones_like(sums))) + top[a:b],
                                    -math.inf))
        out.append(torch.cat(rows, -1))
    return torch.cat(out)


def log_normalisers(means: se3.Pose, log_weights: Tensor, bandwidth: KernelBandwidth, trial_rounds: Tensor,
                    exponent: Tensor, centres: se3.Pose | None, stream: KeyedStream,
                    samples: int = IMPORTANCE_SAMPLES) -> Tensor:
    """``(B,)`` :func:`log_normaliser` of ``B`` products of experts at once, each from its own keyed draws.

    The products are stacked as a planner's are: kernel means ``(B, K)`` shared by the experts of a problem,
    ``log_weights (E, B, K)`` (``-inf``: not in that expert), ``trial_rounds (B, 3)``, ``exponent (E, B)`` (0: a
    padding expert, neither drawn from nor counted), ``centres (B, C)`` (None: drawn from the experts, the padding
    ones too, as :func:`log_normaliser`'s default draws from its experts). The estimator is
    :func:`log_normaliser`'s: the experts at their own bandwidth, two trial rounds wider, and narrow kernels at the
    centres, ``samples`` per counted expert each. ``stream`` (a :class:`~pushtorch.streams.KeyedStream` over the
    problems) makes every draw, so a problem's value depends neither on the other problems nor on its batch's
    padding. The experts' log densities come from one evaluation of each kernel for all of a problem's experts
    (float64), with no loop over the problems.

    Raises:
        InvalidParameterError: a stream that is not keyed over the ``B`` problems.
    """
    if not is_keyed(stream) or len(stream) != log_weights.shape[1]:
        raise InvalidParameterError("log_normalisers draws from a keyed stream with one key per problem")
    n_experts, count, _ = log_weights.shape
    device = log_weights.device
    counted = (exponent > 0).transpose(0, 1)  # (B, E)
    n_counted = counted.sum(-1).clamp_min(1)  # (B,)
    gamma = torch.where(counted, exponent.transpose(0, 1).double(), 0.0)  # (B, E)
    sharpness = gamma.sum(-1).clamp_min(1e-6)
    log_w = log_weights.transpose(0, 1).double()  # (B, E, K)
    log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)  # each expert normalised
    mu_p, mu_q = means.p.double(), unit_quaternions(means.q.double())
    delta_p, delta_q, _ = bandwidth.delta
    beta = torch.pow(torch.tensor(bandwidth.alpha_t, dtype=torch.float64, device=device),
                     -trial_rounds.double()).to(means.p.dtype).double()  # (B, 3), as PoseKDE's
    widen = torch.tensor([bandwidth.alpha_t**2, bandwidth.alpha_t**2, 1.0], dtype=torch.float64, device=device)
    wide_beta = beta / widen  # two trial rounds wider
    n = samples * n_experts  # per problem and part: the padding experts' share is drawn, then masked

    def around_kernels(b: Tensor, draws: KeyedStream) -> tuple[Tensor, Tensor]:
        index = _draw_kernels(log_w, samples, draws).reshape(count, n)
        p = torch.gather(mu_p, 1, index.unsqueeze(-1).expand(count, n, 3))
        q = torch.gather(mu_q, 1, index.unsqueeze(-1).expand(count, n, 4))
        return _offset_draws(p, q, bandwidth.p_std / torch.sqrt(b[:, 0]), b[:, 1] / bandwidth.sigma_q, delta_p,
                             delta_q, draws)

    if centres is None:
        c_p, c_q = around_kernels(beta, stream.fork())
    else:
        c_p = centres.p.double().reshape(count, -1, 3)
        c_q = unit_quaternions(centres.q.double().reshape(count, -1, 4))
    narrow_std = bandwidth.p_std / torch.sqrt(beta[:, 0] * sharpness)  # (B,)
    narrow_kappa = 4.0 * beta[:, 1] * sharpness / bandwidth.rot_std**2  # 1 / σ_q of the narrow kernels
    own_p, own_q = around_kernels(beta, stream.fork())
    wide_p, wide_q = around_kernels(wide_beta, stream.fork())
    draws = stream.fork()
    centres_count = c_p.shape[1]
    pick = (draws.uniform((count, n), torch.float64).to(device) * centres_count).long().clamp_max(centres_count - 1)
    narrow_p, narrow_q = _offset_draws(torch.gather(c_p, 1, pick.unsqueeze(-1).expand(count, n, 3)),
                                       torch.gather(c_q, 1, pick.unsqueeze(-1).expand(count, n, 4)),
                                       narrow_std, narrow_kappa, math.inf, math.inf, draws)
    x_p, x_q = torch.cat([own_p, wide_p, narrow_p], 1), torch.cat([own_q, wide_q, narrow_q], 1)  # (B, 3n)
    drawn_from = torch.arange(n, device=device) // samples  # the expert of each own or wide draw
    valid = torch.cat([counted[:, drawn_from], counted[:, drawn_from],
                       torch.arange(n, device=device) < (samples * n_counted).unsqueeze(-1)], 1)  # (B, 3n)
    top = log_w.amax(-1, keepdim=True)
    relative = torch.exp(log_w - top)

    def experts_at(b: Tensor) -> Tensor:  # (B, E, 3n) each expert's normalised log density
        sums = _kernel_log_sums(x_p, x_q, mu_p, mu_q, relative, top, b[:, 0] / bandwidth.sigma_p,
                                b[:, 1] / bandwidth.sigma_q, delta_p, delta_q)
        return sums - log_kernel_integral(bandwidth, b)[:, None, None]

    own, wide = experts_at(beta), experts_at(wide_beta)
    mixture, log_count = counted.unsqueeze(-1), torch.log(n_counted.double()).unsqueeze(-1)
    uniform = torch.ones(count, 1, centres_count, dtype=torch.float64, device=device)
    narrow = _kernel_log_sums(x_p, x_q, c_p, c_q, uniform, uniform[..., :1] * -math.log(centres_count),
                              1.0 / (2.0 * narrow_std**2), narrow_kappa, math.inf, math.inf)[:, 0]
    uncut = KernelBandwidth(p_std=bandwidth.p_std, rot_std=bandwidth.rot_std, cutoff_std=NO_CUTOFF)
    narrow_beta = torch.stack([beta[:, 0] * sharpness, beta[:, 1] * sharpness, torch.ones_like(sharpness)], -1)
    parts = [torch.logsumexp(torch.where(mixture, own, -math.inf), 1) - log_count,
             torch.logsumexp(torch.where(mixture, wide, -math.inf), 1) - log_count,
             narrow - log_kernel_integral(uncut, narrow_beta).unsqueeze(-1)]
    log_proposal = torch.logsumexp(torch.stack(parts), 0) - math.log(3.0)
    target = torch.where(mixture, gamma.unsqueeze(-1) * own, 0.0).sum(1)  # (B, 3n)
    terms = torch.where(valid, target - log_proposal, -math.inf)
    return torch.logsumexp(terms, -1) - torch.log(3.0 * samples * n_counted.double())
