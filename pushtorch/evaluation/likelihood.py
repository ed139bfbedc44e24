"""The likelihood score: how probable the true outcome is under a predicted density (issue 15, item 2).

Paper, §Motion Model: the method predicts a *density* over the object's final pose, the product of experts of
Eq. poe; its experiments score only the density's mode (Eq. pam). ``nll`` scores the density itself: the
negative log-likelihood of the true final pose, so a prediction that is confidently wrong costs more than one
that is wrong but says it is unsure. Decisions (docs/method.md, "Likelihood score"):

* **Base measure and units.** Densities are taken with respect to Lebesgue measure on positions (m³) times
  the uniform *probability* measure on SO(3) (q and −q one rotation), so ``nll`` is in nats: one kernel of
  the model's motion bandwidth (1 cm, 0.05 rad) scores −21.7 at its own centre (−11.1 from the position,
  −10.6 from the orientation), and a truth k kernel stds away costs k²/2 nats more. The Haar measure of
  SE(3) is invariant under left and right multiplication, so a density moved by rigid motions keeps its
  values (used below for the displacement sense and the mean-motion baseline).
* **Kernels without cut-offs.** The model's kernels are the paper's cut-off Gaussians and vMF pairs
  (:mod:`pushtorch.kde`); the scored density uses the exact Gaussian × folded vMF kernels the cut-offs
  approximate, with the model's bandwidths and trial rounds, so a truth beyond every kernel's reach gets a
  large finite ``nll`` instead of +inf.
* **Normalisation.** Each expert is a normalised mixture; the product of experts is normalised by importance
  sampling (:func:`log_normaliser`), proposals from the experts, from wider experts and from narrow kernels
  at the prediction's annealed candidates; each expert enters raised to its exponent ``γ_e``.
* **Displacement sense.** A prediction is a density over ``B̂1`` given the estimated start ``B̂0``; the
  truth enters as its displacement applied to that start, ``x* = B1 ∘ S ∘ B0⁻¹ ∘ B̂0`` for each symmetry
  ``S`` of the test object, and the nearest copy (largest density) is scored, as H_acc scores the nearest
  copy. A continuous symmetry is scanned on a 3° grid and refined to 0.25°.
* **Calibration.** A density's ``α`` highest-density region is ``{x : log p(x) ≥ t_α}``, in the 7-D pose space,
  with ``t_α`` the ``1 − α`` quantile of ``log p`` over :data:`COVERAGE_SAMPLES` draws from the density itself
  (:func:`hdr_thresholds`), each draw scored as a truth is (its nearest symmetric copy); a truth is inside when
  its score (``−nll``, the nearest symmetric copy, as above) reaches ``t_α``. The draws are first moved onto the
  plane of the estimated start (x, y and the twist about world z kept; height and tilt the start's), where the
  truths of pushes on a table lie: scored in all seven dimensions, the draws' spread in height, roll and pitch
  would lower ``t_α`` below what a planar truth at the same distance scores, and every density would look wider
  than it is. A truth that leaves the plane (a toppled object) is scored as it is, and counts against the region.
  ``coverage_50`` and ``coverage_90`` are the shares of truths inside: a calibrated density has 0.5 and 0.9, an
  overconfident one less. Point predictions have no such region and get none.
* **Baselines.** The mean-motion baseline's density is an isotropic Gaussian × folded vMF over the training
  motions in the robot's start frame, fitted by moments (:func:`mean_motion_density`). A point prediction
  (no motion, nearest push, physics) is scored as one kernel of the model's motion bandwidth at the
  predicted pose (:func:`point_density`).
"""

from __future__ import annotations

import math

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.distribution import FinalPoseDistribution
from pushtorch.errors import InvalidParameterError
from pushtorch.kde import KernelBandwidth
from pushtorch.kde.normaliser import (
    IMPORTANCE_SAMPLES,
    log_kernel_normaliser,
    log_normaliser,
    log_rotation_normaliser,
    unit_quaternions,
)
from pushtorch.objects import Symmetry

Tensor = torch.Tensor

