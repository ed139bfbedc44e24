"""Kernel density estimation over SE(3), optionally × R^k descriptors, batched in torch.

One module per concern: :mod:`~pushtorch.kde.bandwidth` (bandwidths, trial rounds, the distances),
:mod:`~pushtorch.kde.density` (:class:`PoseKDE`: the density, its dispatch, mean shift, sampling),
:mod:`~pushtorch.kde.queries` (a density's queries: checks, broadcasting, chunks), :mod:`~pushtorch.kde.dense`
(the dense reference), :mod:`~pushtorch.kde.straightforward` (the textbook evaluation),
:mod:`~pushtorch.kde.rounds` (the trial-round search), :mod:`~pushtorch.kde.reductions` (the dense reference's
distances and reductions), :mod:`~pushtorch.kde.sampling` (one kernel factor's exact draws),
:mod:`~pushtorch.kde.fused` (how the fast path's fused functions run: compiled or eager, in chunks),
:mod:`~pushtorch.kde.kernel_sums` (the fused functions themselves), :mod:`~pushtorch.kde.fast_index` (kernels
laid out for the fast path), :mod:`~pushtorch.kde.products` (products of experts),
:mod:`~pushtorch.kde.annealing` (densities that anneal themselves: the fast annealing steps fused with a
density's evaluation, for :func:`pushtorch.anneal.anneal`) and :mod:`~pushtorch.kde.normaliser` (the
normalising constants of kernels and of products of experts); :mod:`~pushtorch.kde.method` names the two
evaluation methods (:class:`Evaluation`). This package re-exports the public names.

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

Two evaluation paths give the same values (:class:`Evaluation`, or its string, wherever ``method=`` is
taken): ``method="dense"`` (the reference, every query against every kernel with matmuls) and
``method="fast"`` (exact distances in fused, optionally compiled passes, pruned by the hard cut-offs to the
leaf blocks of kernels that can reach a query; :mod:`pushtorch.kde.fast_index`).
Inside :func:`straightforward_evaluation` the dense reference is evaluated the textbook way instead
(``cdist`` and the quaternion dot for all queries at once, cut-offs, ``logsumexp``): the baseline the
prediction benchmark times for scale, and an oracle for both paths.
"""

from pushtorch.kde.annealing import AnnealInputs, AnnealOutcome, DrawnSteps, FusedAnnealing
from pushtorch.kde.bandwidth import (
    COMPONENTS,
    KernelBandwidth,
    TrialRounds,
    descriptor_distance,
    descriptor_distance_unscaled,
    rotation_distance,
    translation_distance,
)
from pushtorch.kde.density import PoseKDE
from pushtorch.kde.fast_index import FAST_DENSE_KERNELS, FAST_LEAF_SIZE
from pushtorch.kde.fused import (
    declare_long_run,
    fast_path_compiled,
    fused_function,
    share_compiled,
    shared_compiled_folder,
)
from pushtorch.kde.method import Evaluation
from pushtorch.kde.products import ProductOfExperts, SharedKernelProduct, product_log_prob
from pushtorch.kde.straightforward import straightforward_evaluation

__all__ = [
    "AnnealInputs",
    "AnnealOutcome",
    "COMPONENTS",
    "DrawnSteps",
    "Evaluation",
    "FAST_DENSE_KERNELS",
    "FAST_LEAF_SIZE",
    "FusedAnnealing",
    "KernelBandwidth",
    "PoseKDE",
    "ProductOfExperts",
    "SharedKernelProduct",
    "TrialRounds",
    "declare_long_run",
    "descriptor_distance",
    "descriptor_distance_unscaled",
    "fast_path_compiled",
    "fused_function",
    "product_log_prob",
    "rotation_distance",
    "share_compiled",
    "shared_compiled_folder",
    "straightforward_evaluation",
    "translation_distance",
]
