"""The residual model, ``pushtorch_residual``: physics on the body the observed cloud builds, corrected by how
the world's outcomes differed from the simulator's in the training pushes (beyond the paper: its §Conclusions
and future work ask for models that transfer to unlike shapes; a simulator with a learned stochastic residual
follows Ajay et al. 2018, "Augmenting physical simulators with stochastic neural networks").

Local contact decides where a learned model transfers (paper, §Contact Models), and it cannot tell an object
that spins against the bumper from one that sticks to it; a simulator on the observed shape can, but its
contact and friction are not the world's. The residual model keeps both:

* **Training** (:func:`train_residual_model`). Every training push is rolled out again in the model's
  simulator (``sim.engine``), with the push's own robot start, action, friction and mass, on the body that a
  single-shot cloud of the object at that push's start builds (:func:`pushtorch.sim.bodies.cloud_body`). The
  residual is how the world's outcome of the body's reference pose differs from the rollout's, in the robot's
  start frame about the rollout's centre (:func:`residual_of`): a lateral slide or an extra turn of the
  object, whatever its shape or heading. Each manipulator kernel of the underlying :class:`PushModel` carries
  its push's residual, so residuals are weighed by local contact as the paper's motion kernels are.
* **Prediction** (:func:`pushtorch.prediction.residual.predict_residual`). The push condition is the
  model's own (or a given robot start); the cloud's body is rolled out for an ensemble of ``(μ, m)`` drawn from
  the training pushes' physics, in one call; each rollout is corrected by every residual kernel, weighted by
  its contact weight, and the density is the mixture of these kernels (:data:`RESIDUAL_LADDER` widths chosen
  by leave-one-push-out likelihood), with a defensive share of the same kernels centimetres wider that grows
  with how new the rollouts are (:data:`DEFENSIVE_PARTS`, :func:`defensive_share`), and a share of the rollouts
  themselves, uncorrected, that grows with it too (:data:`UNCORRECTED_RATES`), the push model's disagreement
  with the corrected mode counted as novelty (:data:`DISAGREEMENT_WEIGHTS`). Its point prediction is the
  density's mode, that mode moved by mean shift, or the push model's own prediction from the same push condition,
  whichever was closest on the model's held-out training pushes (:data:`POINTS`).

Decisions are in docs/method.md, "The residual model".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.kde import KernelBandwidth
from pushtorch.kde.normaliser import log_rotation_normaliser
from pushtorch.models.model import PushModel, write_model_file
from pushtorch.objects import ObjectModel
from pushtorch.perception import capture_partial_cloud
from pushtorch.sim.bodies import cloud_body, rollout_ensemble
from pushtorch.sim.engines import engine_version
from pushtorch.sim.settings import SimSettings

Tensor = torch.Tensor

__all__ = ["DEFAULT_ENSEMBLE", "DEFENSIVE_PARTS", "DEFENSIVE_TURN", "DISAGREEMENT_WEIGHTS",
           "MAX_DEFENSIVE_SHARE", "NOVELTY_FORM", "NOVELTY_WIDENINGS", "OUTCOME_LADDER", "POINTS",
           "RESIDUAL_LADDER", "ResidualModel", "SHIFT_STEPS", "UNCORRECTED_RATES", "choose_bandwidth",
           "correction_spread", "corrected", "defensive_share", "novelty_scored_as_now",
           "novelty_share", "outcome_disagreement", "outcome_log_affinity", "outcome_novelty",
           "outcome_spread", "residual_of", "rollout_outcome", "train_residual_model", "uncorrected_share",
           "with_ensemble"]

#: Rollouts per prediction unless the model says otherwise, chosen by held-out likelihood on generated training
#: shapes among the sizes within 3× a pushtorch prediction (tools/residual_ensemble.py on an Intel Xeon, 2 cores:
#: nll −17.31 / −18.26 / −18.83 at 2 / 4 / 8 rollouts, 2.0 / 3.0 / 5.0 × pushtorch's time; 2 is 0.95 nats worse
#: than 4, paired SE 0.71). tools/bench_residual.py: 0.35 s at 4 against pushtorch's 0.15 s.
DEFAULT_ENSEMBLE = 4
#: The residual kernels' stds tried, position (m) × rotation (rad): the pair of highest leave-one-push-out
#: likelihood of the training residuals is kept.
RESIDUAL_LADDER = ((0.0025, 0.005, 0.01, 0.02, 0.04, 0.08), (0.005, 0.01, 0.02, 0.04, 0.08, 0.16))

#: The widths tried for pairing residual kernels with a rollout by its outcome, in the training outcomes' stds
#: (``inf``: every kernel weighs alike whatever the rollout did): chosen with the kernels' stds, leave one push out.
OUTCOME_LADDER = (0.25, 0.5, 1.0, 2.0, 4.0, math.inf)

#: The novelty widenings ``ν`` tried: a prediction whose rollouts did something ``n`` training-outcome stds² from
#: what any training rollout did (:func:`outcome_novelty`, their median) adds a share ``ν·n / (1 + ν·n)`` of the
#: training outcomes' spread (:func:`outcome_spread`) to its kernels' variances (0: never).
NOVELTY_WIDENINGS = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
#: The defensive parts tried with each widening, ``(ε0, λ, w)``: a share ``ε = ε0 + (1 − ε0)·λn / (1 + λn)`` of
#: the density (:func:`defensive_share`, ``n`` the prediction's outcome novelty) is the same kernels with ``w`` (m)
#: and ``w · DEFENSIVE_TURN`` (rad) added to their stds in quadrature (:class:`~pushtorch.distribution.
#: DefensiveMixture`; ``(0, 0, 0)``: none). Chosen with ``ν`` (and a pool's ``κ``) on pushes of shapes the model
#: did not see. The share grows with novelty (a constant one made the own objects' 90 % regions hold every truth);
#: the widths are absolute (one action's training outcomes spread by millimetres, another shape's miss by cm).
DEFENSIVE_PARTS = ((0.0, 0.0, 0.0),) + tuple((floor, rate, width) for floor in (0.0, 0.03)
                                             for rate in (0.0, 0.1, 1.0, 10.0) for width in (0.01, 0.03, 0.1)
                                             if floor or rate)
#: The uncorrected shares' rates ``τ`` tried with each widening and defensive part: a share ``τn / (1 + τn)`` of
#: the density (narrow and wide alike) is the rollouts themselves, uncorrected, their kernels widened by the
#: corrections' spread (:func:`correction_spread`), ``n`` the prediction's outcome novelty (:func:`uncorrected_share`;
#: 0: none). Where the simulator did something no training rollout did, which correction holds is unknown: a
#: correction learnt on one shape can move a shape the simulator gets right away from the truth, and the
#: simulator's own outcome is the prior the corrections depart from.
UNCORRECTED_RATES = (0.0, 0.01, 0.1, 1.0, 10.0)
#: The largest defensive share: the narrow part keeps a weight however new the rollouts
MAX_DEFENSIVE_SHARE = 0.999
#: Radians of a defensive part's rotation width per metre of its position width: the paper's motion kernels' ratio
#: (1 cm to 0.05 rad, §Motion Model's bandwidths)
DEFENSIVE_TURN = 5.0
#: Which form of the novelty widening a model's choice of ``ν`` was made for (kept beside it in its ``meta``; a
#: cached choice of another form is made again): 7, the share of the outcomes' spread, the defensive part, the
#: uncorrected share and the disagreement weight chosen together, the own pushes held out in the choice itself
#: and a tie in likelihood broken by calibration per group of held-out pushes, then by sharpness among those
#: calibrated alike, each model's on the pushes it predicted (9; earlier forms lacked one or more of these)
NOVELTY_FORM = 9
#: The disagreement weights ``ξ`` tried with each hedge: a prediction whose push model's own point lies ``δ²``
#: training-outcome stds² from its corrected mode (:func:`outcome_disagreement`) is hedged as if its rollouts'
#: novelty were ``n + ξ·δ²`` (0: theirs alone). Where the two disagree, one of them misses, at any novelty.
DISAGREEMENT_WEIGHTS = (0.0, 0.1, 0.3, 1.0, 3.0)
#: A model's point predictions: ``corrected``, its density's mode (the highest corrected kernel centre);
#: ``shifted``, that mixture's local mode at the push model's motion kernels' width (where pushtorch anneals its
#: own mode), found by mean shift from its highest kernel centres (:func:`pushtorch.prediction.residual.
#: shifted_mode`); ``learned``, its push model's own prediction (pushtorch's annealed product of experts) from the
#: same push condition. Chosen per model by the mean H_acc of each on its own held-out training pushes
#: (:func:`pushtorch.evaluation.transfer.choose_residual_scale`; a pooled model's on its held-out shapes' pushes,
#: :func:`pushtorch.evaluation.transfer.choose_residual_widening`): where the simulator is far off the world for the
#: training object, the corrections are large and the corrected rollouts scatter, while the learned kernels of the
#: same pushes keep their contact's outcome. The density is the corrected one whichever.
POINTS = ("corrected", "shifted", "learned")
#: Mean-shift steps of the ``shifted`` point
SHIFT_STEPS = 20

_IDENTITY_Q = torch.tensor([1.0, 0.0, 0.0, 0.0])


def rollout_outcome(robot_start: se3.Pose, start: se3.Pose, final: se3.Pose) -> Tensor:
    """``(..., 3)`` float64 what a rollout did, in the robot's start frame: the body's displacement ``(dx, dy)``
    (m) and its turn (rad, wrapped to (−π, π]) from ``start`` to ``final`` (batch dims broadcast)."""
    s0 = se3.relative(se3.Pose.unchecked(robot_start.p.double(), robot_start.q.double()),
                      se3.Pose.unchecked(start.p.double(), start.q.double()))
    s1 = se3.relative(se3.Pose.unchecked(robot_start.p.double(), robot_start.q.double()),
                      se3.Pose.unchecked(final.p.double(), final.q.double()))
    p0, p1 = torch.broadcast_tensors(s0.p, s1.p)
    turn = se3.yaw_of(s1.q) - se3.yaw_of(s0.q)
    turn = torch.atan2(torch.sin(turn), torch.cos(turn))
    return torch.cat([(p1 - p0)[..., :2], turn.unsqueeze(-1).expand(*p1.shape[:-1], 1)], -1)


def _outcome_d2(queries: Tensor, kernels: Tensor, stds_of: Tensor | None = None) -> Tensor:
    """``(Q, J)`` float64 squared distances of outcomes ``queries (Q, 3)`` to ``kernels (J, 3)``, per component in
    the stds of ``stds_of`` (default the kernels; turns wrapped)."""
    q, k = queries.double(), kernels.double()
    s = k if stds_of is None else stds_of.double()
    scale = s.std(0).clamp_min(1e-9) if s.shape[0] > 1 else torch.ones(3, dtype=torch.float64, device=k.device)
    d = q.unsqueeze(1) - k.unsqueeze(0)
    d[..., 2] = torch.atan2(torch.sin(d[..., 2]), torch.cos(d[..., 2]))
    return ((d / scale) ** 2).sum(-1)


def outcome_log_affinity(queries: Tensor, kernels: Tensor, width: float) -> Tensor:
    """``(Q, J)`` float64 log of how much each training rollout's outcome ``kernels (J, 3)`` resembles each of
    ``queries (Q, 3)`` (:func:`rollout_outcome`): a Gaussian of ``width`` stds of the training outcomes per
    component, up to a constant; 0 everywhere for an infinite width."""
    if math.isinf(width):
        return torch.zeros(queries.shape[0], kernels.shape[0], dtype=torch.float64, device=kernels.device)
    return -_outcome_d2(queries, kernels) / (2.0 * width**2)


def outcome_novelty(queries: Tensor, kernels: Tensor) -> Tensor:
    """``(Q,)`` float64 how new each rollout outcome of ``queries (Q, 3)`` is: its squared distance, in the
    training outcomes' stds, to the nearest of ``kernels (J, 3)`` (what each kernel's training rollout did)."""
    return _outcome_d2(queries, kernels).amin(1)


def outcome_disagreement(a: Tensor, b: Tensor, outcomes: Tensor) -> float:
    """``δ²``: the squared distance between two outcomes ``a`` and ``b`` ``(3,)`` (:func:`rollout_outcome`) in the
    stds of the training outcomes ``outcomes (J, 3)``: how far apart two predictions of one push lie."""
    return float(_outcome_d2(a.reshape(1, 3), b.reshape(1, 3).to(a.device), outcomes.to(a.device))[0, 0])


def outcome_spread(outcomes: Tensor) -> tuple[float, float]:
    """How differently the training pushes of an action turned out: the std of their rollouts' displacement per
    planar component (m; the rms of the two) and of their turn (rad), from ``outcomes (J, 3)``
    (:func:`rollout_outcome`). What a prediction's kernels widen towards where its rollouts did something no
    training rollout did: there the correction is unknown, and the outcome no surer than pushes of the action
    differ."""
    o = outcomes.double().reshape(-1, 3)
    if o.shape[0] < 2:
        return 0.0, 0.0
    turn = torch.atan2(torch.sin(o[:, 2] - o[0, 2]), torch.cos(o[:, 2] - o[0, 2]))  # unwrapped about the first
    return float(o[:, :2].var(0).mean().sqrt()), float(turn.std())


def correction_spread(residuals: se3.Pose) -> tuple[float, float]:
    """How far the simulator's outcomes were from the world's in the training pushes of an action: the rms of the
    corrections ``residuals (J,)`` (:func:`residual_of`) per planar component of their translation (m) and of their
    rotation angle (rad). What a rollout left uncorrected is no surer than: its kernels are widened by it."""
    p, q = residuals.p.double().reshape(-1, 3), residuals.q.double().reshape(-1, 4)
    if not p.shape[0]:
        return 0.0, 0.0
    angle = 2.0 * torch.atan2(q[:, 1:].norm(dim=-1), q[:, 0].abs())
    return float((p[:, :2] ** 2).mean().sqrt()), float((angle**2).mean().sqrt())


def novelty_scored_as_now(entry: dict | None, grid=NOVELTY_WIDENINGS, parts=DEFENSIVE_PARTS,
                          rates=UNCORRECTED_RATES, weights=DISAGREEMENT_WEIGHTS) -> bool:
    """Whether a model's ``meta`` entry of novelty-widening scores (``meta["novelty"]``) was made over ``grid`` ×
    the defensive ``parts`` × the uncorrected shares' ``rates`` × the disagreement ``weights`` and for today's
    :data:`NOVELTY_FORM`: one made otherwise is made again."""
    entry = entry or {}
    return (entry.get("grid") == [float(v) for v in grid] and entry.get("form") == NOVELTY_FORM
            and entry.get("defensive") == [[float(v) for v in part] for part in parts]
            and entry.get("uncorrected") == [float(v) for v in rates]
            and entry.get("disagreement") == [float(v) for v in weights])


def defensive_share(part: tuple[float, float, float], novelty: float) -> float:
    """``ε0 + (1 − ε0)·λn / (1 + λn)``, at most :data:`MAX_DEFENSIVE_SHARE`: the share of a prediction's density in
    the defensive ``part = (ε0, λ, w)`` (:data:`DEFENSIVE_PARTS`) at the prediction's outcome novelty ``n``."""
    floor, rate, _ = part
    return min(floor + (1.0 - floor) * novelty_share(rate, novelty), MAX_DEFENSIVE_SHARE)