__all__ = [
    "COVERAGE_LEVELS",
    "CALIBRATION_CANDIDATES",
    "COVERAGE_SAMPLES",
    "IMPORTANCE_SAMPLES",
    "MIN_P_STD",
    "MIN_ROT_STD",
    "WINSOR",
    "CALIBRATION_RESAMPLES",
    "log_kernel_normaliser",
    "log_normaliser",
    "log_rotation_normaliser",
    "covered",
    "calibrated_choice",
    "ensemble_density",
    "hdr_thresholds",
    "mean_motion_density",
    "motion_product_density",
    "nll",
    "point_density",
    "product_density",
    "symmetric_truths",
    "truth_copies",
]

#: Floors (m, rad) of a fitted mean-motion density: below any spread the simulator resolves, and they keep a
#: baseline whose training pushes all moved alike from an infinite density.
MIN_P_STD = 1e-4
MIN_ROT_STD = 1e-3
#: The levels of the highest-density regions whose coverage is reported (``coverage_50``, ``coverage_90``).
COVERAGE_LEVELS = (0.5, 0.9)
#: Draws from a density that set its regions' thresholds: the 10 % tail's quantile from 40 draws below it.
COVERAGE_SAMPLES = 400
#: The most settings, tied in held-out likelihood, whose held-out coverage :func:`calibrated_choice` measures
CALIBRATION_CANDIDATES = 48
#: The share of paired differences in each tail that :func:`calibrated_choice` winsorises before their SE
WINSOR = 0.05
#: Resamples of the held-out pushes (within each group) that give the SE of a candidate's miscalibration less the
#: least miscalibrated one's, in :func:`calibrated_choice` (from a fixed seed: the choice is reproducible)
CALIBRATION_RESAMPLES = 500
_CONTINUOUS_STEPS = 120  # a 3° grid about a continuous symmetry axis
_REFINE = torch.linspace(-1.5, 1.5, 37, dtype=torch.float64)  # ±1.5 grid steps (±4.5°) in 0.25° steps
#: A draw's search about a continuous axis (:func:`_nearest_copy_scores`): 9 turns over nll's refined span, then 9
#: about the best of them, a quarter as wide
_DRAW_STEPS = (torch.linspace(-1.5, 1.5, 9, dtype=torch.float64) * (2.0 * math.pi / _CONTINUOUS_STEPS),
               torch.linspace(-0.375, 0.375, 9, dtype=torch.float64) * (2.0 * math.pi / _CONTINUOUS_STEPS))


def _full_density(means: se3.Pose, log_weights: Tensor, p_std: float, rot_std: float,
                  trial_rounds: Tensor | None = None, alpha_t: float = 2.0, exponent: Tensor | None = None,
                  frame: tuple[se3.Pose, se3.Pose] | None = None) -> FinalPoseDistribution:
    """Experts ``(E,)`` with uncut kernels at the shared ``means (K,)`` (float32, unit q), normaliser not set."""
    e, k = log_weights.shape
    if means.batch_shape != (k,):
        raise InvalidParameterError(f"the experts share their kernel means: means (K,) = ({k},), got "
                                    f"{tuple(means.batch_shape)}")
    bandwidth = KernelBandwidth(p_std=p_std, rot_std=rot_std, alpha_t=alpha_t)
    shared = se3.Pose.unchecked(means.p.float(), unit_quaternions(means.q.float()))
    rounds = torch.zeros(3, dtype=torch.int64) if trial_rounds is None else torch.as_tensor(trial_rounds)
    gamma = torch.ones(e, dtype=torch.float64) if exponent is None else _exponents_of(e, exponent)
    return FinalPoseDistribution(shared, log_weights.float(), bandwidth, rounds.reshape(-1, 3)[0], gamma, None,
                                 method="dense", kernels="full", frame=frame)


def _exponents_of(experts: int, exponent: Tensor) -> Tensor:
    """``(E,)`` float64 exponents, checked (finite, >= 0, one per expert)."""
    g = torch.as_tensor(exponent, dtype=torch.float64).reshape(-1)
    if g.shape[0] != experts or not torch.isfinite(g).all() or (g < 0).any():
        raise InvalidParameterError(f"expert exponents must be {experts} finite numbers >= 0, got {g.tolist()}")
    return g


