"""Predicting with the residual model (:mod:`pushtorch.models.residual`): the cloud's body rolled out for an
ensemble of friction and mass, each rollout corrected by the training pushes' residuals weighed by local
contact, as one normalised density over the final pose (beyond the paper; its §Conclusions and future work).

The density is a mixture: ``Σ_i Σ_j (w_ij / N) K(B1 | D_j · S_i)`` over the ``N`` rollouts ``S_i`` and the
residual kernels ``D_j`` (:func:`pushtorch.models.residual.corrected`), ``w_ij ∝ w_j · A_h(o_i, o_j)``
normalised over ``j``: ``w_j`` the normalised contact weight ``K^c`` of kernel ``j``'s training contact against
this push's manipulator contact (the paper's Eq. contact_frame_probability, as its motion kernels are weighed),
``A_h`` how alike rollout ``i``'s outcome is to kernel ``j``'s training rollout's
(:func:`pushtorch.models.residual.outcome_log_affinity`; 1 at the model's ``outcome_width = inf``): a correction
learnt where the simulator did one thing is applied where it does the same. The kernels' stds are the model's,
widened by ``sqrt(1 + κ·d²)`` where this contact is ``d`` contact-kernel stds from the nearest training contact
(``κ`` the model's ``widening``, chosen across a pool's training shapes; 0 for a model of one object); where the
rollouts did something ``n`` training-outcome stds² from what any training rollout did (the median over the
rollouts of :func:`pushtorch.models.residual.outcome_novelty`), a share ``ν·n / (1 + ν·n)`` of the spread of
the action's training outcomes (:func:`pushtorch.models.residual.outcome_spread`) is added to their variances
(``ν`` the model's ``novelty_widening``, chosen on an experiment's other training objects, 0 unless chosen): where
the simulator did something else the correction is unknown, and the outcome no surer than pushes differ. Its mode
is the mixture's highest corrected kernel centre. It is a :class:`~pushtorch.distribution.FinalPoseDistribution`
of one expert with exponent 1, so ``log_prob``, ``sample`` and the coverage work as for pushtorch's own prediction. A
model with a defensive part (``defensive = (ε0, λ, w)``, chosen with ``ν`` on pushes of shapes it did not see)
predicts ``(1 − ε)`` of that density and ``ε`` of the same kernels with ``w`` (m) and ``w ·``
:data:`~pushtorch.models.residual.DEFENSIVE_TURN` (rad) added to their stds in quadrature
(:class:`~pushtorch.distribution.DefensiveMixture`, the same mode), ``ε = ε0 + (1 − ε0)·λn / (1 + λn)``
(:func:`~pushtorch.models.residual.defensive_share`): where the rollouts did something new the corrections may
not hold at all, and a truth far from every corrected rollout costs ``−log ε`` and its distance in centimetres,
not its distance in the narrow kernels' millimetres. A model with an uncorrected share (``uncorrected = τ``,
chosen with them) gives a share ``ρ = τn / (1 + τn)`` of the narrow (and the wide) part to the rollouts themselves,
each ``ρ / N``, their kernels widened in quadrature by the action's corrections' spread
(:func:`~pushtorch.models.residual.correction_spread`), the corrected kernels ``1 − ρ``: where the rollouts did
something no training rollout did, which correction holds is unknown, and the simulator's own outcome, no surer
than the simulator has been off, is the prior a correction departs from. A model with a disagreement weight
``ξ`` (chosen with them) gives every hedge the novelty ``n + ξ·δ²``, ``δ²`` how far its push model's own point
lies from the corrected mode (:func:`pushtorch.models.residual.outcome_disagreement`): where the two disagree,
one misses. The hedges widen the density: the mode stays the corrected kernels'. The point prediction
``final_pose`` is the model's (:data:`~pushtorch.models.residual.POINTS`; the density is the same whichever):
that mode (``corrected``), the corrected kernels' local mode at the push model's motion width (``shifted``,
:func:`shifted_mode`), or the push model's own prediction of the same push from the same push condition, in the
cloud body's frame (``learned``):
:func:`pushtorch.prediction.predict` makes that prediction first, a caller of :func:`predict_residual` gives it.
A planner's candidates of one cloud share their push conditions (one pose estimate) and roll out an ensemble each
(:func:`residual_candidates`, through :func:`pushtorch.prediction.predict_candidates`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from pushtorch import se3
from pushtorch.distribution import DefensiveMixture, FinalPoseDistribution
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import Evaluation, KernelBandwidth, PoseKDE
from pushtorch.kde.normaliser import NO_CUTOFF
from pushtorch.models.clearance import check_start
from pushtorch.models.motion import contact_distances, contact_log_weights
from pushtorch.models.push_condition import PushCondition, features_for, push_conditions
from pushtorch.models.residual import (
    DEFENSIVE_TURN,
    POINTS,
    SHIFT_STEPS,
    ResidualModel,
    corrected,
    correction_spread,
    defensive_share,
    novelty_share,
    outcome_disagreement,
    outcome_log_affinity,
    outcome_novelty,
    outcome_spread,
    rollout_outcome,
    uncorrected_share,
)
from pushtorch.models.settings import as_generator
from pushtorch.perception import PointCloud
from pushtorch.sim.bodies import cloud_body, rollout_ensemble
from pushtorch.streams import keyed_seed

__all__ = ["ResidualCandidates", "ResidualPrediction", "corrected_mode", "defensive_factors", "disagreeing",
           "hedged_density", "learned_point", "narrow_density", "novelty_factors", "predict_residual", "rescaled",
           "residual_candidates", "scaled_parts", "shifted_mode"]


@dataclass
class ResidualPrediction:
    """A residual model's prediction.

    Attributes:
        start: ``()`` the cloud body's pose before the push (score the displacement from it).
        final_pose: ``()`` the model's point prediction (module docstring): the density's mode unless the model
            reports another; density: the mixture (module docstring).
        rollouts: ``(N,)`` each rollout's final pose of the body; physics: ``(N, 2)`` its ``(μ, m)``.
        thrown: rollouts whose body tipped, left the ground or was never touched (kept in the density: the
            flag says the simulator's outcome was not a push).
    """

    model_name: str
    action: torch.Tensor
    condition: PushCondition
    start: se3.Pose
    final_pose: se3.Pose
    density: FinalPoseDistribution | DefensiveMixture
    rollouts: se3.Pose
    physics: torch.Tensor
    thrown: int
    residual_weights: torch.Tensor = field(repr=False)  # (J,) the residual kernels' normalised log weights
    #: ``d²``: the squared distance, in contact-kernel stds, from this push's manipulator contact to the nearest
    #: training contact of the action (:func:`~pushtorch.models.motion.contact_distances`)
    contact_distance2: float = 0.0
    #: the factor the residual kernels' position std was widened by, by contact distance and novelty together
    #: (1: the model does not widen)
    widened_by: float = 1.0
    #: the novelty the hedges take: the rollouts' median novelty ``n`` (:func:`~pushtorch.models.residual.
    #: outcome_novelty`) plus the model's ``ξ`` times :attr:`disagreement`; 0 without outcomes
    outcome_novelty: float = 0.0
    #: the spread of the action's training outcomes, (m, rad) (:func:`~pushtorch.models.residual.outcome_spread`),
    #: towards which novelty widens the kernels
    outcome_spread: tuple[float, float] = (0.0, 0.0)
    #: ``ρ``: the share of the density on the rollouts themselves, uncorrected (0: none)
    uncorrected_share: float = 0.0
    #: the spread of the action's corrections, (m, rad) (:func:`~pushtorch.models.residual.correction_spread`),
    #: added to the uncorrected rollouts' kernel stds in quadrature
    correction_spread: tuple[float, float] = (0.0, 0.0)
    #: which point ``final_pose`` is (:data:`~pushtorch.models.residual.POINTS`)
    point: str = "corrected"
    #: ``δ²``: how far the push model's own point lies from the corrected mode at the kernels' unhedged stds, in
    #: the training outcomes' stds (:func:`~pushtorch.models.residual.outcome_disagreement`; 0 without it)
    disagreement: float = 0.0


def predict_residual(residual: ResidualModel, cloud, action, generator: torch.Generator | int | None = None,
                     robot_start: se3.Pose | None = None, learned: tuple[se3.Pose, se3.Pose] | None = None,
                     condition: PushCondition | None = None,
                     features: SurfaceFeatures | None = None) -> ResidualPrediction:
    """Predict where the object in ``cloud`` ends up after ``action`` (module docstring).

    Args:
        residual: a trained :class:`~pushtorch.models.residual.ResidualModel`.
        cloud: the single-shot cloud (world), or its surface features.
        action: one of the model's actions.
        generator: seeded generator or int seed (the push condition and the ensemble's physics draws).
        robot_start: the robot's start pose, when the caller places it; default the model's push condition.
        learned: ``(object start, final pose)`` of the push model's own prediction of the same push from the same
            robot start (:func:`pushtorch.prediction.predict` with ``residual.model``): the point a model whose
            point is ``learned`` reports, and what the disagreement ``δ²`` is measured from (its hedge's, where
            the model's ``ξ > 0``).
        condition: the push condition of this cloud and action made already (the push model's prediction's, whose
            robot start and pose estimate the rollouts then share), instead of ``robot_start``: its pose query is
            not made twice.
        features: the surface features of ``cloud`` under the model's settings, made already
            (:func:`~pushtorch.models.push_condition.features_for`): not made twice; the body is still built
            from the cloud's points.

    Raises:
        ModelError: a cloud that spans no volume, or a rollout with a non-finite outcome.
        InvalidParameterError: a model that needs ``learned`` (its point, or ``ξ > 0``) without it (predict
            through :func:`pushtorch.prediction.predict`, which makes it), or a point not one of ``POINTS``.
        InvalidParameterError, InvalidPoseError: as :func:`pushtorch.prediction.predict`.
    """
    model = residual.model
    if residual.point not in POINTS:
        raise InvalidParameterError(f"a residual model's point prediction is one of {POINTS}, got {residual.point!r}")
    if residual.needs_learned and learned is None:
        raise InvalidParameterError("this residual model reports or hedges by its push model's own prediction: "
                                    "predict through pushtorch.prediction.predict, or give it (learned=(object "
                                    "start, final pose))")
    generator = as_generator(generator)
    a = model.action_index(action)
    features = features_for(cloud if features is None else features, model.settings, model.position)
    if condition is None:
        start = None if robot_start is None else check_start(robot_start)
        condition = push_conditions(model, [features], [a], generator, False, [start])[0]
    elif robot_start is not None:
        raise InvalidParameterError("give the residual prediction a robot start or a push condition, not both")
    points = cloud.points if isinstance(cloud, PointCloud) else features.p
    body, body_start = cloud_body(points, condition.object_pose)
    motion = model.motions[a]
    physics = motion.manipulator.physics
    if physics is None:
        raise ModelError("this model's kernels do not know the friction and mass of their pushes: retrain it")
    n = residual.ensemble
    # the kernels' posterior weights where the model was conditioned on observed pushes (else equal)
    log_posterior = motion.manipulator.log_weight
    if log_posterior is None:
        picks = torch.randint(len(physics), (n,), generator=generator)
    else:
        picks = torch.multinomial(torch.softmax(log_posterior.detach().double().cpu(), 0), n, replacement=True,
                                  generator=generator)
    drawn = physics.detach().double().cpu()[picks]
    records = rollout_ensemble(body, body_start, condition.robot_start, motion.action, drawn[:, 0], drawn[:, 1],
                               residual.sim)
    finals = records.object_final
    if not (torch.isfinite(finals.p).all() and torch.isfinite(finals.q).all()):
        raise ModelError("a rollout of the cloud's body ended at a non-finite pose")
    dtype = model.dtype
    log_w = contact_log_weights(condition.manipulator_frame, motion.manipulator, condition.robot_start,
                                model.settings.contact_bandwidth, condition.contact_patch)
    log_w = torch.logsumexp(log_w.reshape(-1, len(motion.manipulator)), 0).double()
    if log_posterior is not None:
        log_w = log_w + log_posterior.detach().double().to(log_w.device)
    log_w = log_w - torch.logsumexp(log_w, 0)  # (J,) normalised
    robot = condition.robot_start
    robot = se3.Pose.unchecked(robot.p.double().reshape(1, 1, 3), robot.q.double().reshape(1, 1, 4))
    kernels = residual.residuals[a]
    means = corrected(robot, se3.Pose.unchecked(finals.p.unsqueeze(1), finals.q.unsqueeze(1)),
                      se3.Pose.unchecked(kernels.p.double().unsqueeze(0), kernels.q.double().unsqueeze(0)))
    means = se3.Pose.unchecked(means.p.reshape(-1, 3).to(dtype), se3.quat_normalize(means.q.reshape(-1, 4)).to(dtype))
    log_v = log_w.unsqueeze(0).expand(n, -1)  # (N, J) each rollout's residual kernels
    novelty = 0.0
    if residual.outcomes is not None:
        did = rollout_outcome(condition.robot_start, body_start, finals)
        kernels_did = residual.outcomes[a].to(did)
        if not math.isinf(residual.outcome_width):  # each rollout leans on the kernels whose rollout did the same
            log_v = log_v + outcome_log_affinity(did, kernels_did, residual.outcome_width)
            log_v = log_v - torch.logsumexp(log_v, 1, keepdim=True)
        reached = torch.isfinite(log_w).to(kernels_did.device)  # kernels no contact reaches correct nothing
        if bool(reached.any()):
            novelty = float(outcome_novelty(did, kernels_did[reached]).median())
    log_weights = (log_v - math.log(n)).reshape(1, -1).to(dtype)
    keep = torch.isfinite(log_weights[0])  # kernels no contact reaches weigh nothing
    means = means.take(keep.nonzero().reshape(-1))
    log_weights = log_weights[:, keep]
    d2 = float(contact_distances(condition.manipulator_frame, motion.manipulator, condition.robot_start,
                                 model.settings.contact_bandwidth, condition.contact_patch).amin())
    # corrections learnt far from this contact are less sure; where the simulator did something else, the outcome
    # is no surer than the action's pushes differ
    scale = math.sqrt(1.0 + residual.widening * d2)
    spread = (0.0, 0.0) if residual.outcomes is None else outcome_spread(residual.outcomes[a])

    def bandwidth_at(novelty: float) -> KernelBandwidth:
        share = novelty_share(residual.novelty_widening, novelty)
        return dataclasses.replace(residual.bandwidth, cutoff_std=NO_CUTOFF,
                                   p_std=math.sqrt((residual.bandwidth.p_std * scale) ** 2 + share * spread[0] ** 2),
                                   rot_std=math.sqrt((residual.bandwidth.rot_std * scale) ** 2
                                                     + share * spread[1] ** 2))

    bandwidth = bandwidth_at(novelty)
    # the mode: the corrected kernel centre of highest density (the hedges below never move it)
    unwidened = _mixture(means, log_weights, bandwidth, None)
    mode = _highest_centre(unwidened)
    disagreement = 0.0
    if learned is not None and residual.outcomes is not None:  # the push model's point against the unhedged mode
        bare = mode if novelty_share(residual.novelty_widening, novelty) == 0 \
            else _highest_centre(_mixture(means, log_weights, bandwidth_at(0.0), None))
        cpu = ("cpu", torch.float64)
        own = learned_point(tuple(pose.to(*cpu) for pose in learned), body_start)
        disagreement = outcome_disagreement(*(rollout_outcome(condition.robot_start.to(*cpu), body_start, pose)
                                              for pose in (own, bare.to(*cpu))), residual.outcomes[a].cpu())
        if residual.disagreement > 0:  # where the two disagree, one misses: hedged as if the rollouts were newer
            novelty += residual.disagreement * disagreement
            bandwidth = bandwidth_at(novelty)
    uncorrected = uncorrected_share(residual.uncorrected, novelty)
    spread_c = correction_spread(kernels)

    def hedged(widths) -> FinalPoseDistribution | DefensiveMixture:
        """The corrected kernels at ``widths``; where the rollouts did something no training rollout did, with a
        share on the rollouts themselves, no surer than the simulator has been off (the corrections' spread)."""
        corrected_part = _mixture(means, log_weights, widths, mode.vector())
        if uncorrected == 0:
            return corrected_part
        return DefensiveMixture(corrected_part, _rollout_mixture(finals, widths, spread_c, mode.vector()),
                                uncorrected)

    density = hedged(bandwidth)
    share = defensive_share(residual.defensive, novelty)
    if share > 0:  # where the corrections may not hold: the same kernels, centimetres wider
        w = residual.defensive[2]
        density = DefensiveMixture(density, hedged(_widened(bandwidth, (w, w * DEFENSIVE_TURN))), share)
    thrown = int((~records.valid).sum())
    if residual.point == "learned":
        point = learned_point(learned, body_start.to(dtype))
    elif residual.point == "shifted":
        point = shifted_mode(unwidened, model.settings.motion_bandwidth)
    else:
        point = mode
    return ResidualPrediction(residual.name, motion.action, condition, body_start.to(dtype), point, density,
                              se3.Pose.unchecked(finals.p.to(dtype), finals.q.to(dtype)), drawn, thrown, log_w, d2,
                              bandwidth.p_std / residual.bandwidth.p_std, novelty, spread, uncorrected, spread_c,
                              residual.point, disagreement)


@dataclass(frozen=True)
class ResidualCandidates:
    """Many candidate pushes of one cloud predicted by a residual model
    (:func:`pushtorch.prediction.predict_candidates`, :func:`residual_candidates`).

    Attributes:
        predictions: per candidate, its :class:`ResidualPrediction`, or None where it is not a push.
        valid: ``(C,)`` bool, the candidates that are pushes.
        reasons: per candidate, why it is not a push (None where it is).
        estimate: ``()`` the object's pose estimate every candidate's push condition shares (None: no candidate).
    """

    predictions: list[ResidualPrediction | None]
    valid: torch.Tensor
    reasons: tuple[str | None, ...]
    estimate: se3.Pose | None

    def log_prob(self, goal: torch.Tensor) -> torch.Tensor:
        """``(C,)`` the log density (nats) each candidate gives the object ending at ``goal`` ``(7,)`` (x, y, z, w,
        x, y, z), a pose of the estimated object as a push model's candidates take it (the motion from
        :attr:`estimate` to ``goal``, applied to each prediction's cloud body, :func:`learned_point`), −inf for a
        candidate that is not a push; differentiable with respect to ``goal``. Each density is scored on its own:
        their widths differ with each push's contact distance and novelty, so they are not one batched density."""
        out = torch.full((len(self.predictions),), -math.inf, dtype=goal.dtype, device=goal.device)
        if self.estimate is None:
            return out
        target = se3.Pose.unchecked(goal.reshape(7)[:3], goal.reshape(7)[3:])
        values = [p.density.log_prob(learned_point((self.estimate, target), p.start).vector()).reshape(()).to(goal)
                  for p in self.predictions if p is not None]
        return out.index_put((self.valid.nonzero(as_tuple=True)[0].to(goal.device),), torch.stack(values))


def residual_candidates(residual: ResidualModel, cloud, features, conditions: list[PushCondition | None],
                        reasons: list[str | None], actions: torch.Tensor, keys: torch.Tensor, seed: int,
                        learned: list[tuple[se3.Pose, se3.Pose] | None] | None = None) -> ResidualCandidates:
    """A residual model's predictions of a planner's candidates of one cloud from their push conditions, made once
    for all (one pose estimate, :func:`~pushtorch.models.push_condition.candidate_conditions`): each candidate's
    ensemble drawn from a generator seeded by the call's ``seed`` and its ``keys`` entry (its start and action,
    :func:`~pushtorch.streams.content_keys`), so no order or other candidate changes it. A candidate whose rollouts
    fail (a non-finite outcome) is flagged, with the reason, as a start that is not a push is.

    Args:
        cloud, features: the cloud (its points build the body) and its surface features under the model's settings.
        conditions, reasons: per candidate its push condition, or None and why not.
        actions: ``(C, 2)`` each candidate's action; keys: ``(C,)`` int64 its key.
        learned: per candidate the push model's own ``(object start, final pose)``, for a model whose point is
            learned (None otherwise).
    """
    predictions: list[ResidualPrediction | None] = []
    reasons = list(reasons)
    for i, condition in enumerate(conditions):  # each candidate rolls its own ensemble out: a simulator call each
        made = None
        if condition is not None:
            generator = torch.Generator().manual_seed(keyed_seed(seed, int(keys[i])))
            try:
                made = predict_residual(residual, cloud, actions[i], generator, condition=condition, features=features,
                                        learned=None if learned is None else learned[i])
            except ModelError as exc:  # its rollouts failed: not a prediction
                reasons[i] = str(exc)
        predictions.append(made)
    estimate = next((c.object_pose for c in conditions if c is not None), None)
    valid = torch.tensor([p is not None for p in predictions], dtype=torch.bool)
    return ResidualCandidates(predictions, valid, tuple(reasons), None if not bool(valid.any()) else estimate)


def learned_point(learned: tuple[se3.Pose, se3.Pose], body_start: se3.Pose) -> se3.Pose:
    """``()`` the push model's prediction ``learned = (object start, final pose)`` as the final pose of the cloud
    body whose start is ``body_start``: the same rigid motion, so the same displacement, in the body's frame."""
    start, final = (se3.Pose.unchecked(p.p.reshape(3).double(), p.q.reshape(4).double()) for p in learned)
    body = se3.Pose.unchecked(body_start.p.reshape(3).double(), body_start.q.reshape(4).double())
    moved = se3.compose(final, se3.compose(se3.inverse(start), body))
    return se3.Pose.unchecked(moved.p.to(body_start.p.dtype),
                              se3.quat_normalize(moved.q).to(body_start.q.dtype))


def _highest_centre(density: FinalPoseDistribution) -> se3.Pose:
    """``()`` the kernel centre of ``density`` (one expert, every kernel in full) where it is highest."""
    best = int(density.unnormalised_log_prob(density.means.vector().unsqueeze(-2)).reshape(-1).argmax())
    return density.means.take(best)


#: The kernel centres a ``shifted`` point's mean shift starts from, the highest at the motion width: its cost is
#: starts × kernels a step, not kernels²
SHIFT_STARTS = 16


def shifted_mode(density: FinalPoseDistribution, bandwidth: KernelBandwidth, steps: int = SHIFT_STEPS) -> se3.Pose:
    """``()`` the local mode of ``density``'s kernels (their centres and weights) at ``bandwidth`` (no cut-off)
    that is highest there, found by ``steps`` mean-shift steps from the :data:`SHIFT_STARTS` kernel centres where
    that density is highest: the residual model's ``shifted`` point, at the push model's motion kernels' width."""
    wide = KernelBandwidth(bandwidth.p_std, bandwidth.rot_std, cutoff_std=NO_CUTOFF, alpha_t=bandwidth.alpha_t)
    means = density.means
    centres = se3.Pose.unchecked(means.p.unsqueeze(0), means.q.unsqueeze(0))
    kde = PoseKDE(centres, wide, density.log_weights.reshape(1, -1))
    top = kde.log_prob(centres).reshape(-1).topk(min(SHIFT_STARTS, means.p.shape[0])).indices
    x = se3.Pose.unchecked(centres.p[:, top], centres.q[:, top])
    for _ in range(int(steps)):
        x = kde.mean_shift(x)
    best = int(kde.log_prob(x).reshape(-1).argmax())
    return se3.Pose.unchecked(x.p[0, best], se3.quat_normalize(x.q[0, best]))


def corrected_mode(prediction: ResidualPrediction, factor: float) -> se3.Pose:
    """``()`` the mode ``prediction``'s corrected kernels would have with their stds times ``factor`` (the mode
    :func:`predict_residual` gives a model whose kernels were scaled so): what choosing a scale and a point
    prediction on held-out pushes scores without rolling them out again."""
    return _highest_centre(scaled_parts(prediction, (float(factor), float(factor)))[0])


def _mixture(means: se3.Pose, log_weights: torch.Tensor, bandwidth, mode: torch.Tensor | None) -> FinalPoseDistribution:
    """The residual density: one expert of exponent 1, every kernel in full (no cut-off)."""
    return FinalPoseDistribution(means, log_weights, bandwidth, torch.zeros(3, dtype=torch.int64),
                                 torch.ones(1, dtype=means.p.dtype), mode, Evaluation.DENSE, means, kernels="full")


def narrow_density(prediction: ResidualPrediction) -> FinalPoseDistribution:
    """The prediction's corrected kernels as a density, without its defensive part or uncorrected share (the
    density itself where it has neither)."""
    density = prediction.density
    while isinstance(density, DefensiveMixture):
        density = density.narrow
    return density


def rescaled(prediction: ResidualPrediction, factor: float | tuple[float, float],
             defensive: tuple[float, tuple[float, float]] | None = None) -> FinalPoseDistribution | DefensiveMixture:
    """``prediction``'s corrected kernels with their stds times ``factor`` (or times ``(position, rotation)``
    factors; same kernels, weights and mode), and with ``defensive = (ε, wide factors)`` a share ``ε`` of the same
    kernels times the wide factors (:func:`defensive_factors`): what scoring a widening on held-out pushes needs
    without rolling them out again (with an uncorrected share too: :func:`scaled_parts`)."""

    def times(f):
        return scaled_parts(prediction, f if isinstance(f, tuple) else (f, f))[0]

    if defensive is None or defensive[0] == 0:
        return times(factor)
    return DefensiveMixture(times(factor), times(defensive[1]), defensive[0])


def scaled_parts(prediction: ResidualPrediction, factor: tuple[float, float]
                 ) -> tuple[FinalPoseDistribution, FinalPoseDistribution]:
    """``prediction``'s corrected kernels and its rollouts themselves, each as a normalised density with the
    narrow kernels' stds times ``factor = (position, rotation)`` (the rollouts' widened by the corrections' spread,
    as :func:`predict_residual` widens them): the two parts whose mixtures, at a defensive part's and an
    uncorrected share's weights, make every density a choice scores (without rolling the push out again)."""
    density = narrow_density(prediction)
    bandwidth = dataclasses.replace(density.bandwidth, p_std=density.bandwidth.p_std * factor[0],
                                    rot_std=density.bandwidth.rot_std * factor[1])
    mode = density.mode  # the corrected kernels' (a learned point is not the density's mode)
    return (_mixture(density.means, density.log_weights, bandwidth, mode),
            _rollout_mixture(prediction.rollouts, bandwidth, prediction.correction_spread, mode))


def disagreeing(prediction: ResidualPrediction, weight: float) -> ResidualPrediction:
    """``prediction`` (made without a disagreement weight, knowing its ``δ²``) as a model of disagreement weight
    ``ξ = weight`` hedges it: its novelty ``n + ξ·δ²`` (what :func:`predict_residual` gives such a model)."""
    return dataclasses.replace(prediction,
                               outcome_novelty=prediction.outcome_novelty + weight * prediction.disagreement)


def hedged_density(prediction: ResidualPrediction, factors: tuple[float, float], part: tuple[float, float, float],
                   rate: float) -> FinalPoseDistribution | DefensiveMixture:
    """``prediction``'s density (made without hedges) with its narrow kernels' stds times ``factors``, the
    defensive part ``part = (ε0, λ, w)`` and the uncorrected share's ``rate`` at its outcome novelty: the density
    :func:`predict_residual` makes from the same rollouts for a model of those hedges (what
    :func:`pushtorch.evaluation.transfer.residual_nll_grid` scores without building it, and a choice of the hedges
    draws from to measure their calibration)."""
    rho = uncorrected_share(rate, prediction.outcome_novelty)
    eps = defensive_share(part, prediction.outcome_novelty)

    def mixed(f: tuple[float, float]) -> FinalPoseDistribution | DefensiveMixture:
        corrected_part, rollouts = scaled_parts(prediction, f)
        return corrected_part if rho == 0 else DefensiveMixture(corrected_part, rollouts, rho)

    density = mixed(factors)
    if eps > 0:
        density = DefensiveMixture(density, mixed(defensive_factors(prediction, factors, part[2])), eps)
    return density


def _rollout_mixture(rollouts: se3.Pose, bandwidth, spread: tuple[float, float], mode: torch.Tensor
                     ) -> FinalPoseDistribution:
    """The rollouts ``(N,)`` themselves, uncorrected, as a density: each ``1 / N``, at ``bandwidth`` widened by
    the corrections' ``spread`` (in the mode's dtype)."""
    n, dtype = int(rollouts.p.shape[0]), mode.dtype
    raw = se3.Pose.unchecked(rollouts.p.to(dtype), se3.quat_normalize(rollouts.q).to(dtype))
    return _mixture(raw, torch.full((1, n), -math.log(n), dtype=dtype), _widened(bandwidth, spread), mode)


def _widened(bandwidth, by: tuple[float, float]):
    """``bandwidth`` with ``by = (m, rad)`` added to its stds in quadrature."""
    return dataclasses.replace(bandwidth, p_std=math.hypot(bandwidth.p_std, by[0]),
                               rot_std=math.hypot(bandwidth.rot_std, by[1]))


def novelty_factors(prediction: ResidualPrediction, novelty_widening: float, scale: float = 1.0
                    ) -> tuple[float, float]:
    """The ``(position, rotation)`` factors on the stds of ``prediction`` (made by a model of novelty widening 0)
    that give its kernels' stds times ``scale`` widened at ``novelty_widening`` (module docstring), for
    :func:`rescaled`: how a widening is scored from one prediction."""
    share = novelty_share(novelty_widening, prediction.outcome_novelty)
    bandwidth = narrow_density(prediction).bandwidth
    return (math.sqrt(scale**2 + share * prediction.outcome_spread[0] ** 2 / bandwidth.p_std**2),
            math.sqrt(scale**2 + share * prediction.outcome_spread[1] ** 2 / bandwidth.rot_std**2))


def defensive_factors(prediction: ResidualPrediction, factors: tuple[float, float], width: float
                      ) -> tuple[float, float]:
    """The factors on ``prediction``'s stds of a defensive part of ``width`` (``w``, m) over kernels scaled by
    ``factors``: ``w`` and ``w ·`` :data:`~pushtorch.models.residual.DEFENSIVE_TURN` added to their stds in
    quadrature, as :func:`predict_residual` adds them."""
    bandwidth = narrow_density(prediction).bandwidth
    return (math.hypot(factors[0], width / bandwidth.p_std),
            math.hypot(factors[1], width * DEFENSIVE_TURN / bandwidth.rot_std))