def uncorrected_share(rate: float, novelty: float) -> float:
    """``τn / (1 + τn)``, at most :data:`MAX_DEFENSIVE_SHARE`: the share of a prediction's density on its rollouts
    themselves, uncorrected, at the model's rate ``τ`` (:data:`UNCORRECTED_RATES`) and outcome novelty ``n``."""
    return min(novelty_share(rate, novelty), MAX_DEFENSIVE_SHARE)


def novelty_share(novelty_widening: float, novelty: float) -> float:
    """``ν·n / (1 + ν·n)``: the share of the outcomes' spread added to a prediction's kernel variances at the
    model's novelty widening ``ν`` and the prediction's outcome novelty ``n`` (0 at either 0, towards 1 as the
    rollouts do something ever further from every training rollout)."""
    x = float(novelty_widening) * float(novelty)
    return x / (1.0 + x)


def _centre(pose: se3.Pose) -> se3.Pose:
    """The pure translation to ``pose``'s position (same batch)."""
    return se3.Pose.unchecked(pose.p, _IDENTITY_Q.to(pose.q).expand_as(pose.q))


def residual_of(robot_start: se3.Pose, simulated: se3.Pose, world: se3.Pose) -> se3.Pose:
    """The correction ``D`` that carries a rollout's final pose to the world's (batch dims broadcast): in the
    robot's start frame ``R0``, with ``s = R0⁻¹ ∘ simulated``, ``y = R0⁻¹ ∘ world`` and ``C`` the translation to
    ``s``'s position, ``y = C ∘ D ∘ C⁻¹ ∘ s``: ``D``'s translation is the world's extra slide, its rotation the
    extra turn about the object's centre."""
    s, y = se3.relative(robot_start, simulated), se3.relative(robot_start, world)
    c = _centre(s)
    return se3.compose(se3.inverse(c), se3.compose(y, se3.compose(se3.inverse(s), c)))