def product_density(means: se3.Pose, log_weights: Tensor, p_std: float, rot_std: float,
                    trial_rounds: Tensor | None = None, alpha_t: float = 2.0,
                    generator: torch.Generator | None = None, centres: se3.Pose | None = None,
                    samples: int = IMPORTANCE_SAMPLES, exponent: Tensor | None = None) -> FinalPoseDistribution:
    """The normalised product of experts whose kernels sit at the shared ``means`` (``(K,)``), each expert
    raised to its ``exponent`` ``γ_e`` (``(E,)``, default 1): a :class:`FinalPoseDistribution` with
    ``kernels="full"``.

    Args:
        log_weights: ``(E, K)`` each expert's kernel log-weights (normalised here; ``-inf``: not in it).
        p_std, rot_std: the kernels' bandwidth before trial rounds; trial_rounds ``(3,)``.
        generator: the importance sampler's random stream; centres: where the product's modes are
            believed to be; samples: proposals per expert and part (:func:`log_normaliser`).

    Raises:
        InvalidParameterError: an expert without kernels, or malformed kernels (as :class:`PoseKDE`).
    """
    density = _full_density(means, log_weights, p_std, rot_std, trial_rounds, alpha_t, exponent)
    density._log_z = log_normaliser(density.experts(), generator, samples, centres, exponent)
    return density


def motion_product_density(density, generator: torch.Generator | None = None,
                           candidates: se3.Pose | None = None) -> FinalPoseDistribution:
    """The normalised, uncut form of a prediction's product of experts
    (:class:`pushtorch.models.motion.MotionDensity`), with the density's bandwidth (the calibrated one,
    ``MotionDensity.density_bandwidth``) and the annealing's trial rounds; ``candidates``: the prediction's
    annealed candidates (``Prediction.candidates``), where the product's modes are."""
    means, log_weights = density.shared_kernels()
    bandwidth = density.density_bandwidth
    rounds = density.experts.trial_rounds[0]
    return product_density(means, log_weights, bandwidth.p_std, bandwidth.rot_std, rounds, bandwidth.alpha_t,
                           generator, candidates, exponent=density.expert_exponent)


def point_density(pose: se3.Pose, p_std: float, rot_std: float) -> FinalPoseDistribution:
    """One kernel of bandwidth (p_std, rot_std) at ``pose`` ``()``: how a point prediction is scored."""
    one = se3.Pose.unchecked(pose.p.reshape(1, 3), pose.q.reshape(1, 4))
    density = _full_density(one, torch.zeros(1, 1), p_std, rot_std)
    density._log_z = torch.zeros((), dtype=torch.float64)
    return density


def mean_motion_density(motions: se3.Pose, mean_motion: se3.Pose, robot_start: se3.Pose,
                        object_pose: se3.Pose) -> FinalPoseDistribution:
    """The mean-motion baseline's density: ``B1 = R0 ∘ M ∘ R0⁻¹ ∘ B̂0`` with ``M`` an isotropic Gaussian ×
    folded vMF around ``mean_motion`` fitted to the training ``motions`` ``(N,)`` (robot start frame).

    Moments: ``p_std² = mean |p − p̄|² / 3`` and ``rot_std² = (8/3) mean(1 − |<q, q̄>|)`` (for a Gaussian
    rotation vector of std σ per axis, ``E[1 − |<q, q̄>|] ≈ E[θ²]/8 = 3σ²/8``), floored at
    :data:`MIN_P_STD`, :data:`MIN_ROT_STD`.
    """
    p = motions.p.double().reshape(-1, 3)
    q = motions.q.double().reshape(-1, 4)
    centre_p, centre_q = mean_motion.p.double().reshape(3), mean_motion.q.double().reshape(4)
    if p.shape[0] == 0:
        raise InvalidParameterError("the mean-motion density needs at least one training motion")
    p_std = max(math.sqrt(float(((p - centre_p) ** 2).sum(-1).mean()) / 3.0), MIN_P_STD)
    spread = (1.0 - (q * centre_q).sum(-1).abs()).clamp_min(0.0).mean()
    rot_std = max(math.sqrt(8.0 / 3.0 * float(spread)), MIN_ROT_STD)
    centre = se3.Pose.unchecked(centre_p.reshape(1, 3), centre_q.reshape(1, 4))
    robot = se3.Pose.unchecked(robot_start.p.double().reshape(3), robot_start.q.double().reshape(4))
    start = se3.Pose.unchecked(object_pose.p.double().reshape(3), object_pose.q.double().reshape(4))
    density = _full_density(centre, torch.zeros(1, 1), p_std, rot_std,
                            frame=(robot, se3.compose(se3.inverse(robot), start)))
    density._log_z = torch.zeros((), dtype=torch.float64)
    return density


