"""Kernel density estimation over SE(3), optionally × R^k descriptors, batched in torch.

Paper, Background → Kernel Density Estimation: the surface-feature kernel (Eq. surface_feature_kernel)
approximated by the cut-off Gaussians N3 / N2 and the antipodal von Mises–Fisher pair Θ, the distances
d_p, d_q, d_r, the bandwidth multipliers β = α_T^(−T) and the trial rounds T = (T_p, T_q, T_r), the
weighted kernel sum P(x) ≈ Σ w_i K(x | x_i) (Eqs. surface_feature_probability, contact_frame_probability,
pdf_motion once the contact-frame terms are folded into the weights, as the paper does), the
descriptor distance d'_r used by the heuristic H_r, and the product of experts (Eq. poe) in log space.

Units (one decision, used everywhere): bandwidths are given as **standard deviations** and the paper's
distances are exact Gaussians / vMF in those units:

* translation: ``d_p = ||p − μ||² / σ_p`` with ``σ_p = 2 p_std²`` (metres), so ``exp(−d_p)`` is an
  isotropic Gaussian of std ``p_std`` per axis;
* rotation: ``d_q = (1 − |<q, μ>|) / σ_q`` with ``σ_q = rot_std² / 4`` (radians), so for small angles
  ``exp(−d_q)`` is a Gaussian in the rotation vector with std ``rot_std`` per axis; exactly it is the vMF
  density of concentration ``κ = 1/σ_q`` folded onto SO(3) (q and −q are one rotation);
* descriptors: ``d_r = Σ_k (r_k − μ_k)² / σ_r,k`` with ``σ_r,k = 2 r_std_k²``;
* cut-offs are given as std multiples ``cutoff_std = (c_p, c_q, c_r)``: a kernel factor is zero when
  ``β d ≥ δ`` with ``δ = c² / 2`` (a Mahalanobis radius of ``c`` effective stds);
* ``β_* = α_T^(−T_*)`` with ``α_T > 1``: one more trial round divides the factor's precision by α_T,
  i.e. widens its std by ``sqrt(α_T)``.

Kernels are the paper's unnormalised ``exp(−β d)`` (``K(μ | μ) = 1``): every kernel of one density
shares the bandwidth and cut-offs, so the missing constant is common to all kernels and cancels in every
ratio and arg-max the method takes (P(m|c,a) = Σ…/P(c), annealing, the product of experts). Omitting the
descriptors of a query (``descriptors=None``) therefore evaluates the density marginalised over the
descriptors, up to that same constant — the paper's "descriptor distance is omitted during optimisation".

Two evaluation paths give the same values: ``method="dense"`` (the reference, every query against every
kernel with matmuls) and ``method="fast"`` (exact distances in fused, optionally compiled passes, pruned by
the hard cut-offs to the leaf blocks of kernels that can reach a query; see the "Fast path" section).
Inside :func:`straightforward_evaluation` the dense reference is evaluated the textbook way instead
(``cdist`` and the quaternion dot for all queries at once, cut-offs, ``logsumexp``): the baseline the
prediction benchmark times for scale, and an oracle for both paths.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import shutil
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.se3 import Pose, check_unit_quaternion, truncated_gamma_1p5, vmf_offsets

Tensor = torch.Tensor

__all__ = [
    "KernelBandwidth",
    "PoseKDE",
    "ProductOfExperts",
    "SharedKernelProduct",
    "TrialRounds",
    "descriptor_distance",
    "descriptor_distance_unscaled",
    "declare_long_run",
    "fast_path_compiled",
    "fused_function",
    "product_log_prob",
    "rotation_distance",
    "straightforward_evaluation",
    "translation_distance",
]

COMPONENTS = ("p", "q", "r")
# Elements of one dense (queries x kernels) block per chunk when no chunk size is given: about 8 MB
# per float32 temporary, so the few temporaries of a chunk stay in a CPU's last-level cache (faster
# here than one 500 x 25,500 block) while the matmuls stay efficient.
_DEFAULT_BLOCK_ELEMENTS = 1 << 21


# --------------------------------------------------------------------------------------------------
# Bandwidths and trial rounds
# --------------------------------------------------------------------------------------------------


def _positive_finite(value: float, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise InvalidParameterError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(value) or value <= 0.0:
        raise InvalidParameterError(f"{name} must be finite and > 0, got {value}")
    return value


@dataclass(frozen=True)
class KernelBandwidth:
    """Kernel bandwidths (as standard deviations), cut-offs and the trial-round settings.

    Attributes:
        p_std: translation std in metres (σ_p = 2 p_std²).
        rot_std: rotation std in radians per axis of the rotation vector (σ_q = rot_std² / 4).
        r_std: per-dimension descriptor stds (σ_r = 2 r_std²), or None for a density over SE(3) only.
        cutoff_std: (c_p, c_q, c_r) cut-offs in effective stds, δ = c²/2; ``math.inf`` disables one.
            Default (3, 3, 5): 3 std keeps 97 % of a 3-D Gaussian's mass; the method's lineage cuts
            descriptors at 5 std.
        alpha_t: α_T > 1, the rate at which β = α_T^(−T) decreases with trial rounds (default 2, the
            lineage's 1/2^round).
        max_trial_rounds: the largest total T_p + T_q + T_r the trial-round search may reach (default 10,
            the lineage's limit) before it gives up with a ModelError.
    """

    p_std: float
    rot_std: float
    r_std: tuple[float, ...] | None = None
    cutoff_std: tuple[float, float, float] = (3.0, 3.0, 5.0)
    alpha_t: float = 2.0
    max_trial_rounds: int = 10

    def __post_init__(self) -> None:
        object.__setattr__(self, "p_std", _positive_finite(self.p_std, "p_std"))
        object.__setattr__(self, "rot_std", _positive_finite(self.rot_std, "rot_std"))
        if self.r_std is not None:
            r_std = tuple(self.r_std) if isinstance(self.r_std, Sequence) else (self.r_std,)
            if len(r_std) == 0:
                raise InvalidParameterError("r_std must hold at least one std (None: no descriptors)")
            r_std = tuple(_positive_finite(s, f"r_std[{i}]") for i, s in enumerate(r_std))
            object.__setattr__(self, "r_std", r_std)
        cutoff = tuple(self.cutoff_std)
        if len(cutoff) != 3:
            raise InvalidParameterError(f"cutoff_std must hold 3 values (c_p, c_q, c_r), got {cutoff}")
        for name, c in zip(COMPONENTS, cutoff, strict=True):
            c = float(c)
            if math.isnan(c) or c <= 0.0:
                raise InvalidParameterError(f"cutoff_std for {name} must be > 0 (inf disables it), got {c}")
        object.__setattr__(self, "cutoff_std", tuple(float(c) for c in cutoff))
        alpha = _positive_finite(self.alpha_t, "alpha_t")
        if alpha <= 1.0:
            raise InvalidParameterError(f"alpha_t must be > 1 so trial rounds widen kernels, got {alpha}")
        object.__setattr__(self, "alpha_t", alpha)
        if isinstance(self.max_trial_rounds, bool) or int(self.max_trial_rounds) != self.max_trial_rounds:
            raise InvalidParameterError(f"max_trial_rounds must be an integer, got {self.max_trial_rounds!r}")
        if self.max_trial_rounds < 0:
            raise InvalidParameterError(f"max_trial_rounds must be >= 0, got {self.max_trial_rounds}")
        object.__setattr__(self, "max_trial_rounds", int(self.max_trial_rounds))

    @property
    def sigma_p(self) -> float:
        """The paper's σ_p = 2 p_std² (m²)."""
        return 2.0 * self.p_std**2

    @property
    def sigma_q(self) -> float:
        """The paper's σ_q = rot_std² / 4, i.e. 1/κ of the vMF pair."""
        return self.rot_std**2 / 4.0

    @property
    def sigma_r(self) -> tuple[float, ...] | None:
        """The paper's per-dimension σ_r = 2 r_std² (the diagonal of D_σr^-1 inverted), or None."""
        return None if self.r_std is None else tuple(2.0 * s**2 for s in self.r_std)

    @property
    def descriptor_dim(self) -> int:
        return 0 if self.r_std is None else len(self.r_std)

    @property
    def delta(self) -> tuple[float, float, float]:
        """The paper's cut-offs (δ_p, δ_q, δ_r) = c² / 2."""
        return tuple(c * c / 2.0 for c in self.cutoff_std)  # type: ignore[return-value]


@dataclass(frozen=True)
class TrialRounds:
    """Trial rounds T = (T_p, T_q, T_r): how many times each kernel factor has been widened."""

    p: int = 0
    q: int = 0
    r: int = 0

    def __post_init__(self) -> None:
        for name in COMPONENTS:
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 0:
                raise InvalidParameterError(f"trial round T_{name} must be an integer >= 0, got {value!r}")
            object.__setattr__(self, name, int(value))

    def beta(self, alpha_t: float) -> tuple[float, float, float]:
        """Bandwidth multipliers (β_p, β_q, β_r) = α_T^(−T)."""
        return (alpha_t ** (-self.p), alpha_t ** (-self.q), alpha_t ** (-self.r))

    def as_tensor(self, device=None) -> Tensor:
        """``(3,)`` int64 tensor (T_p, T_q, T_r)."""
        return torch.tensor([self.p, self.q, self.r], dtype=torch.int64, device=device)

    @staticmethod
    def from_tensor(rounds: Tensor) -> TrialRounds:
        """From a ``(3,)`` tensor (e.g. ``kde.trial_rounds[i]`` of one batch element)."""
        if rounds.shape != (3,):
            raise InvalidParameterError(f"trial rounds must have shape (3,), got {tuple(rounds.shape)}")
        return TrialRounds(*(int(v) for v in rounds.tolist()))


# --------------------------------------------------------------------------------------------------
# The paper's distances (exact, broadcasting)
# --------------------------------------------------------------------------------------------------


def _check_sigma(sigma: float | Tensor, name: str) -> None:
    if isinstance(sigma, Tensor):
        if not torch.isfinite(sigma).all() or (sigma <= 0).any():
            raise InvalidParameterError(f"{name} must be finite and > 0")
    else:
        _positive_finite(sigma, name)


def translation_distance(p: Tensor, mu: Tensor, sigma_p: float | Tensor) -> Tensor:
    """The paper's d_p = ||p − μ||² / σ_p.

    Args:
        p: points ``(..., 3)``; mu: kernel means ``(..., 3)``; batch dims broadcast.
        sigma_p: bandwidth σ_p > 0 (m², = 2 p_std²), scalar or broadcastable to the batch dims.

    Returns:
        ``(...)`` distances.

    Raises:
        InvalidParameterError: σ_p not finite and positive.
    """
    _check_sigma(sigma_p, "sigma_p")
    return ((p - mu) ** 2).sum(-1) / sigma_p


def rotation_distance(q: Tensor, mu: Tensor, sigma_q: float | Tensor) -> Tensor:
    """The paper's d_q = (1 − |<q, μ>|) / σ_q (sign-invariant: q and −q are one rotation).

    Args:
        q: unit quaternions ``(..., 4)`` w,x,y,z; mu: kernel means ``(..., 4)``; batch dims broadcast.
        sigma_q: bandwidth σ_q > 0 (= rot_std² / 4), scalar or broadcastable to the batch dims.

    Returns:
        ``(...)`` distances in ``[0, 1/σ_q]``.

    Raises:
        InvalidParameterError: σ_q not finite and positive.
    """
    _check_sigma(sigma_q, "sigma_q")
    return (1.0 - (q * mu).sum(-1).abs().clamp(max=1.0)) / sigma_q


def descriptor_distance(r: Tensor, mu: Tensor, sigma_r: float | Sequence[float] | Tensor) -> Tensor:
    """The paper's d_r = (r − μ)ᵀ D_σr^-1 (r − μ), with D_σr^-1 = diag(1/σ_r).

    Args:
        r: descriptors ``(..., k)``; mu: kernel descriptors ``(..., k)``; batch dims broadcast.
        sigma_r: per-dimension bandwidths σ_r > 0 (= 2 r_std²), a scalar or ``(k,)``.

    Returns:
        ``(...)`` distances.

    Raises:
        InvalidParameterError: a σ_r not finite and positive.
    """
    sigma = torch.as_tensor(sigma_r, dtype=r.dtype, device=r.device)
    _check_sigma(sigma, "sigma_r")
    return ((r - mu) ** 2 / sigma).sum(-1)


def descriptor_distance_unscaled(r1: Tensor, r2: Tensor) -> Tensor:
    """The paper's d'_r(r1, r2) = (r1 − r2)ᵀ I (r1 − r2), used by the selection heuristic H_r.

    Args:
        r1, r2: descriptors ``(..., k)``; batch dims broadcast.

    Returns:
        ``(...)`` squared Euclidean distances.
    """
    return ((r1 - r2) ** 2).sum(-1)


# --------------------------------------------------------------------------------------------------
# Samplers for one kernel factor (exact, truncated at the cut-off)
# --------------------------------------------------------------------------------------------------


def _unit_vectors(shape: tuple[int, ...], generator, device) -> Tensor:
    v = torch.randn(*shape, 3, generator=generator, dtype=torch.float64, device=device)
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def _sample_translation_offsets(
    std: Tensor, delta_p: float, generator: torch.Generator | None
) -> Tensor:
    """Offsets ``(..., 3)`` (float64): isotropic Gaussian of per-axis ``std (...)``, cut at β d_p < δ_p."""
    x = truncated_gamma_1p5(torch.full_like(std, delta_p), generator)
    radius = torch.sqrt(2.0 * x) * std  # β d_p = |Δ|² / (2 std²) = x
    return radius.unsqueeze(-1) * _unit_vectors(tuple(std.shape), generator, std.device)


def _sample_rotation_offsets(kappa: Tensor, delta_q: float, generator: torch.Generator | None) -> Tensor:
    """Unit quaternions ``(..., 4)`` (float64) around identity, density ∝ exp(κ|w|), cut at κ(1−|w|) < δ_q
    (:func:`pushtorch.se3.vmf_offsets`, the library's one vMF sampler)."""
    return vmf_offsets(kappa, kappa.shape, generator, torch.float64, kappa.device, delta_q)


# --------------------------------------------------------------------------------------------------
# The density
# --------------------------------------------------------------------------------------------------


def _augment_query(x: Tensor) -> Tensor:
    """``[x, 1, |x|²]`` so that ``aug(x) @ aug_kernel(μ)ᵀ = s (|x|² − 2 x·μ + |μ|²)`` is one matmul."""
    return torch.cat([x, torch.ones_like(x[..., :1]), (x * x).sum(-1, keepdim=True)], -1)


def _augment_kernel(mu: Tensor, scale: Tensor) -> Tensor:
    """``scale · [−2 μ, |μ|², 1]``; ``scale`` broadcasts over ``mu``'s batch dims as ``(*B, 1, 1)``."""
    aug = torch.cat([-2.0 * mu, (mu * mu).sum(-1, keepdim=True), torch.ones_like(mu[..., :1])], -1)
    return aug * scale


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
        self._trial_rounds = self._rounds_tensor(trial_rounds, batch, device)
        self._precompute()

    # -- construction helpers ------------------------------------------------------------------

    @staticmethod
    def _rounds_tensor(rounds: TrialRounds | Tensor | None, batch: torch.Size, device) -> Tensor:
        if rounds is None:
            rounds = TrialRounds()
        if isinstance(rounds, TrialRounds):
            t = rounds.as_tensor(device)
        else:
            t = torch.as_tensor(rounds, device=device)
            if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
                raise InvalidParameterError(f"trial rounds must be an integer tensor, got {t.dtype}")
            if (t < 0).any():
                raise InvalidParameterError("trial rounds must be >= 0")
            t = t.to(torch.int64)
        if t.shape[-1:] != (3,):
            raise InvalidParameterError(f"trial rounds must have shape (*B, 3) or (3,), got {tuple(t.shape)}")
        try:
            return t.expand(*batch, 3).contiguous()
        except RuntimeError as exc:
            raise InvalidParameterError(
                f"trial rounds of shape {tuple(t.shape)} do not match the batch shape {tuple(batch)}"
            ) from exc

    def _precompute(self) -> None:
        """Scaled kernel matrices so that every chunk needs one matmul per factor."""
        bw = self.bandwidth
        dtype = self._p.dtype
        self._beta = torch.pow(
            torch.tensor(bw.alpha_t, dtype=torch.float64, device=self._p.device), -self._trial_rounds.double()
        ).to(dtype)  # (*B, 3)
        weights = self._log_w.exp().unsqueeze(-1)  # padding kernels get 0 weight in the centre
        # Centring on the weighted kernel mean keeps the expanded |x|² − 2x·μ + |μ|² well conditioned.
        self._p_centre = (weights * self._p).sum(-2, keepdim=True)
        # Kernel matrices carry the minus sign and β/σ, so one matmul yields −β d directly.
        scale_p = -(self._beta[..., 0] / bw.sigma_p)[..., None, None]
        self._p_aug_t = _augment_kernel(self._p - self._p_centre, scale_p).transpose(-1, -2).contiguous()
        self._kappa = (self._beta[..., 1] / bw.sigma_q)[..., None, None]  # κ = β_q / σ_q, (*B, 1, 1)
        self._q_kappa_t = (self._q * self._kappa).transpose(-1, -2).contiguous()
        if self._r is not None:
            sigma_r = torch.tensor(bw.sigma_r, dtype=torch.float64)
            inv_sqrt_sigma = sigma_r.rsqrt().to(dtype=dtype, device=self._r.device)
            self._r_inv_sqrt_sigma = inv_sqrt_sigma
            self._r_centre = (weights * self._r).sum(-2, keepdim=True)
            scale_r = -self._beta[..., 2][..., None, None]
            mu_r = (self._r - self._r_centre) * inv_sqrt_sigma
            self._r_aug_t = _augment_kernel(mu_r, scale_r).transpose(-1, -2).contiguous()

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
        return Pose(self._p, self._q)

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
        return self._replace(_trial_rounds=self._rounds_tensor(rounds, self.batch_shape, self.device))

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

        p = torch.stack([pad(k._p, k.num_kernels, 0.0) for k in kdes])
        q_parts = []
        for k in kdes:
            qk = pad(k._q, k.num_kernels, 0.0)
            qk[..., k.num_kernels :, 0] = 1.0
            q_parts.append(qk)
        log_w = torch.stack([pad(k._log_w.unsqueeze(-1), k.num_kernels, -math.inf).squeeze(-1) for k in kdes])
        r = None if first._r is None else torch.stack([pad(k._r, k.num_kernels, 0.0) for k in kdes])
        return PoseKDE(
            Pose(p, torch.stack(q_parts)),
            first.bandwidth,
            log_w,
            r,
            torch.stack([k._trial_rounds for k in kdes]),
            validate_args=first.validate_args,
        )

    # -- queries -------------------------------------------------------------------------------

    def _prepare_queries(
        self, pose: Pose, descriptors: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        p, q = pose
        if p.dim() < 2 or p.shape[-1] != 3 or q.dim() < 2 or q.shape[-1] != 4:
            raise InvalidPoseError(
                f"query poses need p (..., M, 3) and q (..., M, 4); got {tuple(p.shape)} and {tuple(q.shape)}"
            )
        p = p.to(self.dtype)
        q = q.to(self.dtype)
        try:
            shape = torch.broadcast_shapes(p.shape[:-1], q.shape[:-1])
        except RuntimeError as exc:
            raise InvalidPoseError(
                f"query p {tuple(p.shape)} and q {tuple(q.shape)} do not broadcast"
            ) from exc
        if descriptors is not None:
            if self._r is None:
                raise InvalidParameterError("query descriptors given to a PoseKDE built without descriptors")
            descriptors = descriptors.to(self.dtype)
            if descriptors.shape[-1:] != (self.descriptor_dim,):
                raise InvalidParameterError(
                    f"query descriptors must have shape (..., M, {self.descriptor_dim}),"
                    f" got {tuple(descriptors.shape)}"
                )
            try:
                shape = torch.broadcast_shapes(shape, descriptors.shape[:-1])
            except RuntimeError as exc:
                raise InvalidParameterError(
                    f"query descriptors {tuple(descriptors.shape)} do not broadcast with the poses"
                    f" {tuple(shape)}"
                ) from exc
            descriptors = descriptors.expand(*shape, self.descriptor_dim)
        try:
            torch.broadcast_shapes(shape[:-1], self.batch_shape)
        except RuntimeError as exc:
            raise InvalidPoseError(
                f"query batch dims {tuple(shape[:-1])} do not broadcast with the density's batch shape"
                f" {tuple(self.batch_shape)} (queries are (..., M))"
            ) from exc
        p = p.expand(*shape, 3)
        q = q.expand(*shape, 4)
        if self.validate_args:
            if not torch.isfinite(p).all():
                raise InvalidPoseError("query positions hold NaN or infinite values")
            check_unit_quaternion(q, name="query q")
            if descriptors is not None and not torch.isfinite(descriptors).all():
                raise InvalidParameterError("query descriptors hold NaN or infinite values")
        return p, q, descriptors

    def _chunk_size(self, query_batch: torch.Size, chunk_size: int | None) -> int:
        if chunk_size is not None:
            if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
                raise InvalidParameterError(f"chunk_size must be a positive integer, got {chunk_size!r}")
            return int(chunk_size)
        batch = torch.broadcast_shapes(query_batch, self.batch_shape).numel()
        return max(1, _DEFAULT_BLOCK_ELEMENTS // max(1, batch * self.num_kernels))

    def _neg_terms(self, p: Tensor, q: Tensor, r: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
        """−β·d of each factor for a chunk of queries: ``(*BB, m, N)`` tensors (r: None if unused).

        One matmul per factor plus in-place element-wise passes: this is the hot path of every density
        evaluation, so it avoids boolean masks and ``where`` (several times slower on CPU).
        """
        neg_p = torch.matmul(_augment_query(p - self._p_centre), self._p_aug_t).clamp_max_(0.0)
        neg_q = torch.matmul(q, self._q_kappa_t).abs_().sub_(self._kappa).clamp_max_(0.0)
        neg_r = None
        if r is not None:
            x = (r - self._r_centre) * self._r_inv_sqrt_sigma
            neg_r = torch.matmul(_augment_query(x), self._r_aug_t).clamp_max_(0.0)
        return neg_p, neg_q, neg_r

    def _scaled_terms(self, p: Tensor, q: Tensor, r: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
        """β·d of each factor, computed exactly as in :meth:`log_prob` (negation is exact)."""
        neg_p, neg_q, neg_r = self._neg_terms(p, q, r)
        return neg_p.neg_(), neg_q.neg_(), (None if neg_r is None else neg_r.neg_())

    def _chunk_log_kernels(self, p: Tensor, q: Tensor, r: Tensor | None, with_weights: bool) -> Tensor:
        """log(w_i K(x|μ_i)) (or log K) for a chunk: ``(*BB, m, N)``, -inf where a factor is cut off."""
        terms = self._neg_terms(p, q, r)
        total = None
        for neg, delta in zip(terms, self.bandwidth.delta, strict=True):
            if neg is None:
                continue
            # threshold keeps x where x > −δ (β d < δ) and writes −inf elsewhere: the paper's cut-off.
            torch.nn.functional.threshold_(neg, -delta, -math.inf)
            total = neg if total is None else total.add_(neg)
        assert total is not None
        if with_weights:
            total.add_(self._log_w.unsqueeze(-2))
        return total

    def _iter_chunks(self, pose: Pose, descriptors: Tensor | None, chunk_size: int | None):
        p, q, r = self._prepare_queries(pose, descriptors)
        m = p.shape[-2]
        step = self._chunk_size(p.shape[:-2], chunk_size)
        for start in range(0, m, step):
            sl = slice(start, start + step)
            yield p[..., sl, :], q[..., sl, :], (None if r is None else r[..., sl, :])

    def log_prob(
        self,
        pose: Pose,
        descriptors: Tensor | None = None,
        chunk_size: int | None = None,
        method: str = "dense",
    ) -> Tensor:
        """log P(x) = log Σ_i w_i K(x | μ_i) with the hard cut-offs (Eq. surface_feature_probability).

        Args:
            pose: query poses, ``p (*B', M, 3)``, ``q (*B', M, 4)``; ``*B'`` broadcasts with ``batch_shape``.
            descriptors: query descriptors ``(*B', M, k)``; None evaluates the density over SE(3) alone
                (marginal over descriptors, see the module docstring).
            chunk_size: queries per dense ``(chunk, N)`` block; None picks one bounded in memory.
            method: ``"dense"`` (the reference: every query against every kernel) or ``"fast"``:
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

        Precision: the dense path expands squared distances (|x|² − 2x·μ + |μ|², one matmul) around the
        weighted kernel centre, so in float32 the error of β d_p is about 1e-7 · (distance to that
        centre / p_std)² and that of β d_q about 1e-7 · κ (both paths); use float64 densities for
        extreme ratios. The fast path subtracts directly.
        """
        if method not in ("dense", "fast"):
            raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}")
        if method == "fast" and descriptors is None:
            index = self.fast_index()
            # uncompiled, the dense reference is as fast as an eager fused pass for small densities
            if index.linear and (index.blocks or fast_path_compiled(self.device)):
                p, q, _ = self._prepare_queries(pose, None)
                return index.log_prob(p, q)
        if method == "fast" and descriptors is not None and len(self.batch_shape) == 0:
            table = self._descriptor_table()
            if table is not None:
                p, q, r = self._prepare_queries(pose, descriptors)
                return self._fast_log_prob_descriptors(table, p, q, r)
        if _STRAIGHTFORWARD.get():
            return self._straightforward_log_prob(*self._prepare_queries(pose, descriptors))
        out = [
            _logsumexp_last(self._chunk_log_kernels(p, q, r, with_weights=True))
            for p, q, r in self._iter_chunks(pose, descriptors, chunk_size)
        ] if not _needs_grad(pose, descriptors) else self._differentiable_log_prob(pose, descriptors, chunk_size)
        if not out:  # M = 0
            p, _, _ = self._prepare_queries(pose, descriptors)
            shape = torch.broadcast_shapes(p.shape[:-2], self.batch_shape) + (0,)
            return torch.empty(shape, dtype=self.dtype, device=self.device)
        return torch.cat(out, -1)

    def _differentiable_log_prob(self, pose: Pose, descriptors: Tensor | None, chunk_size: int | None
                                 ) -> list[Tensor]:
        """The dense path's chunks with out-of-place operations, so gradients flow to the queries (the
        in-place passes of :meth:`_chunk_log_kernels` overwrite what autograd needs): the same values."""
        out = []
        for p, q, r in self._iter_chunks(pose, descriptors, chunk_size):
            neg_p = torch.matmul(_augment_query(p - self._p_centre), self._p_aug_t).clamp_max(0.0)
            neg_q = (torch.matmul(q, self._q_kappa_t).abs() - self._kappa).clamp_max(0.0)
            terms = [neg_p, neg_q]
            if r is not None:
                x = (r - self._r_centre) * self._r_inv_sqrt_sigma
                terms.append(torch.matmul(_augment_query(x), self._r_aug_t).clamp_max(0.0))
            total = self._log_w.unsqueeze(-2)
            for neg, delta in zip(terms, self.bandwidth.delta, strict=False):
                total = total + torch.where(neg > -delta, neg, torch.full_like(neg, -math.inf))
            # a query no kernel reaches is -inf; its logsumexp is taken of zeros and masked, so the
            # gradient there is 0 instead of exp(−inf + inf) = NaN
            reached = torch.isfinite(total).any(-1, keepdim=True)
            safe = torch.logsumexp(torch.where(reached, total, torch.zeros_like(total)), -1)
            out.append(torch.where(reached.squeeze(-1), safe, torch.full_like(safe, -math.inf)))
        return out

    def _straightforward_log_prob(self, p: Tensor, q: Tensor, r: Tensor | None) -> Tensor:
        """log_prob the textbook way (see :func:`straightforward_evaluation`): ``(*BB, M)``."""
        batch = torch.broadcast_shapes(p.shape[:-2], self.batch_shape)
        m, n = p.shape[-2], self.num_kernels
        flat = batch.numel()
        p = p.expand(*batch, m, 3).reshape(flat, m, 3)
        q = q.expand(*batch, m, 4).reshape(flat, m, 4)
        kernel_p = self._p.expand(*batch, n, 3).reshape(flat, n, 3)
        kernel_q = self._q.expand(*batch, n, 4).reshape(flat, n, 4)
        log_w = self._log_w.expand(*batch, n).reshape(flat, n)
        beta = self._beta.expand(*batch, 3).reshape(flat, 3)
        bw = self.bandwidth
        delta_p, delta_q, delta_r = bw.delta
        if r is not None:
            inv_sqrt_sigma = torch.tensor(bw.sigma_r, dtype=torch.float64).rsqrt().to(self.device, self.dtype)
            k = r.shape[-1]
            r = (r * inv_sqrt_sigma).expand(*batch, m, k).reshape(flat, m, k)
            kernel_r = (self._r * inv_sqrt_sigma).expand(*batch, n, k).reshape(flat, n, k)
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

    def _descriptor_table(self) -> tuple[Tensor, Tensor] | None:
        """Kernels as rows ``(8 + k, N)`` (p, q, log w relative to the largest, r) and that largest log w,
        for the fused pass with descriptors; None when the weights cannot be summed in the linear domain.
        Built on first use and cached."""
        if "_fast_descriptor_table" not in self.__dict__:
            top = self._log_w.amax()
            relative = self._log_w - top
            rows = torch.cat([self._p, self._q, relative.unsqueeze(-1), self._r], -1).T.contiguous()
            self._fast_descriptor_table = (rows, top) if _linear_sums_exact(relative) else None
        return self._fast_descriptor_table

    def _fast_log_prob_descriptors(self, table: tuple[Tensor, Tensor], p: Tensor, q: Tensor, r: Tensor) -> Tensor:
        """log_prob of one density (batch shape ()) with descriptors in one fused pass per chunk."""
        rows, top = table
        shape = p.shape[:-1]
        x = torch.cat([p, q, r], -1).reshape(-1, p.shape[-1] + q.shape[-1] + r.shape[-1]).T.contiguous()
        bw = self.bandwidth
        beta = self._beta.double()
        scale = torch.stack([beta[0] / bw.sigma_p, beta[1] / bw.sigma_q, beta[2]]).to(self.dtype)
        r_scale = (1.0 / torch.tensor(bw.sigma_r, dtype=torch.float64)).to(device=x.device, dtype=self.dtype)
        evaluate = fused_function("descriptor_sums", _descriptor_sums, x.device)
        step = max(1, _DEFAULT_BLOCK_ELEMENTS // rows.shape[1])
        total = torch.cat([evaluate(x[:, s : s + step], rows, scale, r_scale, *bw.delta)
                           for s in range(0, x.shape[1], step)])
        return (torch.log(total) + top).reshape(shape)

    def mean_shift(self, pose: Pose, chunk_size: int | None = None, method: str = "dense") -> Pose:
        """One mean-shift step of every query towards a local mode of the density over SE(3).

        With responsibilities ``a_i ∝ w_i K(x | μ_i)`` (cut-offs included) the step is
        ``p ← Σ a_i μ_p,i`` and ``q ← normalise(Σ a_i s_i μ_q,i)``, ``s_i = sign<q, μ_q,i>``: the
        fixed-point equations of a maximum of ``Σ w_i K(x | μ_i)`` (the Gaussian's and the vMF's
        stationarity conditions), so a mode is a fixed point. A query of zero density stays where it is.
        ``method="fast"`` sums the moments over the leaf blocks in reach (large densities only);
        ``"dense"`` forms every query's responsibilities. Poses ``(*B', M)`` → ``(*broadcast, M)``.
        """
        if method not in ("dense", "fast"):
            raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}")
        if method == "fast" and self._r is None:
            index = self.fast_index()
            if index.linear and index.blocks:
                p, q, _ = self._prepare_queries(pose, None)
                return index.mean_shift(p, q)
        new_p, new_q = [], []
        for p, q, _ in self._iter_chunks(pose, None, chunk_size):
            logits = self._chunk_log_kernels(p, q, None, with_weights=True)  # (*BB, m, N)
            alive = torch.isfinite(logits).any(-1, keepdim=True)
            a = torch.softmax(torch.where(alive, logits, torch.zeros_like(logits)), -1) * alive
            sign = torch.where(q @ self._q.transpose(-1, -2) < 0, -1.0, 1.0).to(a.dtype)
            moved_p = a @ self._p
            moved_q = (a * sign) @ self._q
            moved_q = moved_q / moved_q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
            new_p.append(torch.where(alive, moved_p, p.expand_as(moved_p)))
            new_q.append(torch.where(alive, moved_q, q.expand_as(moved_q)))
        return Pose(torch.cat(new_p, -2), torch.cat(new_q, -2))

    def fast_index(self) -> _FastIndex:
        """The fast path's leaf blocks of this density (built on first use, then cached)."""
        index = self.__dict__.get("_fast_index")
        if index is None:
            index = _FastIndex(self)
            self._fast_index = index
        return index

    def __call__(self, pose: Pose, descriptors: Tensor | None = None) -> Tensor:
        """Alias of :meth:`log_prob`, so a PoseKDE is itself a ``log_prob_fn`` for annealing."""
        return self.log_prob(pose, descriptors)

    def log_kernels(self, pose: Pose, descriptors: Tensor | None = None) -> Tensor:
        """Per-kernel log K(x | μ_i) (weights not included): dense ``(*BB, M, N)``, -inf at cut-offs.

        Use it for the contact-frame terms of Eq. pdf_motion; memory is ``M × N`` per batch element.
        """
        p, q, r = self._prepare_queries(pose, descriptors)
        return self._chunk_log_kernels(p, q, r, with_weights=False)

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
        p, q, r = self._prepare_queries(pose, descriptors)
        bd_p, bd_q, bd_r = self._scaled_terms(p, q, r)
        if bd_r is None:
            bd_r = torch.zeros_like(bd_p)
        return torch.stack(torch.broadcast_tensors(bd_p, bd_q, bd_r), -1)

    # -- trial rounds --------------------------------------------------------------------------

    def _coverage(
        self, pose: Pose, descriptors: Tensor | None, chunk_size: int | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Per batch element: surviving (query, kernel) pairs ``(*B,)``, cut-offs per factor ``(*B, 3)``
        and the smallest β·d per factor ``(*B, 3)``, over valid (non-padding) kernels."""
        delta = self.bandwidth.delta
        valid = self._log_w > -math.inf  # (*B, N)
        batch = self.batch_shape
        survivors = torch.zeros(batch, dtype=torch.int64, device=self.device)
        cuts = torch.zeros(*batch, 3, dtype=torch.int64, device=self.device)
        nearest = torch.full((*batch, 3), math.inf, dtype=self.dtype, device=self.device)
        for p, q, r in self._iter_chunks(pose, descriptors, chunk_size):
            terms = self._scaled_terms(p, q, r)
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
                nearest[..., k] = torch.minimum(nearest[..., k], _amin_to_size(masked, batch))
            survivors += alive.sum((-1, -2)).sum_to_size(batch)
        return survivors, cuts, nearest

    def fit_trial_rounds(
        self, pose: Pose, descriptors: Tensor | None = None, chunk_size: int | None = None
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
        p, _, _ = self._prepare_queries(pose, descriptors)
        if p.shape[-2] == 0:
            return self
        current = self
        max_rounds = self.bandwidth.max_trial_rounds
        while True:
            survivors, cuts, nearest = current._coverage(pose, descriptors, chunk_size)
            failed = survivors == 0
            if not failed.any():
                return current
            rounds = current._trial_rounds
            exhausted = failed & (rounds.sum(-1) >= max_rounds)
            if exhausted.any():
                where = exhausted.nonzero().tolist()
                first = tuple(where[0])
                raise ModelError(
                    f"no kernel covers any query after {max_rounds} trial rounds"
                    f" (T=(T_p, T_q, T_r)={tuple(rounds[first].tolist())}) for batch element(s)"
                    f" {where[:5]}{'...' if len(where) > 5 else ''}; the smallest scaled distances β·d there"
                    f" are (p, q, r)={tuple(round(v, 3) for v in nearest[first].tolist())} against cut-offs"
                    f" δ={tuple(round(v, 3) for v in self.bandwidth.delta)}. The queries lie far outside the"
                    " model: widen the bandwidth, relax cutoff_std or raise max_trial_rounds."
                )
            eligible = cuts > 0
            big = torch.iinfo(torch.int64).max
            masked_rounds = torch.where(eligible, rounds, torch.full_like(rounds, big))
            smallest = masked_rounds.amin(-1, keepdim=True)
            candidates = eligible & (rounds == smallest)
            choice = torch.where(candidates, cuts, torch.full_like(cuts, -1)).argmax(-1)
            step = torch.nn.functional.one_hot(choice, 3) * failed.unsqueeze(-1)
            current = current._replace(_trial_rounds=rounds + step)

    # -- sampling ------------------------------------------------------------------------------

    def sample_kernels(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """Kernel indices ``(*B, n)`` drawn with probability w_i (padding is never drawn)."""
        if isinstance(n, bool) or int(n) != n or n < 0:
            raise InvalidParameterError(f"number of samples must be an integer >= 0, got {n!r}")
        n = int(n)
        flat = self._log_w.reshape(-1, self.num_kernels).double().exp()
        if n == 0:
            return torch.zeros(*self.batch_shape, 0, dtype=torch.int64, device=self.device)
        idx = torch.multinomial(flat, n, replacement=True, generator=generator)
        return idx.reshape(*self.batch_shape, n)

    def kernel_means(self, index: Tensor) -> Pose:
        """Gather kernel means at ``index (*B, n)`` → Pose ``(*B, n)``."""
        p = torch.gather(self._p, -2, index.unsqueeze(-1).expand(*index.shape, 3))
        q = torch.gather(self._q, -2, index.unsqueeze(-1).expand(*index.shape, 4))
        return Pose(p, q)

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
        offset = _sample_translation_offsets(std, delta_p, generator)
        kappa = beta[..., 1] / self.bandwidth.sigma_q
        around_identity = _sample_rotation_offsets(kappa, delta_q, generator)
        p = mean.p + offset.to(self.dtype)
        q = pkt.quaternion_raw_multiply(mean.q.double(), around_identity)
        q = q / q.norm(dim=-1, keepdim=True)
        return Pose(p, q.to(self.dtype)), index


def _needs_grad(pose: Pose, descriptors: Tensor | None) -> bool:
    """Whether autograd records a density evaluation of these queries."""
    tensors = [pose.p, pose.q] + ([] if descriptors is None else [descriptors])
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def _logsumexp_last(x: Tensor) -> Tensor:
    """logsumexp over the last dim, consuming ``x`` in place; all ``-inf`` gives ``-inf``.

    ``torch.logsumexp`` over a long last dim is several times slower on CPU than these four passes.
    """
    peak = x.amax(-1, keepdim=True)
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))  # small: (*BB, m, 1)
    return x.sub_(peak).exp_().sum(-1).log_().add_(peak.squeeze(-1))


def _amin_to_size(x: Tensor, size: torch.Size) -> Tensor:
    """Min-reduce broadcast dims of ``x`` down to ``size`` (the min analogue of ``sum_to_size``)."""
    for dim, (have, want) in enumerate(zip(x.shape, size, strict=False)):
        if want == 1 and have != 1:
            x = x.amin(dim, keepdim=True)
    return x.expand(size) if x.shape != size else x


# --------------------------------------------------------------------------------------------------
# Fast path: kernels pruned by the hard cut-offs, fused evaluation
# --------------------------------------------------------------------------------------------------
#
# The cut-offs make every kernel exactly zero beyond a translation radius and a rotation angle. For a
# density with many kernels (a query density: 3,000), kernels are put once into leaf blocks of a k-d
# tree over (position, rotation); a query visits only the blocks whose bounding box and rotation cap
# come within the cut-offs (a bound: nothing that could survive is skipped) and each visited block is
# evaluated with the exact distances in one fused pass. A density with few kernels (an expert of the
# product: ~500, most of them near every candidate) is evaluated in one fused dense pass instead.
# Sums run in the linear domain relative to each density's largest weight: a surviving kernel factor is
# at least e^(−δ_p−δ_q), so nothing underflows unless weights span ~e^60 (then the dense reference
# path is used). With a C++ compiler (CPU) or Triton (CUDA) the fused functions are compiled by
# torch.compile in processes that declared a long run (``PUSHTORCH_COMPILE``: ``auto`` default, ``1``
# insist, ``0`` never); otherwise the same functions run eagerly, in chunks.

FAST_LEAF_SIZE = 16  # kernels per leaf block: prunes best on the paper-scale query densities (measured)
# Densities with at most this many kernels skip the blocks: pruning cannot pay for its bookkeeping.
FAST_DENSE_KERNELS = 1024
# Relative slack on the pruning bounds: float rounding of a bound must never skip a live kernel.
_BOUND_SLACK = 1e-3
_COMPILE_ENV = "PUSHTORCH_COMPILE"
_compiled_functions: dict[str, Callable] = {}
_compile_failed: set[str] = set()
_compiler_found: list[bool] = []  # cached shutil.which answer
_long_run = [False]  # declare_long_run: compiling pays in this process
# Inductor stores an intermediate that is read twice (the distance d in `where(d < δ, exp(w − d), 0)`)
# as a full (queries × kernels) buffer and reduces it in a second loop; recomputing it in the one fused
# loop is ~7× faster on CPU (measured on the query density's group sums: 12.3 → 1.6 ms).
_INDUCTOR_OPTIONS = {"realize_reads_threshold": 1000}


def _compile_mode() -> str:
    mode = os.environ.get(_COMPILE_ENV, "auto").strip().lower()
    if mode not in ("auto", "1", "0"):
        raise InvalidParameterError(f"{_COMPILE_ENV} must be auto, 1 or 0, got {mode!r}")
    return mode


def declare_long_run(enabled: bool = True) -> None:
    """Tell the fast path that this process makes many predictions, so compiling pays (``auto`` mode).

    torch.compile traces and generates code on a function's first calls: 5-9 s on a 2-core CPU before the
    first prediction, against ~0.2 s of eager evaluation saved per prediction at the quickstart's sizes
    (``tools/bench_cold.py``). A library user's single ``predict`` therefore runs eagerly; the experiment
    app (``python -m pushtorch``), the paper reproduction and the prediction benchmark declare a long run.
    """
    _long_run[0] = bool(enabled)


def fast_path_compiled(device: torch.device | str = "cpu") -> bool:
    """Whether the fast path's fused functions are compiled with torch.compile on ``device``.

    ``PUSHTORCH_COMPILE=0`` never compiles; ``1`` always tries; ``auto`` (default) compiles in a process
    that declared a long run (:func:`declare_long_run`), on CUDA and on CPU when a C++ compiler is on the
    PATH (Inductor needs one), and otherwise runs eagerly, so a first prediction is never slower than
    eager evaluation. A compilation that fails at run time falls back to eager evaluation with a warning,
    once.
    """
    mode = _compile_mode()
    if mode == "0":
        return False
    if mode == "1":
        return True
    if not _long_run[0]:
        return False
    if torch.device(device).type == "cuda":
        return True
    if not _compiler_found:
        _compiler_found.append(any(shutil.which(cc) is not None for cc in ("g++", "c++", "clang++", "cl")))
    return _compiler_found[0]


def fused_function(name: str, fn: Callable, device: torch.device | str) -> Callable:
    """``fn`` compiled with torch.compile if :func:`fast_path_compiled` allows it, else ``fn`` itself.

    For the fast paths' pure tensor functions (no generators, no data-dependent shapes inside). One
    compiled function per ``name`` and device type, shared by every caller; shapes that change between
    calls are made dynamic by torch.compile's automatic dynamic shapes. A failing compilation warns once
    and falls back to ``fn``.
    """
    device = torch.device(device)
    if name in _compile_failed or not fast_path_compiled(device):
        return fn
    key = f"{name}:{device.type}"
    if key not in _compiled_functions:
        from torch._inductor import config as inductor_config

        # torch.compile refuses option names its Inductor does not know (older torch): leave those out
        options = {k: v for k, v in _INDUCTOR_OPTIONS.items() if hasattr(inductor_config, k)}
        compiled = torch.compile(fn, dynamic=None, options=options)

        def call(*args):
            if name in _compile_failed:
                return fn(*args)
            try:
                return compiled(*args)
            except Exception as exc:  # a missing/broken compiler surfaces here, on first use
                _compile_failed.add(name)
                warnings.warn(f"torch.compile of the fast kernel path failed ({type(exc).__name__}: {exc});"
                              f" running it eagerly (set {_COMPILE_ENV}=0 to skip compiling)", stacklevel=2)
                return fn(*args)

        _compiled_functions[key] = call
    return _compiled_functions[key]


def _pose_distances(x: Sequence[Tensor], t: Sequence[Tensor], scale_p: Tensor, scale_q: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """The fused passes' kernel distances from the rows of queries ``x`` and kernels ``t`` (p then q, in
    any broadcastable layout): ``(β_p/σ_p |x_p − μ_p|², <x_q, μ_q>, β_q/σ_q (1 − |<x_q, μ_q>|))`` — the
    scaled terms :meth:`PoseKDE.log_prob` cuts off and sums (written out: compiled, nothing is stored)."""
    d_p = ((x[0] - t[0]) ** 2 + (x[1] - t[1]) ** 2 + (x[2] - t[2]) ** 2) * scale_p
    dot = x[3] * t[3] + x[4] * t[4] + x[5] * t[5] + x[6] * t[6]
    return d_p, dot, (1.0 - dot.abs()).clamp_min(0.0) * scale_q


def _dense_sums(x: Tensor, table: Tensor, scale: Tensor, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) for every query against every kernel of its density: ``(Q, M)``.

    x: queries ``(Q, 7, M)`` (rows p, q); table: kernels ``(Q, 8, N)`` (rows p, q, log w relative to the
    largest); scale: ``(Q, 2)`` (β_p/σ_p, β_q/σ_q). Exact distances, the cut-offs of
    :meth:`PoseKDE.log_prob`; compiled, no ``(Q, M, N)`` tensor is stored.
    """
    t = table.unsqueeze(2)  # (Q, 8, 1, N)
    sc = scale[:, :, None, None]
    d_p, _, d_q = _pose_distances(x.unsqueeze(-1).unbind(1), t.unbind(1), sc[:, 0], sc[:, 1])  # x: (Q, 7, M, 1)
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)).sum(-1)


def _linear_sums_exact(relative_log_w: Tensor) -> bool:
    """Whether weights given relative to the largest (``≤ 0``, ``-inf`` padding) can be summed in the
    linear domain: exactly unless a kernel weighs ~e^-60 less than the largest (float32)."""
    live = relative_log_w[relative_log_w > -math.inf]
    return bool((live > math.log(torch.finfo(relative_log_w.dtype).tiny) + 25.0).all())


def _descriptor_sums(x: Tensor, table: Tensor, scale: Tensor, r_scale: Tensor, delta_p: float, delta_q: float,
                     delta_r: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) with descriptors for queries ``x (7 + k, M)`` (rows p, q, r) against kernels
    ``table (8 + k, N)`` (rows p, q, relative log w, r): ``(M,)``. scale: ``(3,)`` (β_p/σ_p, β_q/σ_q,
    β_r), r_scale: ``(k,)`` 1/σ_r. Exact distances and every cut-off of :meth:`PoseKDE.log_prob`."""
    xs = x.unsqueeze(-1)  # (7 + k, M, 1)
    t = table.unsqueeze(1)  # (8 + k, 1, N)
    d_p, _, d_q = _pose_distances(xs, t, scale[0], scale[1])
    d_r = sum((xs[7 + k] - t[8 + k]) ** 2 * r_scale[k] for k in range(r_scale.shape[0])) * scale[2]
    keep = (d_p < delta_p) & (d_q < delta_q) & (d_r < delta_r)
    return torch.where(keep, torch.exp(t[7] - d_p - d_q - d_r), torch.zeros_like(d_p)).sum(-1)


def _reachable_blocks(
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
    ``(P, 8, L)`` and the quaternion dot products ``(P, L)``; arguments as :func:`_block_sums`."""
    density = query_density[pair_query]
    t = table[density * num_blocks + pair_block]  # (P, 8, L)
    xs = x[pair_query].unsqueeze(-1)  # (P, 7, 1)
    sc = scale[density]
    d_p, dot, d_q = _pose_distances(xs.unbind(1), t.unbind(1), sc[:, 0:1], sc[:, 1:2])
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)), t, dot


def _block_sums(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) per query ``(R,)`` over its (query, block) pairs.

    x: ``(R, 7)`` queries; table: ``(D·nb + 1, 8, L)`` blocks (rows p, q, relative log w; kernels along
    L); scale: ``(D, 2)``; query_density: ``(R,)`` each query's density row; pair_query, pair_block:
    ``(P,)`` the pairs. Exact distances and the cut-offs of :meth:`PoseKDE.log_prob`.
    """
    k, _, _ = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p, delta_q)
    return torch.zeros_like(x[:, 0]).index_add(0, pair_query, k.sum(-1))


def _block_moments(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                   pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """The mean-shift moments of each query over its (query, block) pairs: ``(R, 8)``, columns
    ``Σ w K``, ``Σ w K μ_p`` (3) and ``Σ w K s μ_q`` (4) with ``s = sign<x_q, μ_q>``; arguments as
    :func:`_block_sums`."""
    k, t, dot = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p,
                              delta_q)
    ks = torch.where(dot < 0, -k, k)
    moments = torch.stack([k.sum(-1)] + [(k * t[:, i]).sum(-1) for i in range(3)]
                          + [(ks * t[:, i]).sum(-1) for i in range(3, 7)], -1)  # (P, 8)
    return torch.zeros(x.shape[0], 8, dtype=x.dtype, device=x.device).index_add(0, pair_query, moments)


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


class _FastIndex:
    """A PoseKDE's kernels laid out for the fast path: a dense table or pruned leaf blocks."""

    def __init__(self, kde: PoseKDE, leaf: int = FAST_LEAF_SIZE, blocks: bool | None = None) -> None:
        """Lay out ``kde``'s kernels; ``blocks`` forces leaf blocks (True) or the dense table (False),
        None chooses by size (blocks above ``FAST_DENSE_KERNELS`` kernels)."""
        bw = kde.bandwidth
        dtype, device = kde.dtype, kde.device
        n = kde.num_kernels
        self.batch_shape = kde.batch_shape
        d = max(1, self.batch_shape.numel())
        p = kde._p.reshape(d, n, 3)
        q = kde._q.reshape(d, n, 4)
        log_w = kde._log_w.reshape(d, n)
        valid = log_w > -math.inf
        beta = kde._beta.reshape(d, 3).double()
        self.delta_p, self.delta_q, _ = bw.delta
        sp = beta[:, 0] / bw.sigma_p
        kappa = beta[:, 1] / bw.sigma_q
        self.scale = torch.stack([sp, kappa], -1).to(dtype)  # (D, 2)
        self.log_w_max = log_w.amax(-1)  # (D,): every element has a finite weight
        relative = log_w - self.log_w_max.unsqueeze(-1)
        self.linear = _linear_sums_exact(relative)
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
            evaluate = fused_function("dense_sums", _dense_sums, x.device)
            if own and m not in self.groups:
                self.groups[m] = _row_groups(self.counts, m, _DENSE_ROW_GROUPS)
            groups = self.groups[m] if own else [(None, self.table.shape[-1])]
            total = x.new_empty(rows, m)
            for members, width in groups:
                if members is None:
                    table, scale, xg = per_query(self.table)[..., :width], per_query(self.scale), x_t
                else:
                    table, scale, xg = self.table[members, :, :width], self.scale[members], x_t[members]
                streamed = compiled and "dense_sums" not in _compile_failed
                step = m if streamed else max(1, _DEFAULT_BLOCK_ELEMENTS // max(1, table.shape[0] * width))
                part = torch.cat([evaluate(xg[..., s : s + step], table, scale, self.delta_p, self.delta_q)
                                  for s in range(0, m, step)], -1)
                if members is None:
                    total = part
                else:
                    total[members] = part
        else:
            total = self._pair_sums("block_sums", _block_sums, x, density, own, ())
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
        """``fn`` (:func:`_block_sums` or :func:`_block_moments`) summed over the (query, block) pairs
        in reach: ``(rows · M, *columns)``."""
        rows, m = x.shape[:2]
        bounds = [t if own else t[density] for t in (self.lo, self.hi, self.centre, self.cos_reach, self.r2)]
        # compiled reach is ~10x faster with a float result; nonzero is faster on bool
        reach = fused_function("reach", _reachable_blocks, x.device)(x.transpose(1, 2), *bounds) > 0
        pair_query, pair_block = reach.reshape(rows * m, self.num_blocks).nonzero(as_tuple=True)
        query_density = density.repeat_interleave(m)
        flat_x = x.reshape(rows * m, 7)
        evaluate = fused_function(name, fn, x.device)
        # eager evaluation materialises (pairs, 8, L): chunk it; compiled code streams it
        streamed = fast_path_compiled(x.device) and name not in _compile_failed
        step = pair_query.numel() if streamed else _DEFAULT_BLOCK_ELEMENTS // (8 * self.table.shape[-1])
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
            return Pose(p.expand(*batch, m, 3), q.expand(*batch, m, 4))
        moments = self._pair_sums("block_moments", _block_moments, x, density, own, (8,)).reshape(*batch, m, 8)
        p, q = p.expand(*batch, m, 3), q.expand(*batch, m, 4)
        alive = moments[..., :1] > 0
        moved_q = moments[..., 4:]
        moved_q = moved_q / moved_q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        return Pose(torch.where(alive, moments[..., 1:4] / moments[..., :1].clamp_min(1e-30), p),
                    torch.where(alive, moved_q, q))

# --------------------------------------------------------------------------------------------------
# Product of experts
# --------------------------------------------------------------------------------------------------


def product_log_prob(
    experts: PoseKDE,
    pose: Pose,
    expert_log_weight: Tensor | None = None,
    expert_mask: Tensor | None = None,
    chunk_size: int | None = None,
    method: str = "dense",
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

    def log_prob(self, pose: Pose, chunk_size: int | None = None, method: str = "dense") -> Tensor:
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
    d_p, dot, d_q = _pose_distances(xs.unbind(2), t.unbind(2), sc[:, :, 0], sc[:, :, 1])
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
        self.rounds = PoseKDE._rounds_tensor(trial_rounds, batch, device)
        beta = torch.pow(torch.tensor(bandwidth.alpha_t, dtype=torch.float64), -self.rounds.double()).reshape(d, 3)
        self.scale = torch.stack([beta[:, 0] / bandwidth.sigma_p, beta[:, 1] / bandwidth.sigma_q], -1).to(dtype)
        self.table = torch.cat([means.p, means.q], -1).reshape(d, k, 7).contiguous()  # (D, K, 7)
        self.weights = relative.exp().reshape(n_experts, d, k).transpose(0, 1).contiguous()  # (D, E, K)
        self.offset = offset.reshape(n_experts, d, 1).transpose(0, 1).contiguous()  # (D, E, 1)
        self.exponent = exponent.reshape(n_experts, d, 1).transpose(0, 1).contiguous()  # (D, E, 1), 0: left out
        self.delta_p, self.delta_q, _ = bandwidth.delta

    def log_prob(self, pose: Pose) -> Tensor:
        """``Σ_e (log w^P_e + γ_e log P_e(pose))`` for poses ``(*B, M)`` → ``(*B, M)``; ``-inf`` where a counted
        expert has no kernel within its cut-offs.

        Raises:
            InvalidPoseError: (``validate_args``) misshaped, non-finite or non-unit queries.
        """
        self._check_queries(pose)
        out = self._per_problem("shared_kernel_product", _shared_kernel_product, pose,
                                self.table, self.weights, self.scale, self.offset, self.exponent)
        return out.reshape(*self.batch_shape, pose.p.shape[-2])

    def mean_shift(self, pose: Pose) -> Pose:
        """One mean-shift step of every query towards a local mode of the product (see
        :meth:`PoseKDE.mean_shift`; the experts' weights w^P do not move a mode): poses ``(*B, M)``."""
        self._check_queries(pose)
        out = self._per_problem("shared_kernel_shift", _shared_kernel_shift, pose,
                                self.table, self.weights, self.scale, self.exponent)
        out = out.transpose(1, 2).reshape(*self.batch_shape, pose.p.shape[-2], 7)
        return Pose(out[..., :3], out[..., 3:])

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

    def _per_problem(self, name: str, fn: Callable, pose: Pose, *layout: Tensor) -> Tensor:
        """``fn`` (fused) over the queries ``(D, 7, M)`` and this product's per-problem ``layout`` tensors,
        in chunks of problems that keep the ``(problems × K × M)`` kernel values cache-sized (~8 MB)."""
        d, m = self.table.shape[0], pose.p.shape[-2]
        x = torch.cat([pose.p, pose.q], -1).expand(*self.batch_shape, m, 7).reshape(d, m, 7)
        x = x.transpose(1, 2).contiguous()  # (D, 7, M): a strided view compiles ~6x slower (measured)
        evaluate = fused_function(name, fn, x.device)
        step = max(1, _DEFAULT_BLOCK_ELEMENTS // max(1, m * self.table.shape[1]))
        return torch.cat([evaluate(x[s : s + step], *(t[s : s + step] for t in layout), self.delta_p, self.delta_q)
                          for s in range(0, d, step)], 0)

    def __call__(self, pose: Pose) -> Tensor:
        return self.log_prob(pose)