def corrected(robot_start: se3.Pose, simulated: se3.Pose, residual: se3.Pose) -> se3.Pose:
    """A rollout's final pose with a residual applied (world; the inverse of :func:`residual_of`; batch dims
    broadcast)."""
    s = se3.relative(robot_start, simulated)
    c = _centre(s)
    return se3.compose(robot_start, se3.compose(c, se3.compose(residual, se3.compose(se3.inverse(c), s))))


@dataclass
class ResidualModel:
    """A push model's contact kernels, each with its training push's residual, and the simulator to roll out in.

    Attributes:
        model: the :class:`PushModel` whose push conditions place the robot and whose manipulator contact kernels
            weigh the residuals.
        residuals: per action, ``(J,)`` the residual of each manipulator kernel's push (:func:`residual_of`).
        bandwidth: the residual kernels' stds (no cut-off: the density is a plain mixture).
        sim: the rollout engine and its settings; engine_version: that engine's version string at training.
        ensemble: rollouts per prediction.
        meta: how the residuals and widths were chosen (scores, rollouts that failed).
        shapes: a pooled model's, per action ``(J,)`` the training shape (index into ``shape_names``) of each
            residual kernel's push; None for one object's.
        shape_names: the training objects, in the order the residuals were taken.
        widening: ``κ``, the residual kernels' stds are widened by ``sqrt(1 + κ·d²)`` where the prediction's
            manipulator contact is ``d`` contact-kernel stds from every training contact (0: never;
            :func:`pushtorch.evaluation.transfer.choose_residual_widening` chooses it across training shapes).
        outcomes: per action ``(J, 3)`` what each kernel's training rollout did (:func:`rollout_outcome`), or
            None (a file written before rollouts were kept: every kernel then weighs alike for every rollout).
        outcome_width: ``h``, how closely a prediction's rollout pairs with the kernels whose training rollout
            did the same (:func:`outcome_log_affinity`; ``inf``: not at all), chosen with the stds.
        novelty_widening: ``ν``: a prediction whose rollouts' outcomes lie a median ``n`` (:func:`outcome_novelty`)
            from every training rollout's adds a share :func:`novelty_share` of the action's
            :func:`outcome_spread` to the residual kernels' variances (0: never;
            :func:`pushtorch.evaluation.transfer.choose_novelty_widening` chooses it across training objects).
        defensive: ``(ε0, λ, w)``: a share :func:`defensive_share` of the density, growing with the prediction's
            outcome novelty, is the same kernels with ``w`` (m) and ``w ·`` :data:`DEFENSIVE_TURN` (rad) added in
            quadrature to their stds, for the predictions whose corrections do not hold (zeros: none; chosen with
            ``ν`` or ``κ``, :data:`DEFENSIVE_PARTS`).
        uncorrected: ``τ``: a share :func:`uncorrected_share` ``(τ, n)`` of the density is the rollouts
            themselves, uncorrected and widened by the corrections' spread (:func:`correction_spread`), where they
            did something no training rollout did (0: none; chosen with the defensive part,
            :data:`UNCORRECTED_RATES`).
        point: which point prediction the model reports, one of :data:`POINTS` (``corrected`` unless chosen).
        disagreement: ``ξ``: the hedges take the novelty ``n + ξ·δ²``, ``δ²`` how far the push model's own point
            lies from the corrected mode (:func:`outcome_disagreement`; 0: ``n`` alone; chosen with ``ν``,
            :data:`DISAGREEMENT_WEIGHTS`).
    """

    model: PushModel
    residuals: list[se3.Pose]
    bandwidth: KernelBandwidth
    sim: SimSettings
    engine_version: str
    ensemble: int = DEFAULT_ENSEMBLE
    meta: dict = field(default_factory=dict)
    shapes: list[Tensor] | None = None
    shape_names: list[str] = field(default_factory=list)
    widening: float = 0.0
    outcomes: list[Tensor] | None = None
    outcome_width: float = math.inf
    novelty_widening: float = 0.0
    defensive: tuple[float, float, float] = (0.0, 0.0, 0.0)
    uncorrected: float = 0.0
    point: str = "corrected"
    disagreement: float = 0.0

    @property
    def name(self) -> str:
        return f"{self.model.name}_residual"

    @property
    def needs_learned(self) -> bool:
        """Whether a prediction needs its push model's own from the same push condition (its point or its hedge)."""
        return self.point == "learned" or self.disagreement > 0

    @property
    def actions(self) -> Tensor:
        return self.model.actions

    def action_index(self, action) -> int:
        return self.model.action_index(action)

    # what a prediction and a library read of a model: the push model's own (selection by H_r, the cloud's
    # features, conditioning's evidence), so residual models sit in a ModelLibrary as push models do
    @property
    def settings(self):
        return self.model.settings

    @property
    def position(self):
        return self.model.position

    @property
    def contact(self):
        return self.model.contact

    @property
    def motions(self):
        return self.model.motions

    @property
    def motion_kernels(self):
        return self.model.motion_kernels

    @property
    def physics_posterior(self):
        return self.model.physics_posterior

    @property
    def dtype(self) -> torch.dtype:
        return self.model.dtype

    @property
    def device(self) -> torch.device:
        return self.model.device

    def without_shape(self, shape: int) -> ResidualModel:
        """This pooled model without the kernels of training shape ``shape`` (its residuals and its push model's
        manipulator kernels; the contact and position models are kept: a prediction from a given robot start
        uses the position model only to name the body's frame). What holds a shape out to choose the widening.

        Raises:
            InvalidParameterError: a model of one object, a shape it does not have, or an action only that shape
                had kernels of."""
        if self.shapes is None or not 0 <= shape < len(self.shape_names):
            raise InvalidParameterError(f"shape {shape} is not one of this model's pooled training shapes "
                                        f"({self.shape_names})")
        return self._keeping([of != shape for of in self.shapes], f"only {self.shape_names[shape]} was pushed")

    def without_pushes(self, action: int, pushes: Tensor) -> ResidualModel:
        """This model without the kernels that training pushes ``pushes`` of action ``action`` gave (indices
        among the action's valid pushes, as its kernels' ``push`` holds them): their residuals and their push
        model's manipulator kernels. What holds a push out to choose the kernels' scale
        (:func:`pushtorch.evaluation.transfer.choose_residual_scale`).

        Raises:
            InvalidParameterError: a model read from its file (its kernels no longer know their pushes), or
                pushes that gave every kernel of the action."""
        push = self.model.motions[action].manipulator.push
        if push is None:
            raise InvalidParameterError("holding a push out needs a model trained in this session (its kernels "
                                        "know their pushes), not a loaded one")
        keep = [torch.ones(r.p.shape[0], dtype=torch.bool) for r in self.residuals]
        held = torch.as_tensor(pushes).reshape(-1).cpu()
        keep[action] = ~torch.isin(push.cpu(), held)
        out = self._keeping(keep, f"pushes {held.tolist()} gave every kernel")
        motion = out.model.motions[action]
        environment = motion.environment.push
        if environment is not None:
            kept = (~torch.isin(environment.cpu(), held)).nonzero().reshape(-1)
            if len(kept):  # an action with no other push keeps its environment kernels (only contacts' placing)
                motions = list(out.model.motions)
                motions[action] = dataclasses.replace(motion, environment=motion.environment.take(kept.to(
                    motion.environment.r.device)))
                out = dataclasses.replace(out, model=dataclasses.replace(out.model, motions=motions))
        return out

    def _keeping(self, keep: list[Tensor], why: str) -> ResidualModel:
        """This model with each action's kernels where ``keep (J_a,)`` holds (residuals, outcomes, shapes and the
        push model's manipulator kernels alike)."""
        motions, residuals = [], []
        for motion, residual, mask in zip(self.model.motions, self.residuals, keep, strict=True):
            index = mask.cpu().nonzero().reshape(-1)
            if not len(index):
                raise InvalidParameterError(f"{why} of action {motion.action.tolist()}: holding them out leaves "
                                            "no kernel")
            motions.append(dataclasses.replace(motion, manipulator=motion.manipulator.take(index.to(
                motion.manipulator.r.device))))
            residuals.append(residual.take(index))
        outcomes = None if self.outcomes is None else [o[m.to(o.device)] for o, m in zip(self.outcomes, keep,
                                                                                           strict=True)]
        shapes = None if self.shapes is None else [of[m.to(of.device)] for of, m in zip(self.shapes, keep,
                                                                                         strict=True)]
        return dataclasses.replace(self, model=dataclasses.replace(self.model, motions=motions), residuals=residuals,
                                   shapes=shapes, outcomes=outcomes)

    def condition_on(self, observations, seed: int | None = None, prior: tuple | None = None,
                     bandwidth=None) -> ResidualModel:
        """This model with its push model conditioned on observed pushes
        (:meth:`PushModel.condition_on <pushtorch.models.model.PushModel.condition_on>`): the ensemble's
        friction and mass are then drawn from the posterior, and each residual kernel weighs by it too."""
        return dataclasses.replace(self, model=self.model.condition_on(observations, seed, prior, bandwidth))

    def save(self, path) -> Path:
        """Write the model atomically to ``path``: the push model's sealed file, with the residuals' arrays and a
        ``residual`` header (the rollout engine, its version and settings, the ensemble and the kernels' stds).
        :func:`~pushtorch.models.model.load_model` reads the push model back from it;
        :func:`load_residual_model` the whole."""
        arrays = {}
        for a, r in enumerate(self.residuals):
            arrays[f"residual{a}.p"], arrays[f"residual{a}.q"] = r.p, r.q
            if self.shapes is not None:
                arrays[f"residual{a}.shape"] = self.shapes[a]
            if self.outcomes is not None:
                arrays[f"residual{a}.outcome"] = self.outcomes[a]
        header = {"residual": {"engine": self.sim.engine, "engine_version": self.engine_version,
                               "sim": dataclasses.asdict(self.sim), "ensemble": self.ensemble,
                               "p_std": self.bandwidth.p_std, "rot_std": self.bandwidth.rot_std,
                               "widening": self.widening, "shape_names": self.shape_names,
                               "outcome_width": None if math.isinf(self.outcome_width) else self.outcome_width,
                               "novelty_widening": self.novelty_widening,
                               "defensive": list(self.defensive), "uncorrected": self.uncorrected,
                               "point": self.point, "disagreement": self.disagreement, "meta": self.meta}}
        return write_model_file(path, *self.model.file_parts(arrays, header))