def _axis_turns(axis: Tensor, angles: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` of turns by ``angles (...)`` about the unit ``axis (3,)``."""
    return pkt.axis_angle_to_quaternion(axis * angles.unsqueeze(-1))


def symmetric_truths(truth_final: se3.Pose, truth_start: se3.Pose, estimate_start: se3.Pose,
                     rotations: Tensor) -> se3.Pose:
    """``B1 ∘ S ∘ B0⁻¹ ∘ B̂0`` for body rotations ``S`` ``(..., G, 4)``: the truth's displacement applied to
    the estimated start, once per symmetric copy. ``truth_final (...)``, starts ``()`` → ``(..., G)``."""
    to_estimate = se3.compose(se3.inverse(truth_start), estimate_start)
    final = se3.Pose.unchecked(truth_final.p.unsqueeze(-2), truth_final.q.unsqueeze(-2))
    turned = se3.compose(final, se3.Pose.unchecked(torch.zeros_like(rotations[..., :3]), rotations))
    moved = se3.compose(turned, se3.Pose.unchecked(to_estimate.p.to(rotations), to_estimate.q.to(rotations)))
    return se3.Pose.unchecked(moved.p, se3.quat_normalize(moved.q))


def nll(density: FinalPoseDistribution, truth_final: se3.Pose, truth_start: se3.Pose, estimate_start: se3.Pose,
        symmetry: Symmetry) -> Tensor:
    """Negative log-likelihood (nats) of true final poses ``(T,)`` under a prediction made from the estimated
    start ``estimate_start`` (the truth moved from ``truth_start``), nearest symmetric copy (module docstring).

    Returns:
        ``(T,)`` float64.
    """
    copies, scores = _copies(density, truth_final, truth_start, estimate_start, symmetry)
    if scores is None:
        return -density.log_prob(copies.vector()).amax(-1)
    return -torch.maximum(scores[0], density.log_prob(copies.vector()).amax(-1))


def truth_copies(density: FinalPoseDistribution, truth_final: se3.Pose, truth_start: se3.Pose,
                 estimate_start: se3.Pose, symmetry: Symmetry) -> se3.Pose:
    """``(T, K)`` the symmetric copies of true final poses ``(T,)`` that :func:`nll` takes the best of under
    ``density``: every discrete copy, or about a continuous axis the 3° grid and its refinement about the grid's
    best under ``density``. What scores one truth under many densities of alike kernels at once (their
    ``log_prob`` at the copies, the best taken after combining them)."""
    copies, scores = _copies(density, truth_final, truth_start, estimate_start, symmetry)
    if scores is None:
        return copies
    return se3.Pose.cat([copies, scores[1]], 1)


def _copies(density, truth_final: se3.Pose, truth_start: se3.Pose, estimate_start: se3.Pose, symmetry: Symmetry):
    """The discrete copies and None; or, about a continuous axis, the refined copies and ``(best score on the
    grid (T,), the grid's copies (T, G))`` (:func:`nll`, :func:`truth_copies`)."""
    final = se3.Pose.unchecked(truth_final.p.double().reshape(-1, 3), truth_final.q.double().reshape(-1, 4))
    truth0 = se3.Pose.unchecked(truth_start.p.double().reshape(3), truth_start.q.double().reshape(4))
    est0 = se3.Pose.unchecked(estimate_start.p.double().reshape(3), estimate_start.q.double().reshape(4))
    discrete = symmetry.discrete.double()
    if symmetry.continuous_axis is None:
        return symmetric_truths(final, truth0, est0, discrete.expand(final.p.shape[0], *discrete.shape)), None
    axis = symmetry.continuous_axis.double()
    step = 2.0 * math.pi / _CONTINUOUS_STEPS
    angles = torch.arange(_CONTINUOUS_STEPS, dtype=torch.float64) * step
    turns = _axis_turns(axis, angles)  # (M, 4)
    grid = pkt.quaternion_raw_multiply(discrete.unsqueeze(1), turns.unsqueeze(0)).reshape(-1, 4)  # (K·M, 4)
    on_grid = symmetric_truths(final, truth0, est0, grid.expand(final.p.shape[0], *grid.shape))
    coarse = density.log_prob(on_grid.vector())
    best = coarse.argmax(-1)
    k, m = best // _CONTINUOUS_STEPS, best % _CONTINUOUS_STEPS
    fine_angles = angles[m].unsqueeze(-1) + _REFINE * step  # (T, R)
    fine = pkt.quaternion_raw_multiply(discrete[k].unsqueeze(1).expand(-1, _REFINE.numel(), 4),
                                       _axis_turns(axis, fine_angles))
    return symmetric_truths(final, truth0, est0, fine), (coarse.amax(-1), on_grid)


def ensemble_density(finals: se3.Pose, p_std: float, rot_std: float) -> FinalPoseDistribution:
    """A kernel density ``()`` with one kernel of bandwidth (p_std, rot_std) at each of the poses ``(N,)``,
    equally weighted: the density of an ensemble of rollouts (the ``physics_ensemble`` peer)."""
    n = int(finals.p.reshape(-1, 3).shape[0])
    if n == 0:
        raise InvalidParameterError("an ensemble density needs at least one outcome")
    means = se3.Pose.unchecked(finals.p.reshape(n, 3), finals.q.reshape(n, 4))
    density = _full_density(means, torch.full((1, n), -math.log(n)), p_std, rot_std)
    density._log_z = torch.zeros((), dtype=torch.float64)
    return density


def hdr_thresholds(density: FinalPoseDistribution, levels=COVERAGE_LEVELS, samples: int = COVERAGE_SAMPLES,
                   generator: torch.Generator | None = None, symmetry: Symmetry | None = None,
                   plane: se3.Pose | None = None) -> Tensor:
    """``(L,)`` float64 log-density thresholds of the density's highest-density regions holding ``levels`` of
    its mass (module docstring, "Calibration"): ``t_α`` is the ``1 − α`` quantile of ``log p`` over ``samples``
    draws from the density (batch shape ``()``). With the test object's ``symmetry`` each draw is scored as a
    truth is (:func:`nll`, its nearest symmetric copy), so that a truth drawn from the density itself is inside a
    share ``α`` of the time: scoring the truths by their best copy and the draws as they are would make every
    symmetric object look better calibrated than it is (a surface of revolution's turn would never count).
    With ``plane`` (the estimated start ``B̂0``, ``()``) each draw is first moved onto its plane
    (:func:`pushtorch.se3.onto_plane_of`: its x, y and twist about world z kept, its height and tilt
    ``B̂0``'s), the poses a pushed object on a table takes: the truths lie there, at the centre of the
    density's spread in height, roll and pitch, so that draws spread over those three would set thresholds that
    nearly every truth reaches (module docstring, "Calibration").

    Raises:
        InvalidParameterError: a level outside (0, 1), or fewer than 10 samples.
    """
    alpha = torch.as_tensor(levels, dtype=torch.float64).reshape(-1)
    if not ((alpha > 0) & (alpha < 1)).all():
        raise InvalidParameterError(f"coverage levels must lie in (0, 1), got {alpha.tolist()}")
    if samples < 10:
        raise InvalidParameterError(f"a region's threshold needs at least 10 draws, got {samples}")
    draws = density.sample((int(samples),), generator)
    if plane is not None:
        on_plane = se3.onto_plane_of(se3.Pose.unchecked(draws[..., :3], draws[..., 3:]),
                                     se3.Pose.unchecked(plane.p.to(draws), plane.q.to(draws)))
        draws = on_plane.vector()
    log_p = density.log_prob(draws).double().reshape(-1)
    if symmetry is not None and (symmetry.continuous_axis is not None or symmetry.discrete.shape[0] > 1):
        log_p = _nearest_copy_scores(density, draws.double().reshape(-1, 7), log_p, symmetry)
    log_p = log_p[torch.isfinite(log_p)]
    if log_p.numel() == 0:
        raise InvalidParameterError("no draw from the density has a finite log density")
    return torch.quantile(log_p, 1.0 - alpha)


def _nearest_copy_scores(density: FinalPoseDistribution, draws: Tensor, log_p: Tensor, symmetry: Symmetry) -> Tensor:
    """``(T,)`` each draw's ``(T, 7)`` log density at its nearest symmetric copy (``log_p``: at itself).
    :func:`nll` scans a truth's every copy (157 evaluations a copy about a continuous axis); a draw is instead
    turned to face the best draw, the orientation the density's mass gathers around: the discrete copy closest to
    it (about a continuous axis, after the twist that aligns the two) is scored, searched about the axis over
    :func:`nll`'s refined span (±4.5°, to 0.28°), and the draw as it is kept as a candidate. Wherever the density
    has one basin per symmetric class, that is the same maximum, at 1 (discrete) or 19 (continuous) evaluations a
    draw."""
    q = draws[:, 3:]
    copies = pkt.quaternion_raw_multiply(q.unsqueeze(1), symmetry.discrete.double().unsqueeze(0))  # (T, K, 4)
    target = q[int(log_p.argmax())]
    relative = pkt.quaternion_raw_multiply(pkt.quaternion_invert(copies), target.expand_as(copies))
    rows = torch.arange(draws.shape[0])
    if symmetry.continuous_axis is None:
        nearest = copies[rows, relative[..., 0].abs().argmax(-1)]  # (T, 4)
        return torch.maximum(log_p, density.log_prob(torch.cat([draws[:, :3], nearest], -1)).double())
    axis = symmetry.continuous_axis.double()
    along = (relative[..., 1:] * axis).sum(-1)
    k = (relative[..., 0] ** 2 + along**2).argmax(-1)  # the copy whose axis the twist can align with the target's
    best = 2.0 * torch.atan2(along[rows, k], relative[rows, k, 0])  # (T,) the twist that faces the best draw
    found = log_p
    for offsets in _DRAW_STEPS:  # ±4.5° in 1.125° steps, then ±1.125° in 0.28° steps about the best so far
        angles = best.unsqueeze(-1) + offsets  # (T, R)
        turned = pkt.quaternion_raw_multiply(copies[rows, k].unsqueeze(1).expand(*angles.shape, 4),
                                             _axis_turns(axis, angles))
        scores = density.log_prob(torch.cat([draws[:, :3].unsqueeze(1).expand(*angles.shape, 3), turned],
                                            -1)).double()
        best = angles[rows, scores.argmax(-1)]
        found = torch.maximum(found, scores.amax(-1))
    return found


def covered(nll_values: Tensor, thresholds: Tensor) -> Tensor:
    """``(..., L)`` bool: each truth scored ``nll_values (...)`` is inside each region of ``thresholds (..., L)``
    (broadcast): ``−nll ≥ t_α``."""
    return (-nll_values.double()).unsqueeze(-1) >= thresholds.double()


def calibrated_choice(nll_rows: Tensor, covered_at, level: float = 0.9, margin: float = 2.0,
                      most: int = CALIBRATION_CANDIDATES, groups=None) -> tuple[int, dict]:
    """The sharpest setting, of those held-out likelihood cannot tell apart, whose regions hold the truths as
    often as they say: ``nll_rows (n, C)`` the held-out truths' nll under each of ``C`` settings of one density
    (the same ``n`` pushes); the candidates are the settings whose mean nll is within ``margin`` paired SE of the
    lowest (at most ``most``, lowest mean first; the lowest always). The SE is that of the paired differences
    winsorised at their :data:`WINSOR` quantiles: a setting hundreds of nats worse on a few pushes has
    differences whose plain SE is as large as their mean, and would tie with anything. ``covered_at(c)`` gives
    ``(n,)`` whether each truth lies inside the ``level`` region of setting ``c``'s density
    (:func:`hdr_thresholds`, :func:`covered`), or that and ``(n,)`` each region's log-density threshold. A
    candidate's miscalibration is its share inside's distance from ``level``; with ``groups`` (``n`` labels:
    which held-out shape each push is of) the mean over the groups of each group's, every group counted once (a
    pooled share of 0.9 can be one group's 1.0 and another's 0.6, calibrated for neither). The candidates within
    one SE of the least miscalibrated (the SE of each one's miscalibration less the least's, over
    :data:`CALIBRATION_RESAMPLES` resamples of the pushes within their groups) are calibrated alike, and of them
    the one whose regions are sharpest is kept: the highest mean threshold, the log density at the edge of its
    regions (without thresholds: the least miscalibrated), then the least miscalibrated, then the lower mean nll
    (docs/method.md, "Each model's hedges, and a tie in likelihood broken by calibration, then sharpness").
    Likelihood alone trades a sharp core against wide tails and can put the held-out truths' coverage anywhere
    the tails' weight leaves it; a group's coverage on a few pushes is known to a tenth, and of two settings
    calibrated alike the sharper says more. Returns ``(index, report)``: the report holds the candidates, their
    mean nll, paired SE, pooled coverage, miscalibration, its SE and sharpness, which are calibrated alike, and
    with ``groups`` the groups and each candidate's share per group.

    Raises:
        InvalidParameterError: rows that are not ``(n, C)`` with ``n >= 2`` or that hold a NaN, a level outside
            (0, 1), or groups that are not one label per push.
    """
    rows = torch.as_tensor(nll_rows, dtype=torch.float64)
    if rows.dim() != 2 or rows.shape[0] < 2 or rows.shape[1] < 1 or not 0.0 < level < 1.0:
        raise InvalidParameterError(f"a calibrated choice needs (pushes >= 2, settings) nll rows and a level in "
                                    f"(0, 1), got {tuple(rows.shape)} and {level}")
    if bool(torch.isnan(rows).any()):
        raise InvalidParameterError(f"a calibrated choice's nll rows hold {int(torch.isnan(rows).sum())} NaN")
    mean = rows.mean(0)
    best = int(mean.argmin())
    differences = rows - rows[:, best:best + 1]
    low, high = torch.quantile(differences, WINSOR, dim=0), torch.quantile(differences, 1.0 - WINSOR, dim=0)
    se = differences.clamp(low, high).std(0) / math.sqrt(rows.shape[0])
    tied = torch.nonzero((mean - mean[best] <= margin * se) | (torch.arange(len(mean)) == best)).reshape(-1)
    tied = tied[torch.argsort(mean[tied], stable=True)][:max(1, int(most))].tolist()  # the lowest first
    labels = [0] * rows.shape[0] if groups is None else list(groups)
    if len(labels) != rows.shape[0]:
        raise InvalidParameterError(f"a calibrated choice's groups need one label per push ({rows.shape[0]}), got "
                                    f"{len(labels)}")
    names = list(dict.fromkeys(labels))
    members = torch.tensor([[label == name for label in labels] for name in names])  # (G, n)
    measured = [covered_at(c) for c in tied]
    pairs = [m if isinstance(m, tuple) else (m, None) for m in measured]
    inside = torch.stack([torch.as_tensor(i).double().reshape(-1) for i, _ in pairs])  # (K, n)
    sharp = [0.0 if t is None else float(torch.as_tensor(t).double().mean()) for _, t in pairs]
    per_group = ((inside @ members.double().T) / members.sum(1)).tolist()  # (K, G)
    off = [round(sum(abs(g - level) for g in gs) / len(gs), 9) for gs in per_group]  # equal shares tie exactly
    least = min(range(len(tied)), key=lambda k: (off[k], float(mean[tied[k]])))
    spread = _miscalibration_se(inside, members, level, least)
    alike = [k for k in range(len(tied)) if off[k] - off[least] <= spread[k] + 1e-9]
    chosen = min(alike, key=lambda k: (-round(sharp[k], 9), off[k], float(mean[tied[k]])))
    report = {"level": level, "margin": margin, "candidates": tied, "nll": [float(mean[c]) for c in tied],
              "se": [float(se[c]) for c in tied], "coverage": inside.mean(1).tolist(), "likeliest": best,
              "miscalibration": off, "miscalibration_se": spread, "sharpness": sharp,
              "calibrated_alike": [tied[k] for k in alike]}
    if groups is not None:
        report |= {"groups": [str(n) for n in names], "group_coverage": per_group}
    return tied[chosen], report


def _miscalibration_se(inside: Tensor, members: Tensor, level: float, least: int) -> list[float]:
    """``(K,)`` the SE of each candidate's miscalibration (the mean over groups of their share inside's distance
    from ``level``; ``inside (K, n)``, ``members (G, n)``) less candidate ``least``'s, over
    :data:`CALIBRATION_RESAMPLES` resamples of each group's pushes with replacement (paired: the same resample for
    every candidate)."""
    generator = torch.Generator().manual_seed(0)
    off = torch.zeros(inside.shape[0], CALIBRATION_RESAMPLES, dtype=torch.float64)
    for row in members:
        own = inside[:, row]  # (K, m)
        draws = torch.randint(0, own.shape[1], (CALIBRATION_RESAMPLES, own.shape[1]), generator=generator)
        off += (own[:, draws].mean(-1) - level).abs()
    off /= members.shape[0]
    return (off - off[least]).std(1).tolist()
