"""Exact draws of one kernel factor, truncated at its cut-off (the translation's Gaussian, the rotation's vMF
pair): what :meth:`pushtorch.kde.PoseKDE.sample` is made of (:func:`sample_translation_offsets`,
:func:`sample_rotation_offsets`).

Paper, Background → Kernel Density Estimation: the cut-off Gaussian N3 of the translation and the antipodal
von Mises–Fisher pair Θ of the rotation (Eq. surface_feature_kernel), each sampled exactly where ``β d < δ``,
so every draw has the finite density :meth:`pushtorch.kde.PoseKDE.log_prob` gives it.
"""

from __future__ import annotations

import torch

from pushtorch.se3 import draw_device, truncated_gamma_1p5, vmf_offsets
from pushtorch.streams import is_keyed

Tensor = torch.Tensor

__all__ = ["sample_kernel_offsets", "sample_rotation_offsets", "sample_translation_offsets"]

# --------------------------------------------------------------------------------------------------
# Samplers for one kernel factor (exact, truncated at the cut-off)
# --------------------------------------------------------------------------------------------------


def _unit_vectors(shape: tuple[int, ...], generator, device) -> Tensor:
    if is_keyed(generator):
        v = generator.normal((*shape, 3), torch.float64).to(device)
    else:
        v = torch.randn(*shape, 3, generator=generator, dtype=torch.float64,
                        device=draw_device(generator, device)).to(device)
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def sample_translation_offsets(
    std: Tensor, delta_p: float, generator: torch.Generator | None
) -> Tensor:
    """Offsets ``(..., 3)`` (float64): isotropic Gaussian of per-axis ``std (...)``, cut at β d_p < δ_p."""
    x = truncated_gamma_1p5(torch.full_like(std, delta_p), generator)
    radius = torch.sqrt(2.0 * x) * std  # β d_p = |Δ|² / (2 std²) = x
    return radius.unsqueeze(-1) * _unit_vectors(tuple(std.shape), generator, std.device)


def sample_rotation_offsets(kappa: Tensor, delta_q: float, generator: torch.Generator | None) -> Tensor:
    """Unit quaternions ``(..., 4)`` (float64) around identity, density ∝ exp(κ|w|), cut at κ(1−|w|) < δ_q
    (:func:`pushtorch.se3.vmf_offsets`, the library's one vMF sampler)."""
    return vmf_offsets(kappa, kappa.shape, generator, torch.float64, kappa.device, delta_q)


def sample_kernel_offsets(std: Tensor, kappa: Tensor, delta_p: float, delta_q: float,
                          generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """One draw around a kernel mean per element of ``std`` and ``kappa`` (same shape): translation offsets
    ``(..., 3)`` and rotation offsets ``(..., 4)`` (float64, around the identity), each cut at its cut-off; the
    translation drawn first (:meth:`pushtorch.kde.PoseKDE.sample`'s draws)."""
    return sample_translation_offsets(std, delta_p, generator), sample_rotation_offsets(kappa, delta_q, generator)