def _log_kernels(residuals: se3.Pose, p_std: float, rot_std: float) -> Tensor:
    """``(J, J)`` each normalised, uncut residual kernel's log density at every residual (float64)."""
    p = residuals.p.double()
    q = residuals.q.double()
    d2 = ((p.unsqueeze(1) - p.unsqueeze(0)) ** 2).sum(-1)
    dq = (1 - (q.unsqueeze(1) * q.unsqueeze(0)).sum(-1).abs()).clamp_min(0)
    sigma_q = rot_std**2 / 4
    log_norm = 1.5 * math.log(2 * math.pi * p_std**2) + float(log_rotation_normaliser(torch.tensor(1 / sigma_q)))
    return -d2 / (2 * p_std**2) - dq / sigma_q - log_norm


def choose_bandwidth(residuals: list[se3.Pose], push: list[Tensor], settings,
                     outcomes: list[Tensor] | None = None) -> tuple[KernelBandwidth, float, dict]:
    """The residual kernels' stds, and the width ``h`` that pairs them with a rollout by its outcome, of highest
    leave-one-push-out likelihood: each training push's residual scored under the other pushes' kernels, each
    weighed by how alike its training rollout's outcome is to the held-out push's (:func:`outcome_log_affinity`;
    equally at ``h = inf``, the only width without ``outcomes``), summed over actions (nats per push)."""
    widths = OUTCOME_LADDER if outcomes is not None else (math.inf,)
    best, scores = None, {}
    for p_std in RESIDUAL_LADDER[0]:
        for rot_std in RESIDUAL_LADDER[1]:
            kernels = [_log_kernels(r, p_std, rot_std) for r in residuals]
            for width in widths:
                total, count = 0.0, 0
                for a, (log_k, k) in enumerate(zip(kernels, push, strict=True)):
                    if len(k) < 2:
                        continue
                    own = k.unsqueeze(1) == k.unsqueeze(0)  # its own push held out
                    if outcomes is None:
                        affinity = torch.zeros_like(log_k)
                    else:
                        affinity = outcome_log_affinity(outcomes[a], outcomes[a], width)
                    affinity = affinity.masked_fill(own, -math.inf)
                    log_v = affinity - torch.logsumexp(affinity, 1, keepdim=True)
                    held = torch.logsumexp(log_k.masked_fill(own, -math.inf) + log_v, 1)
                    keep = torch.isfinite(held)
                    total += float(held[keep].sum())
                    count += int(keep.sum())
                if count:
                    scores[(p_std, rot_std, width)] = total / count
                    if best is None or scores[(p_std, rot_std, width)] > scores[best]:
                        best = (p_std, rot_std, width)
    if best is None:
        raise ModelError("too few training pushes to choose the residual kernels' width (two per action at least)")
    bandwidth = KernelBandwidth(best[0], best[1], cutoff_std=(math.inf, math.inf, math.inf),
                                alpha_t=settings.alpha_t)
    unpaired = scores.get((best[0], best[1], math.inf))
    return bandwidth, best[2], {"p_std": best[0], "rot_std": best[1],
                                "outcome_width": None if math.isinf(best[2]) else best[2],
                                "score": round(scores[best], 3),
                                "score_unpaired": None if unpaired is None else round(unpaired, 3)}


