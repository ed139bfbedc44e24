"""Bandwidths from data: each model chooses its motion and contact-kernel bandwidths by held-out likelihood.

Not in the paper, which fixes every bandwidth by hand (its tables; our defaults). Issue 17: the motion kernels
(1 cm, 0.05 rad) and the contact position term ``g`` (5 cm) were far wider than the spread of the training
pushes, so each model now picks them from its own pushes, the paper's values being the starting point.

Procedure (:func:`select_bandwidths`, docs/method.md "Bandwidths from data"):

* **k-fold by push.** Every training push of an action is held out in turn (fold = push index mod k); the
  kernels of the other folds form the experts of Eq. poe for it, conditioned on the held-out push's own
  contact frames: its manipulator kernel's ``(u, r, g)``, its first ``environment_contacts`` environment
  kernels' and its contact patch on the bumper.
* **Score.** The log of the experts' pool at the held-out push's true motion (robot start frame; the Haar
  measure makes that the final pose's log density): ``Σ_e γ_e log p_e(m_i)``, each expert a normalised
  mixture of uncut Gaussian × folded-vMF kernels (:mod:`pushtorch.evaluation.likelihood`) weighted by the uncut contact
  kernel. With ``Σγ = 1`` (the default pool) the pool's normaliser is at most 1 (Hölder), so the score is a
  lower bound of the held-out log-likelihood of the normalised pool, exact when the experts agree.
* **Search.** Coordinate ascent from the configured values over a ×2 ladder per parameter (motion position
  and rotation stds; the contact kernel's relation ``u`` position and rotation stds, its contact position
  ``g`` std and its contact patch's extent and heading stds), two sweeps; every term's
  squared distances are computed once, so a candidate costs one weighted logsumexp. The motion stds are
  only widened (``WIDEN_ONLY``): the prediction is the product's mode, which kernels narrower than the
  configured ones turn into a single training push. For the same reason contact stds that leave the
  manipulator expert fewer than ``MIN_EFFECTIVE_PUSHES`` effective training pushes are not considered.

* **The density's stds.** Then ``density_p_std`` / ``density_rot_std`` (``DENSITY``): the same score over the
  motion stds alone, from the chosen ones *down* with no floor, until a sweep gains nothing. They are the kernels
  of the density a prediction returns and observations are weighed by; the mode is still annealed with the
  floored motion stds (docs/method.md, "Two widths: the mode and the density").
* **The evidence's outlier share.** Last ``density_outlier`` (``OUTLIER_LADDER``): each motion kernel of the
  evidence becomes the scale mixture ``(1 − ε) K_density + ε K_mode`` (both normalised), scored the same way.
  Observed pushes are weighed under it (:mod:`pushtorch.models.evidence`): a push that the calibrated kernels
  miss by a few of their widths costs a few nats, not tens, so one surprising push does not decide a library.

The chosen values replace the configured ones in the model's settings (so they are in the model file), and
the search's record (held-out score before and after, and at the density's stds) is kept in ``PushModel.meta``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.kde.normaliser import log_rotation_normaliser
from pushtorch.models.frames import embed_descriptors
from pushtorch.models.motion import MotionKernels, expert_exponents

Tensor = torch.Tensor
log = logging.getLogger(__name__)

__all__ = ["DENSITY", "BandwidthSearch", "SELECTED", "select_bandwidths"]

#: The settings chosen from data, in the order coordinate ascent visits them.
SELECTED = ("motion_p_std", "motion_rot_std", "contact_p_std", "contact_rot_std", "contact_robot_std",
            "contact_patch_std", "contact_patch_yaw_std")
#: The density's motion stds, chosen after ``SELECTED`` from the chosen motion stds down.
DENSITY = ("density_p_std", "density_rot_std")
#: Factors tried around the current value of a setting.
LADDER = (0.25, 0.5, 1.0, 2.0, 4.0)
#: Bounds of each setting (m or rad): below the simulator's resolution, above the object's size. The contact
#: patch is matched against a single-shot cloud of 4 mm voxels at prediction, not the exact training cloud the
#: search sees: its stds stop at 5 mm and 0.01 rad (a 4 mm step across the 0.4 m plate is 0.01 rad).
BOUNDS = {"motion_p_std": (1e-3, 0.1), "motion_rot_std": (5e-3, 0.5), "contact_p_std": (2e-3, 0.5),
          "contact_rot_std": (5e-3, 2.0), "contact_robot_std": (5e-3, 0.5), "contact_patch_std": (5e-3, 0.2),
          "contact_patch_yaw_std": (1e-2, 2.0)}
#: Settings the search only widens: the configured motion stds are floors. The prediction is the product's
#: mode (the paper's), and motion kernels narrower than the spread of outcomes one condition allows make that
#: mode a single training push: held-out likelihood preferred 2.5 mm / 0.005 rad on the cube, and the
#: quickstart's mass-general cube model then predicted 7.6 cm off (H_acc 0.38; 0.8 cm with 1 cm kernels), its
#: annealed mode on one push of another mass 19 cm from the bulk (docs/method.md).
WIDEN_ONLY = ("motion_p_std", "motion_rot_std")
#: The fewest training pushes (Kish's effective sample size of its weights, median over held-out pushes) the
#: manipulator expert may rest on. It carries 2/3 of the product's weight, so contact stds narrow enough to
#: leave it one push make the prediction that push: in the quickstart the mass-general cube model's heading
#: std of 0.01 rad picked one push of another mass and predicted 7.6 cm off on every condition (H_acc 0.39
#: against the mean motion's 0.04), although held-out likelihood preferred it.
MIN_EFFECTIVE_PUSHES = 5.0
_INADMISSIBLE = -1e9  # the score of stds below MIN_EFFECTIVE_PUSHES, plus their effective count
#: Sweeps of the density stds' search at most (it stops when a sweep gains nothing).
DENSITY_SWEEPS = 4
#: The evidence's outlier shares tried (``density_outlier``, the weight of the mode-width component of each
#: kernel); the configured one is the starting point, so 0 is kept unless a share scores higher.
OUTLIER_LADDER = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
#: Held-out pushes scored per action, and the experts' kernels the search keeps (memory bound): the manipulator
#: kernels of at most ``MAX_MANIPULATOR_PUSHES`` pushes, and the environment kernels of as many whole pushes
#: (all of each push's frames, so every kept push can be held out) as ``MAX_ENVIRONMENT_KERNELS`` allows, those
#: pushes among the manipulator's. Above either bound a seeded subsample of pushes is kept, and the log says so:
#: the search then has its ``MAX_HELD_OUT`` held-out pushes at any size (100 to 100,000 pushes per action).
MAX_HELD_OUT = 200
MAX_ENVIRONMENT_KERNELS = 2000
MAX_MANIPULATOR_PUSHES = 2000


@dataclass
class BandwidthSearch:
    """What :func:`select_bandwidths` chose: settings values and held-out scores (nats per push)."""

    chosen: dict[str, float]
    start: dict[str, float]
    score_start: float | None  # None: the configured stds were inadmissible (MIN_EFFECTIVE_PUSHES)
    score_chosen: float | None
    folds: int
    held_out: int
    score_density: float | None = None  # at the density's stds (``chosen``'s density_p_std, density_rot_std)
    score_outlier: float | None = None  # with the evidence's outlier share too (``chosen``'s density_outlier)
    # pushes of which the search kept no kernel (only where it subsampled), scored after it against the kept ones:
    # how many, and the same score at the configured, the chosen and the density's stds
    unseen: int = 0
    unseen_start: float | None = None
    unseen_chosen: float | None = None
    unseen_density: float | None = None

    def as_meta(self) -> dict:
        def rounded(score: float | None) -> float | None:
            return None if score is None else round(score, 3)

        return {"chosen": self.chosen, "start": self.start, "score_start": rounded(self.score_start),
                "score_chosen": rounded(self.score_chosen), "score_density": rounded(self.score_density),
                "score_outlier": rounded(self.score_outlier),
                "folds": self.folds, "held_out": self.held_out, "unseen": self.unseen,
                "unseen_start": rounded(self.unseen_start), "unseen_chosen": rounded(self.unseen_chosen),
                "unseen_density": rounded(self.unseen_density)}


@dataclass
class _Terms:
    """Squared distances of one action's held-out queries to its kernels, per term, and the folds' mask.

    Shapes: ``(Q, E, K)`` for the contact terms (E experts per query, manipulator first), ``(Q, K)`` for the
    motion terms; the manipulator expert uses the first ``n_man`` kernels, environment experts the rest.
    """

    u_p: Tensor  # contact relation: |Δp|² (m²)
    u_q: Tensor  # contact relation: 1 − |<q, q'>|
    r: Tensor  # embedded descriptors, Σ Δ²/(2 std²) at the configured descriptor std
    g: Tensor  # |Δg|² (m²)
    patch: Tensor  # |Δ lateral extent|² (m²)
    patch_yaw: Tensor  # Δ heading² (rad²)
    motion_p: Tensor  # |Δp|² (m²)
    motion_q: Tensor  # 1 − |<q, q'>|
    member: Tensor  # (E, K) bool: kernel k belongs to expert kind e (manipulator / environment)
    same_fold: Tensor  # (Q, K) bool


def _first_of_push(push: Tensor, queries: Tensor, count: int) -> Tensor:
    """``(Q, count)`` indices of the first ``count`` kernels of each push in ``queries`` (each push has them)."""
    order = torch.argsort(push, stable=True)
    sorted_push = push[order]
    first = torch.searchsorted(sorted_push, queries)  # where each query's kernels start
    return order[first.unsqueeze(-1) + torch.arange(count)]


def _joined(man: MotionKernels, env: MotionKernels) -> MotionKernels:
    """The manipulator kernels, then the environment kernels, as one set."""
    return MotionKernels(
        torch.cat([man.r, env.r]), se3.Pose.unchecked(torch.cat([man.u.p, env.u.p]), torch.cat([man.u.q, env.u.q])),
        se3.Pose.unchecked(torch.cat([man.m.p, env.m.p]), torch.cat([man.m.q, env.m.q])),
        torch.cat([man.g, env.g]), torch.cat([man.patch, env.patch]),
    )


def _kernel_terms(man: MotionKernels, env: MotionKernels, man_push: Tensor, env_push: Tensor, queries: Tensor,
                  n_env_frames: int, folds: int, settings,
                  unseen: tuple[MotionKernels, MotionKernels] | None = None) -> _Terms:
    """The distance terms for held-out pushes ``queries`` (push indices) of one action. ``unseen``: the queries are
    pushes none of whose kernels are among these, their frames taken from the whole action's ``(manipulator,
    environment)`` kernels, and no kernel is left out for them (no fold)."""
    kernels = _joined(man, env)
    push = torch.cat([man_push, env_push])
    n_man = len(man)
    source, (m_push, e_push, n_source) = kernels, (man_push, env_push, n_man)
    if unseen is not None:
        source = _joined(unseen[0], unseen[1])
        m_push, e_push, n_source = unseen[0].push, unseen[1].push, len(unseen[0])
    rows = torch.cat([_first_of_push(m_push, queries, 1), _first_of_push(e_push, queries, n_env_frames) + n_source],
                     -1)  # (Q, E): each held-out push's own frames, its manipulator kernel first
    frames = source.take(rows.reshape(-1))
    shape = (*rows.shape, len(kernels))

    def pair(a: Tensor, b: Tensor) -> Tensor:
        return ((a.reshape(-1, 1, a.shape[-1]) - b.unsqueeze(0)) ** 2).sum(-1).reshape(shape)

    dot = (frames.u.q.reshape(-1, 1, 4) * kernels.u.q.unsqueeze(0)).sum(-1).abs().reshape(shape)
    r = pair(embed_descriptors(frames.r), embed_descriptors(kernels.r)) / (2 * settings.descriptor_std**2)
    truth = source.take(rows[:, 0])  # the held-out push's motion (its manipulator kernel's m)
    motion_dot = (truth.m.q.unsqueeze(1) * kernels.m.q.unsqueeze(0)).sum(-1).abs()
    kinds = torch.zeros(rows.shape[1], len(kernels), dtype=torch.bool)
    kinds[0, :n_man] = True
    kinds[1:, n_man:] = True
    return _Terms(
        u_p=pair(frames.u.p, kernels.u.p), u_q=(1 - dot).clamp_min(0), r=r, g=pair(frames.g, kernels.g),
        patch=pair(frames.patch[:, :2], kernels.patch[:, :2]),
        patch_yaw=pair(frames.patch[:, 2:], kernels.patch[:, 2:]),
        motion_p=((truth.m.p.unsqueeze(1) - kernels.m.p.unsqueeze(0)) ** 2).sum(-1),
        motion_q=(1 - motion_dot).clamp_min(0),
        member=kinds, same_fold=((queries.unsqueeze(1) % folds) == (push.unsqueeze(0) % folds)) & (unseen is None),
    )


def _effective_pushes(log_w: Tensor) -> Tensor:
    """``(Q,)`` Kish's effective sample size ``(Σw)² / Σw²`` of each held-out push's manipulator weights."""
    w = torch.softmax(log_w[:, 0], -1)
    return 1.0 / (w * w).sum(-1)


#: The settings the contact weights depend on (the rest, the motion stds, only the kernels' values).
_CONTACT = ("contact_p_std", "contact_rot_std", "contact_robot_std", "contact_patch_std", "contact_patch_yaw_std")


def _contact_log_weights(terms: _Terms, values: dict[str, float]) -> tuple[Tensor, float]:
    """``(Q, E, K)`` the held-out pushes' contact log weights of every kernel at ``values`` (other folds and other
    experts' kernels excluded), and the median held-out push's effective count of manipulator pushes."""
    log_w = -(terms.u_p / (2 * values["contact_p_std"] ** 2) + terms.u_q / (values["contact_rot_std"] ** 2 / 4)
              + terms.r + terms.g / (2 * values["contact_robot_std"] ** 2)
              + terms.patch / (2 * values["contact_patch_std"] ** 2)
              + terms.patch_yaw / (2 * values["contact_patch_yaw_std"] ** 2))  # (Q, E, K)
    excluded = terms.same_fold.unsqueeze(1) | ~terms.member.unsqueeze(0)
    log_w = log_w.masked_fill(excluded, -math.inf)
    return log_w, float(_effective_pushes(log_w).median())


def _score(terms: _Terms, values: dict[str, float], exponent: Tensor,
           weights: tuple[Tensor, float] | None = None) -> float:
    """Mean over held-out pushes of ``Σ_e γ_e log p_e(m_i)`` at the bandwidths ``values``; when the median
    held-out push's manipulator expert rests on fewer than :data:`MIN_EFFECTIVE_PUSHES` pushes, a score below
    every admissible one that still grows with that count (so the search moves towards admissible stds).
    ``weights``: :func:`_contact_log_weights` at ``values``, if known."""
    log_w, effective = weights if weights is not None else _contact_log_weights(terms, values)
    if effective < MIN_EFFECTIVE_PUSHES:
        return _INADMISSIBLE + effective
    log_k = _log_motion_kernels(terms, values["motion_p_std"], values["motion_rot_std"])  # (Q, K)
    outlier = values.get("density_outlier", 0.0) if "mode_p_std" in values else 0.0  # the evidence's kernels
    if outlier > 0:  # each kernel a scale mixture: the calibrated width and, with weight ε, the mode's
        wide = _log_motion_kernels(terms, values["mode_p_std"], values["mode_rot_std"])
        log_k = torch.logaddexp(log_k + math.log1p(-outlier), wide + math.log(outlier))
    log_p = torch.logsumexp(log_w + log_k.unsqueeze(1), -1) - torch.logsumexp(log_w, -1)  # (Q, E)
    return float((log_p * exponent).sum(-1).mean())


def _log_motion_kernels(terms: _Terms, p_std: float, rot_std: float) -> Tensor:
    """``(Q, K)`` each normalised motion kernel's log density at the held-out pushes' motions."""
    sigma_q = rot_std**2 / 4
    log_norm = 1.5 * math.log(2 * math.pi * p_std**2) + float(log_rotation_normaliser(torch.tensor(1 / sigma_q)))
    return -terms.motion_p / (2 * p_std**2) - terms.motion_q / sigma_q - log_norm


def _environment_frames(man_push: Tensor, env_push: Tensor) -> Tensor:
    """Each push index's count of environment kernels (indexable by every push of ``man_push``)."""
    return torch.bincount(env_push, minlength=int(max(int(env_push.max()), int(man_push.max()))) + 1)


