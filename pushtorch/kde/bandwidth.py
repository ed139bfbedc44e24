"""Kernel bandwidths, trial rounds and the paper's distances d_p, d_q, d_r, d'_r (Background → Kernel Density
Estimation; units and cut-offs as :mod:`pushtorch.kde` says): :class:`KernelBandwidth`, :class:`TrialRounds`
and :func:`trial_rounds_tensor` (a density's rounds per batch element), the distance functions."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from pushtorch.errors import InvalidParameterError

Tensor = torch.Tensor

COMPONENTS = ("p", "q", "r")

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


def trial_rounds_tensor(rounds: TrialRounds | Tensor | None, batch: torch.Size, device) -> Tensor:
    """Trial rounds as the ``(*batch, 3)`` int64 tensor a density keeps: a :class:`TrialRounds` for every batch
    element, an integer tensor ``(*batch, 3)`` or ``(3,)``, or None for (0, 0, 0).

    Raises:
        InvalidParameterError: a tensor that is not integer, negative rounds, or a shape that does not
            broadcast to ``(*batch, 3)``.
    """
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