def _training_body(obj: ObjectModel, pose: se3.Pose, voxel_size: float) -> tuple[ObjectModel, se3.Pose]:
    """The body a single-shot cloud of ``obj`` at ``pose`` builds, as a prediction would build it."""
    cloud = capture_partial_cloud(obj, pose, voxel_size=voxel_size)
    return cloud_body(cloud.points, pose)


def train_residual_model(model: PushModel, obj: ObjectModel | list[ObjectModel], records,
                         sim: SimSettings | None = None, ensemble: int = DEFAULT_ENSEMBLE,
                         body_of: Callable[[ObjectModel, se3.Pose], tuple[ObjectModel, se3.Pose]] | None = None
                         ) -> ResidualModel:
    """The residual model of ``model``, trained on the same push ``records`` of ``obj`` (module docstring).

    Args:
        model: trained on ``records`` by this pushtorch (its kernels know their pushes): one object's model
            (:func:`~pushtorch.models.training.train_push_model`) or a pooled one
            (:func:`~pushtorch.models.pooled.train_pooled_model`, ``obj`` and ``records`` then its lists of shapes
            and their records, in its order).
        records: the :class:`~pushtorch.sim.records.PushRecords` the model was trained on.
        sim: the simulator the residual is taken against (default pybullet's settings).
        ensemble: rollouts per prediction.
        body_of: ``(object, pose) → (body, body pose)``, the body each push is rolled out on; default the
            body a single-shot cloud at the push's start builds (the true mesh: ``lambda o, p: (o, p)``).

    Raises:
        InvalidParameterError: an ensemble < 1, kernels that do not know their pushes (a loaded model), records
            without friction and mass, or records that are not the model's (other actions, other pushes).
    """
    sim = sim or SimSettings()
    if isinstance(ensemble, bool) or int(ensemble) != ensemble or ensemble < 1:
        raise InvalidParameterError(f"the ensemble needs at least one rollout, got {ensemble!r}")
    objects = list(obj) if isinstance(obj, list | tuple) else [obj]
    sets = list(records) if isinstance(records, list | tuple) else [records]
    if len(objects) != len(sets) or not objects:
        raise InvalidParameterError(f"{len(objects)} training objects but {len(sets)} sets of push records")
    body_of = body_of or (lambda o, pose: _training_body(o, pose, model.settings.voxel_size))
    valid = [r.take(r.valid) for r in sets]
    for o, v in zip(objects, valid, strict=True):
        if not bool(torch.isfinite(v.ground_friction).all() and torch.isfinite(v.mass).all()):
            raise InvalidParameterError(f"the residual model rolls each training push of {o.name} out at its own "
                                        "friction and mass, and these records have none (a push table without "
                                        "'mass' and 'ground_friction' columns)")
    chosen_pushes = []  # every action's pushes, each shape's in turn, checked against the kernels before any rollout
    for motion in model.motions:
        push = motion.manipulator.push
        if push is None:
            raise InvalidParameterError("a residual model needs a model trained in this session (its kernels know "
                                        "their pushes), not a loaded one")
        action = motion.action.detach().double().cpu()
        sets = [(s, o, v.take((v.action.double() - action).abs().amax(-1) <= 1e-6))
                for s, (o, v) in enumerate(zip(objects, valid, strict=True))]
        count, index = sum(len(sel) for *_, sel in sets), push.cpu()
        if not count or int(index.max()) >= count:
            raise InvalidParameterError(f"the records hold {count} pushes of action {action.tolist()}, the model's "
                                        f"kernels come from {int(index.max()) + 1}: train the residual on the "
                                        "model's own records")
        physics = torch.cat([torch.stack([sel.ground_friction.double(), sel.mass.double()], -1) for *_, sel in sets])
        if motion.manipulator.physics is not None and not torch.allclose(  # each kernel's push is the one it says
                physics[index], motion.manipulator.physics.detach().double().cpu(), rtol=1e-5, atol=1e-6):
            raise InvalidParameterError("the records' pushes are not the ones the model's kernels came from (their "
                                        "friction and mass differ): train the residual on the model's own records, "
                                        "in its order of shapes")
        chosen_pushes.append((action, index, sets))
    residuals, pushes, shapes, outcomes, rollouts = [], [], [], [], 0
    for action, index, sets in chosen_pushes:
        per_push, shape_of, did = [], [], []
        for s, o, sel in sets:
            for i in range(len(sel)):  # each push has its own body: one rollout each
                b0, b1 = sel.object_initial.take(i), sel.object_final.take(i)
                r0 = sel.robot_start.take(i)
                body, start = body_of(o, b0)
                final = rollout_ensemble(body, start, r0, action, sel.ground_friction[i:i + 1],
                                         sel.mass[i:i + 1], sim).object_final.take(0)
                world = se3.compose(se3.compose(b1, se3.inverse(b0)), se3.Pose.unchecked(start.p.double(),
                                                                                         start.q.double()))
                per_push.append(residual_of(r0, final, world))
                did.append(rollout_outcome(r0, start, final))
                rollouts += 1
            shape_of.append(torch.full((len(sel),), s, dtype=torch.int64))
        kernels = se3.Pose.stack(per_push).take(index)
        residuals.append(se3.Pose.unchecked(kernels.p.to(model.dtype), kernels.q.to(model.dtype)))
        pushes.append(index)
        shapes.append(torch.cat(shape_of)[index])
        outcomes.append(torch.stack(did)[index])
    bandwidth, width, chosen = choose_bandwidth(residuals, pushes, model.settings, outcomes)
    return ResidualModel(model, residuals, bandwidth, sim, engine_version(sim.engine), int(ensemble),
                         {"bandwidth": chosen, "training_rollouts": rollouts},
                         shapes=shapes if len(objects) > 1 else None, shape_names=[o.name for o in objects],
                         outcomes=outcomes, outcome_width=width)


def with_ensemble(model: ResidualModel, ensemble: int) -> ResidualModel:
    """``model`` with another ensemble size."""
    if isinstance(ensemble, bool) or int(ensemble) != ensemble or ensemble < 1:
        raise InvalidParameterError(f"the ensemble needs at least one rollout, got {ensemble!r}")
    return dataclasses.replace(model, ensemble=int(ensemble))