def _kept_pushes(motion, n_env_frames: int, generator: torch.Generator | None
                 ) -> tuple[MotionKernels, MotionKernels, Tensor, Tensor, Tensor]:
    """One action's kernels the search keeps (``MAX_MANIPULATOR_PUSHES``, ``MAX_ENVIRONMENT_KERNELS``), as index
    tensors into its manipulator and environment kernels, and the pushes that can be held out (their manipulator
    kernel and at least ``n_env_frames`` environment frames kept). Below both bounds every kernel is kept and no
    number is drawn."""
    man, env = motion.manipulator, motion.environment
    man_push, env_push = man.push, env.push
    pushes = torch.unique(man_push)
    total = len(pushes)
    thin_man, thin_env = total > MAX_MANIPULATOR_PUSHES, len(env) > MAX_ENVIRONMENT_KERNELS
    if thin_man:
        pushes = pushes[torch.randperm(total, generator=generator)[:MAX_MANIPULATOR_PUSHES]].sort().values
    # pushes whose environment frames can be the query's
    pool = pushes[_environment_frames(man_push, env_push)[pushes] >= n_env_frames]
    if not (thin_man or thin_env):
        return man, env, torch.arange(len(man)), torch.arange(len(env)), pool
    per_push = max(1, math.ceil(len(env) / max(1, len(torch.unique(env_push)))))
    most = max(1, MAX_ENVIRONMENT_KERNELS // per_push)
    if len(pool) > most:
        pool = pool[torch.randperm(len(pool), generator=generator)[:most]].sort().values
    log.info("bandwidth search, action %s: the manipulator kernels of %d of %d pushes and the environment kernels "
             "of %d pushes kept (a seeded subsample, for memory)", tuple(round(float(a), 4) for a in motion.action),
             len(pushes), total, len(pool))
    keep_man = torch.isin(man_push, pushes).nonzero().squeeze(-1)
    keep_env = torch.isin(env_push, pool).nonzero().squeeze(-1)
    return man, env, keep_man, keep_env, pool


def select_bandwidths(settings, motions: list, folds: int = 5,
                      generator: torch.Generator | None = None) -> tuple[object, BandwidthSearch]:
    """Choose ``SELECTED`` settings by held-out likelihood on the model's own training pushes (module docstring).

    Args:
        settings: the configured :class:`~pushtorch.models.library.ModelSettings` (the starting point).
        motions: the model's :class:`~pushtorch.models.motion.MotionModel` per action, as
            :func:`~pushtorch.models.motion.fit_motion_model` made them (kernels know their pushes).
        folds: k of the k-fold split by push.
        generator: draws the held-out pushes and environment kernels kept when an action has more.

    Returns:
        The settings with the chosen values, and the search's record.
    """
    n_env_frames = settings.environment_contacts
    terms, exponents, unseen = [], [], []
    # the pushes the search never sees are drawn by a generator of their own: the search's draws stay as they were
    never_generator = None if generator is None else torch.Generator().manual_seed(generator.initial_seed() ^ 0x5EED)
    for motion in motions:
        man_push, env_push = motion.manipulator.push, motion.environment.push
        if man_push is None or env_push is None:
            raise InvalidParameterError("select_bandwidths needs motion kernels that know their pushes "
                                        "(fit_motion_model's, not a loaded model's)")
        man, env, keep_man, keep_env, candidates = _kept_pushes(motion, n_env_frames, generator)
        if len(candidates) > MAX_HELD_OUT:
            candidates = candidates[torch.randperm(len(candidates), generator=generator)[:MAX_HELD_OUT]]
        if len(candidates) < folds:
            continue
        t = _kernel_terms(man.take(keep_man), env.take(keep_env), man_push[keep_man], env_push[keep_env],
                          candidates, n_env_frames, folds, settings)
        n_experts = t.u_p.shape[1]
        terms.append(t)
        exponents.append(expert_exponents(len(motion.manipulator), len(motion.environment), n_experts - 1,
                                          settings.pool_sharpness, torch.float32))
        never = _never_kept(man_push, env_push, man_push[keep_man], n_env_frames, never_generator)
        if len(never):
            unseen.append((man, env, keep_man, keep_env, never, exponents[-1]))
    start = {name: float(getattr(settings, name)) for name in (*SELECTED, *DENSITY, "density_outlier")}
    if not terms:  # too few pushes to hold any out: keep the configured values
        return settings, BandwidthSearch(start, start, None, None, folds, 0, None)

    cached: dict[tuple, list] = {}  # the contact weights of the last contact stds: a motion std's step reuses them

    def total(values: dict[str, float]) -> float:
        key = tuple(values[name] for name in _CONTACT)
        if key not in cached:
            cached.clear()
            cached[key] = [_contact_log_weights(t, values) for t in terms]
        return sum(_score(t, values, g, w) * t.u_p.shape[0]
                   for t, g, w in zip(terms, exponents, cached[key], strict=True)) / sum(t.u_p.shape[0] for t in terms)

    values, best = dict(start), total(start)
    score_start = best
    for _ in range(2):
        for name in SELECTED:
            values, best = _ladder_step(total, values, best, name, start[name] if name in WIDEN_ONLY else None)
    # the density's motion stds: the same score from the mode's stds down, with no floor (docs/method.md)
    density = dict(values)
    density_best = best
    for _ in range(DENSITY_SWEEPS):
        before = density_best
        for name in WIDEN_ONLY:
            density, density_best = _ladder_step(total, density, density_best, name, None)
        if density_best <= before + 1e-6:
            break
    chosen = dict(values, density_p_std=density["motion_p_std"], density_rot_std=density["motion_rot_std"])
    # the evidence's outlier share: each density kernel a scale mixture with the mode's (docs/method.md)
    mixed = dict(density, mode_p_std=values["motion_p_std"], mode_rot_std=values["motion_rot_std"],
                 density_outlier=start["density_outlier"])
    outlier_best = total(mixed)
    for share in OUTLIER_LADDER:
        score = total(dict(mixed, density_outlier=share))
        if score > outlier_best + 1e-6:
            mixed, outlier_best = dict(mixed, density_outlier=share), score
    chosen["density_outlier"] = mixed["density_outlier"]

    def reported(score: float) -> float | None:  # an inadmissible set has no likelihood to report
        return None if score < _INADMISSIBLE / 2 else score

    held_out = sum(t.u_p.shape[0] for t in terms)
    terms.clear()  # the search's terms freed: the unseen pushes' terms, one action at a time, in their place
    cached.clear()
    scores, count = _unseen_scores(unseen, (start, values, density), n_env_frames, folds, settings)
    search = BandwidthSearch(chosen, start, reported(score_start), reported(best), folds,
                             held_out, reported(density_best), reported(outlier_best), count,
                             *(reported(x) if count else None for x in scores))
    if count:
        log.info("bandwidth search: on %d pushes it never saw (no kernel of theirs kept), held-out log-likelihood "
                 "%s configured, %s chosen, %s at the density's stds (nats a push)", count,
                 *(f"{x:.3f}" if x is not None else "inadmissible" for x in
                   (search.unseen_start, search.unseen_chosen, search.unseen_density)))
    return replace(settings, **chosen), search


def _never_kept(man_push: Tensor, env_push: Tensor, kept: Tensor, n_env_frames: int,
                generator: torch.Generator | None) -> Tensor:
    """Up to :data:`MAX_HELD_OUT` pushes (a seeded draw) none of whose kernels the search keeps (``kept``: the
    pushes of the kept manipulator kernels, which hold those of the kept environment kernels), with the
    ``n_env_frames`` environment frames a held-out push needs. Empty wherever the search keeps every push."""
    pushes = torch.unique(man_push)
    never = pushes[~torch.isin(pushes, kept) & (_environment_frames(man_push, env_push)[pushes] >= n_env_frames)]
    if len(never) > MAX_HELD_OUT:
        never = never[torch.randperm(len(never), generator=generator)[:MAX_HELD_OUT]].sort().values
    return never


def _unseen_scores(unseen: list, settings_values: tuple[dict, ...], n_env_frames: int, folds: int,
                   settings) -> tuple[list[float], int]:
    """The held-out score (:func:`_score`) of the pushes the search never saw, per action ``(manipulator and
    environment kernels, the kept ones' indices, the unseen pushes, the experts' exponents)``, against the kept
    kernels, at each of ``settings_values``: the means over all those pushes, and how many there were."""
    sums, count = [0.0] * len(settings_values), 0
    for man, env, keep_man, keep_env, never, exponent in unseen:
        t = _kernel_terms(man.take(keep_man), env.take(keep_env), man.push[keep_man], env.push[keep_env], never,
                          n_env_frames, folds, settings, unseen=(man, env))
        for i, values in enumerate(settings_values):
            sums[i] += _score(t, values, exponent) * len(never)
        count += len(never)
    return [x / max(count, 1) for x in sums], count


def _ladder_step(total, values: dict[str, float], best: float, name: str,
                 floor: float | None) -> tuple[dict[str, float], float]:
    """One coordinate of the ascent: ``name`` tried at every :data:`LADDER` factor of its value, within its
    :data:`BOUNDS` (and above ``floor``); returns the best values and score."""
    low, high = BOUNDS[name]
    if floor is not None:
        low = max(low, floor)
    centre = values[name]
    for factor in LADDER:
        trial = dict(values, **{name: min(max(centre * factor, low), high)})
        score = total(trial)
        if score > best + 1e-6:
            values, best = trial, score
    return values, best
