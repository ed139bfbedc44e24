"""Prediction (paper, Fig. pipeline, prediction; §Motion Model): partial cloud + action → push condition →
the action's product of experts over the object's final pose, optimised by simulated annealing.

With a :class:`~pushtorch.models.library.ModelLibrary`, the model is chosen first by the lowest ``H_r``.

Two implementations of the same method (:class:`~pushtorch.kde.Evaluation`): :attr:`Evaluation.FAST`
(default) evaluates the densities only where the kernels' hard cut-offs let them reach, in fused (compiled
when possible) passes, anneals the robot's and the object's query densities in one batch and, in
:func:`predict_many`, many conditions at once; it anneals for ``ModelSettings.fast_anneal_fraction`` of the
steps and then moves every candidate to its local mode by mean shift (``polish_steps``,
:func:`pushtorch.anneal.polish_candidates`). :attr:`Evaluation.DENSE` is the reference implementation of the
paper (every query against every kernel — the motion kernels whose contact weight is zero included — one
density at a time, the full annealing schedule). Both optimise the same densities; their random streams
differ; ``tools/bench_predict.py`` checks that their accuracy agrees. The push conditions are built by
:mod:`pushtorch.models.push_condition`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult
from pushtorch.distribution import FinalPoseDistribution
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import Evaluation, KernelBandwidth
from pushtorch.models.clearance import check_start
from pushtorch.models.experts import (
    MotionDensity,
    MotionPrediction,
    StackedProducts,
    anneal_motion_densities,
    anneal_stacked,
    candidate_products,
    concat_products,
    draw_starts,
    stack_products,
    widen_stacked,
)
from pushtorch.models.frames import ContactFrames
from pushtorch.models.library import ModelLibrary
from pushtorch.models.model import PushModel
from pushtorch.models.motion import contact_distances, nearest_in_contact
from pushtorch.models.push_condition import (
    PushCondition,
    anneal_schedule,
    candidate_conditions,
    features_for,
    generate_push_condition,
    push_conditions,
)
from pushtorch.models.residual import ResidualModel
from pushtorch.models.settings import as_generator, check_action
from pushtorch.perception import PointCloud
from pushtorch.prediction.residual import (
    ResidualCandidates,
    ResidualPrediction,
    predict_residual,
    residual_candidates,
)
from pushtorch.streams import KeyedStream, content_keys

__all__ = [
    "PLANNER_NORMALISER_SAMPLES",
    "CandidatePredictions",
    "Prediction",
    "predict",
    "predict_candidates",
    "predict_many",
    "transfer_bandwidth",
    "transfer_distance",
]

log = logging.getLogger(__name__)

#: Importance samples per expert of each planner candidate's normaliser (:func:`predict_candidates`). A goal scored
#: under many candidates makes a normaliser for each, and its cost grows linearly with the samples. On the
#: paper-size cube model of ``tools/bench_plan.py`` (``tools/normaliser_spread.py``: four candidates, eight seeds
#: each), log Z's standard deviation between seeds is 0.012 nats at 64 (0.040 s a candidate), 0.0035 at 256
#: (0.13 s) and 0.003 at 1,024 (0.44 s): a planner ranks candidates whose log densities differ by nats.
PLANNER_NORMALISER_SAMPLES = 64


@dataclass
class Prediction:
    """A predicted push outcome and the density it came from."""

    model_name: str
    action: torch.Tensor  # (2,)
    condition: PushCondition
    final_pose: se3.Pose  # ()
    log_prob: torch.Tensor  # () the product of experts at final_pose, up to its constant (as annealed)
    #: the predicted density over final poses as a torch distribution (normalised; ``mode`` = final_pose)
    density: FinalPoseDistribution
    candidates: se3.Pose  # (C,) annealed candidates
    candidate_log_prob: torch.Tensor  # (C,)
    anneal: AnnealResult | None = None  # the motion annealing (with per-step history if recorded)
    #: the product of experts as the method builds it (kernels, experts, mean shift; unnormalised)
    motion_density: MotionDensity | None = field(default=None, repr=False)


@dataclass
class CandidatePredictions:
    """Many candidate pushes of one cloud (:func:`predict_candidates`).

    Attributes:
        predictions: per candidate, its :class:`Prediction` (made when asked for, views of the batch; without
            ``motion_density``), or None where the start is not a push.
        valid: ``(C,)`` bool, the candidates that are pushes (their start touches the cloud, outside it).
        reasons: per candidate, why it is not a push (None where it is).
        density: one batched :class:`~pushtorch.distribution.FinalPoseDistribution` over the valid candidates
            (``batch_shape (V,)``, in candidate order), or None when none is valid.
    """

    predictions: Sequence[Prediction | None]
    valid: torch.Tensor
    reasons: tuple[str | None, ...]
    density: FinalPoseDistribution | None

    def log_prob(self, goal: torch.Tensor) -> torch.Tensor:
        """``(C,)`` the log density (nats) each candidate gives the final pose ``goal`` ``(7,)`` (x, y, z, w, x,
        y, z), −inf for a candidate that is not a push; differentiable with respect to ``goal``."""
        count = len(self.predictions)
        out = torch.full((count,), -math.inf, dtype=goal.dtype, device=goal.device)
        if self.density is None:
            return out
        values = self.density.log_prob(goal.reshape(1, 7).expand(int(self.valid.sum()), 7))
        return out.index_put((self.valid.nonzero(as_tuple=True)[0].to(goal.device),), values.to(goal.dtype))


def _check_actions(actions, count: int) -> torch.Tensor:
    """``(count, 2)`` float64 actions from one ``(2,)`` (or ``(1, 2)``) action for every condition or
    ``(count, 2)``.

    Raises:
        InvalidParameterError: not numeric, misshaped, NaN/infinite, or not one per condition.
    """
    if type(actions).__module__ == "numpy":
        try:
            actions = torch.as_tensor(actions)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InvalidParameterError(f"actions must be numbers (ẋ m/s, θ̇ rad/s), got {actions!r}") from exc
    if isinstance(actions, torch.Tensor) and actions.dim() == 2 and actions.shape[-1] == 2:
        rows = actions
    elif not isinstance(actions, torch.Tensor) and isinstance(actions, list | tuple) and actions \
            and all(isinstance(a, list | tuple | torch.Tensor) for a in actions):
        rows = torch.stack([check_action(a) for a in actions])
    else:
        return check_action(actions).expand(count, 2)
    if len(rows) == 1:
        return check_action(rows[0]).expand(count, 2)
    if len(rows) != count:
        raise InvalidParameterError(f"got {len(rows)} actions for {count} clouds")
    return torch.stack([check_action(a) for a in rows]) if count else torch.zeros(0, 2, dtype=torch.float64)


def predict(
    model: PushModel | ResidualModel | ModelLibrary,
    cloud: PointCloud | SurfaceFeatures,
    action,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: Evaluation | str = Evaluation.FAST,
    robot_start: se3.Pose | None = None,
) -> Prediction | ResidualPrediction:
    """Predict where the object in ``cloud`` ends up after ``action`` (paper, Motion Model, Eq. poe).

    Args:
        model: a trained model, or a library to select from by ``H_r``. A residual model
            (:class:`~pushtorch.models.residual.ResidualModel`, or a library of them) gives a
            :class:`~pushtorch.prediction.residual.ResidualPrediction`
            (:func:`~pushtorch.prediction.residual.predict_residual`: the same push condition, its rollouts
            and their corrected density; ``record_history`` and ``method`` do not apply to it).
        cloud: the object's single-shot cloud (or its surface features), world frame.
        action: ``(2,)`` (ẋ m/s, θ̇ rad/s), one of the model's actions.
        generator: seeded generator (or an int seed): the same seed (and method) gives the same prediction.
        record_history: keep every annealing step (for Rerun).
        method: :attr:`Evaluation.FAST` or ``"fast"`` (default): densities evaluated only where the hard
            cut-offs let kernels reach, fused (compiled when a compiler is available,
            :func:`pushtorch.kde.fast_path_compiled`), query densities annealed together, cheaper exact proposal
            draws, a shorter annealing polished by mean shift (module docstring); :attr:`Evaluation.DENSE` or
            ``"dense"``: the reference implementation, the paper's full schedule. Both optimise the same
            densities; their random streams differ, so single predictions differ as two seeds do.
        robot_start: the robot's start pose (one pose, world), when the caller places the robot instead of
            the manipulator contact model; the bumper must touch the observed cloud there. Default None:
            the model chooses (the paper's push condition generation).

    Raises:
        InvalidParameterError: an unknown method, or an action that is not finite, misshaped or unknown
            to the model.
        InvalidPointCloudError: an empty, misshaped or non-finite cloud (a float64 cloud is cast).
        InvalidPoseError: a ``robot_start`` that is not one finite pose with a unit quaternion, or whose bumper
            or chassis sits more than :data:`GIVEN_START_OVERLAP` inside the observed object.
        ModelError: a ``robot_start`` at which the bumper touches no observed surface feature.

    The robot start (``prediction.condition.robot_start``) clears the observed cloud by
    :data:`START_CLEARANCE` (a given ``robot_start`` is used as it is): an overlapping annealed start is
    backed off along the approach
    (``condition.backoff``), and ``condition.valid`` is False if that took more than :data:`MAX_BACKOFF`
    (``condition.check_start()`` raises ModelError then).
    """
    return predict_many(model, [cloud], action, generator=generator, record_history=record_history,
                        method=method, robot_starts=None if robot_start is None else [robot_start])[0]


def _motion_density(model: PushModel, condition: PushCondition, a: int, method: Evaluation) -> MotionDensity:
    """The action's product of experts; the dense reference keeps every motion kernel of the budget (those the
    contact weight cuts off weigh zero), the fast path drops them before anything is evaluated. Over the
    budget (``manipulator_kernels``, ``environment_kernels``) the kernels nearest in contact are kept
    (:func:`~pushtorch.models.motion.nearest_in_contact`), and a pooled model widens its motion kernels by the
    manipulator contact's distance to the training ones (:func:`transfer_bandwidth`)."""
    settings = model.settings
    motion = model.motions[a]
    patch, start, bandwidth = condition.contact_patch, condition.robot_start, settings.contact_bandwidth
    return MotionDensity(
        type(motion)(
            motion.action,
            nearest_in_contact(condition.manipulator_frame, motion.manipulator, start, bandwidth, patch,
                               settings.manipulator_kernels),
            nearest_in_contact(condition.environment_frames, motion.environment, start, bandwidth, patch,
                               settings.environment_kernels),
            motion.mean_motion,
        ),
        condition.manipulator_frame,
        condition.environment_frames,
        condition.object_pose,
        condition.robot_start,
        condition.contact_patch,
        settings.contact_bandwidth,
        transfer_bandwidth(model, condition, a),
        drop_cut_kernels=method is Evaluation.FAST,
        pool_sharpness=settings.pool_sharpness,
        density_bandwidth=transfer_bandwidth(model, condition, a, density=True),
    )


def transfer_distance(model: PushModel, condition: PushCondition, a: int) -> torch.Tensor:
    """``()`` the squared distance, in contact-kernel stds, from the condition's manipulator contact to the
    nearest training push's of action ``a`` (:func:`~pushtorch.models.motion.contact_distances`): how far the
    new object's local contact is from everything the model was trained on."""
    motion = model.motions[a]
    return contact_distances(condition.manipulator_frame, motion.manipulator, condition.robot_start,
                             model.settings.contact_bandwidth, condition.contact_patch).amin()


def transfer_bandwidth(model: PushModel, condition: PushCondition, a: int, density: bool = False) -> KernelBandwidth:
    """The motion kernels' bandwidth of this prediction: the model's, times
    ``sqrt(transfer_scale² + transfer_widening · d²)`` with ``d²`` :func:`transfer_distance` (docs/method.md,
    "Transfer uncertainty"; 1 for a model that does not widen). ``density``: the bandwidth of the density the
    prediction returns (:attr:`~pushtorch.models.settings.ModelSettings.density_bandwidth`), not the annealing's."""
    settings = model.settings
    base = settings.density_bandwidth if density else settings.motion_bandwidth
    if settings.transfer_scale == 1.0 and settings.transfer_widening == 0.0:
        return base
    d2 = float(transfer_distance(model, condition, a)) if settings.transfer_widening > 0 else 0.0
    scale = math.sqrt(settings.transfer_scale**2 + settings.transfer_widening * d2)
    return replace(base, p_std=base.p_std * scale, rot_std=base.rot_std * scale)


def predict_many(
    model: PushModel | ResidualModel | ModelLibrary,
    clouds: list[PointCloud | SurfaceFeatures],
    actions,
    seed: int = 0,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: Evaluation | str = Evaluation.FAST,
    batch_size: int = 1,
    robot_starts: list[se3.Pose | None] | None = None,
) -> list[Prediction | ResidualPrediction]:
    """Predict several conditions (one cloud and action each).

    With ``generator`` None, batch ``k`` (conditions ``k·batch_size …``) draws from its own generator
    seeded ``seed + k·batch_size``, so ``batch_size=1`` gives each condition ``i`` exactly
    ``predict(..., generator=torch.Generator().manual_seed(seed + i))``. On the fast path with
    ``batch_size > 1`` the conditions of a batch are annealed together (one density call per step for
    all of them: the robot and pose query densities, then the products of experts), which amortises
    the per-step overhead; the memory of a batch grows linearly with its size (at the paper's sizes,
    measured: peak +56 MB for 8 conditions, +180 MB for 32), so bound it with ``batch_size``.

    Args:
        model, clouds: as :func:`predict`, one cloud per condition.
        actions: ``(2,)`` for all or ``(len(clouds), 2)``.
        seed: base seed when no generator is given; generator: one generator for every batch.
        record_history, method: as :func:`predict`.
        batch_size: conditions annealed together (fast method only; the dense method runs one by one). A
            residual model predicts each condition alone (its ensemble's rollouts are its batch), drawing from
            the batch's generator in condition order.
        robot_starts: None (the model places the robot) or one entry per cloud: a start pose as
            :func:`predict`'s ``robot_start``, or None for the model's own.

    Raises:
        InvalidParameterError: an unknown method, a batch size < 1, actions or starts that do not match.

    Every condition's robot start is cleared of its cloud as in :func:`predict`. An empty list of clouds
    gives an empty list of predictions.
    """
    method = Evaluation.of(method)
    if isinstance(batch_size, bool) or not isinstance(batch_size, int | float) or int(batch_size) != batch_size \
            or batch_size < 1:
        raise InvalidParameterError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InvalidParameterError(f"seed must be an integer, got {seed!r}")
    generator = None if generator is None else as_generator(generator)  # None: one seeded stream per batch
    if isinstance(clouds, PointCloud | SurfaceFeatures | torch.Tensor):
        raise InvalidParameterError("clouds must be a list of clouds (use predict for one cloud)")
    clouds = list(clouds)
    if not clouds:  # an empty batch predicts nothing, as map() over nothing
        return []
    actions = _check_actions(actions, len(clouds))
    if robot_starts is None:
        robot_starts = [None] * len(clouds)
    elif isinstance(robot_starts, se3.Pose) or len(robot_starts) != len(clouds):
        raise InvalidParameterError(
            f"robot_starts must be a list with one pose (or None) per cloud, {len(clouds)} in all")
    else:  # refused before any annealing is spent on the batch
        robot_starts = [None if start is None else check_start(start) for start in robot_starts]
    step = int(batch_size) if method is Evaluation.FAST else 1
    out: list[Prediction] = []
    for start in range(0, len(clouds), step):
        g = generator if generator is not None else torch.Generator().manual_seed(seed + start)
        out.extend(_predict_batch(model, clouds[start : start + step], actions[start : start + step], g,
                                  record_history, method, list(robot_starts[start : start + step])))
    return out


def _predict_batch(
    model: PushModel | ResidualModel | ModelLibrary,
    clouds: list[PointCloud | SurfaceFeatures],
    actions: torch.Tensor,
    generator: torch.Generator | None,
    record_history: bool,
    method: Evaluation,
    starts: list[se3.Pose | None],
) -> list[Prediction]:
    """One batch of :func:`predict_many`: a library selects per cloud, then each model's share runs
    together (:func:`_predict_fast`, or :func:`_predict_dense` one by one)."""
    first = model.models[0] if isinstance(model, ModelLibrary) else model
    made: dict[int, SurfaceFeatures] = {}  # a cloud given more than once (a planner's candidates) is featured once
    for c in clouds:
        if id(c) not in made:
            made[id(c)] = features_for(c, first.settings, first.position)
    features = [made[id(c)] for c in clouds]
    chosen = [model.select(f)[0] if isinstance(model, ModelLibrary) else model for f in features]
    out: list[Prediction | None] = [None] * len(clouds)
    distinct = [m for i, m in enumerate(chosen) if all(m is not c for c in chosen[:i])]  # first-use order
    share = _predict_fast if method is Evaluation.FAST else _predict_dense
    for m in distinct:
        rows = [i for i, c in enumerate(chosen) if c is m]
        if isinstance(m, ResidualModel):  # its rollouts are batched per prediction, from the cloud as given
            # its push model's prediction (a learned point, a disagreement hedge), annealed together, same condition
            owns = share(m.model, [features[i] for i in rows], [m.action_index(actions[i]) for i in rows], generator,
                         False, [starts[i] for i in rows]) if m.needs_learned else [None] * len(rows)
            same = m.settings.feature_radius == first.settings.feature_radius  # the features made above serve it
            for i, own in zip(rows, owns, strict=True):
                given = features[i] if same else None
                out[i] = predict_residual(m, clouds[i], actions[i], generator, robot_start=starts[i],
                                          features=given) if own is None \
                    else predict_residual(m, clouds[i], actions[i], generator, condition=own.condition,
                                          learned=(own.condition.object_pose, own.final_pose), features=given)
            continue
        a_idx = [m.action_index(actions[i]) for i in rows]
        predictions = share(m, [features[i] for i in rows], a_idx, generator, record_history, [starts[i] for i in rows])
        for i, prediction in zip(rows, predictions, strict=True):
            out[i] = prediction
    return out  # type: ignore[return-value]


def _predict_fast(model: PushModel, features: list[SurfaceFeatures], a_idx: list[int],
                  generator: torch.Generator | None, record_history: bool,
                  starts: list[se3.Pose | None]) -> list[Prediction]:
    """One model's share of a batch on the fast path: push conditions, then products of experts, each
    annealed together."""
    settings = model.settings
    conditions = push_conditions(model, features, a_idx, generator, record_history, starts)
    densities = [_motion_density(model, c, a, Evaluation.FAST) for c, a in zip(conditions, a_idx, strict=True)]
    results = anneal_motion_densities(densities, settings.anneal_candidates,
                                      anneal_schedule(settings, False, Evaluation.FAST), generator, record_history,
                                      settings.polish_steps)
    return [_prediction(model, a, c, d, r, Evaluation.FAST)
            for a, c, d, r in zip(a_idx, conditions, densities, results, strict=True)]


def _predict_dense(model: PushModel, features: list[SurfaceFeatures], a_idx: list[int],
                   generator: torch.Generator | None, record_history: bool,
                   starts: list[se3.Pose | None]) -> list[Prediction]:
    """One model's share of a batch by the dense reference, one condition after the other."""
    settings = model.settings
    schedule = anneal_schedule(settings, False, Evaluation.DENSE)
    out = []
    for f, a, start in zip(features, a_idx, starts, strict=True):
        condition = generate_push_condition(model, f, a, generator, record_history, Evaluation.DENSE, start)
        density = _motion_density(model, condition, a, Evaluation.DENSE)
        result = density.predict(settings.anneal_candidates, schedule, generator, record_history)
        out.append(_prediction(model, a, condition, density, result, Evaluation.DENSE))
    return out


def _prediction(model: PushModel, a: int, condition: PushCondition, density: MotionDensity,
                result: MotionPrediction, method: Evaluation) -> Prediction:
    """The :class:`Prediction` of one annealed product of experts, with its normalised distribution."""
    distribution = FinalPoseDistribution.from_motion_densities(density, result.final_pose,
                                                               [result.anneal.candidates], method)
    return Prediction(model.name, model.motions[a].action, condition, result.final_pose, result.log_prob,
                      distribution, result.anneal.candidates, result.anneal.log_prob, result.anneal, density)


def _chunk_products(model: PushModel, conditions: list[PushCondition], a_idx: list[int],
                    stream: KeyedStream) -> tuple[StackedProducts, se3.Pose]:
    """A chunk of a planner's candidates: their products of experts, stacked in the chunk's order, and their
    annealing start candidates ``(B, n)``, drawn from ``stream.fork()`` (each candidate's draws its own).

    Each action's candidates are built at once (:func:`~pushtorch.models.experts.candidate_products`, start
    candidates by :func:`~pushtorch.models.experts.draw_starts`, trial rounds by
    :func:`~pushtorch.models.experts.widen_stacked`) when the action's kernels fit the prediction's budget; else
    each candidate's :class:`MotionDensity` is built alone (the budget's nearest kernels differ per candidate)."""
    settings = model.settings
    n = settings.anneal_candidates
    proposals = stream.fork()
    parts, starts, positions = [], [], []
    for a in sorted(set(a_idx)):
        mine = [j for j, b in enumerate(a_idx) if b == a]
        group = [conditions[j] for j in mine]
        motion = model.motions[a]
        together = (len(motion.manipulator) <= settings.manipulator_kernels
                    and len(motion.environment) <= settings.environment_kernels
                    and all(c.environment_frames is group[0].environment_frames
                            and c.object_pose is group[0].object_pose for c in group))
        if together:
            stacked = candidate_products(
                motion, ContactFrames.stack([c.manipulator_frame for c in group]), group[0].environment_frames,
                group[0].object_pose, se3.Pose.stack([c.robot_start for c in group]),
                torch.stack([torch.as_tensor(c.contact_patch) for c in group]), settings.contact_bandwidth,
                transfer_bandwidth(model, group[0], a), transfer_bandwidth(model, group[0], a, density=True),
                settings.pool_sharpness)
            init = draw_starts(stacked, n, proposals.take(mine))
            stacked = widen_stacked(stacked, init)
        else:
            densities = [_motion_density(model, c, a, Evaluation.FAST) for c in group]
            init = se3.Pose.stack([d.widen_until_supported(d.proposal(n, proposals.take(j)), method=Evaluation.FAST)
                                   for d, j in zip(densities, mine, strict=True)])
            stacked = stack_products(densities)
        parts.append(stacked)
        starts.append(init)
        positions.extend(mine)
    back = torch.argsort(torch.tensor(positions))
    joined = concat_products(parts).take(back)
    init = se3.Pose.cat(starts)
    return joined, se3.Pose.unchecked(init.p[back], init.q[back])


class _CandidateList(Sequence):
    """A planner's predictions as a sequence of :class:`Prediction` (None for a candidate that is not a push), each
    made when asked for from the batch's tensors."""

    def __init__(self, model: PushModel, conditions: list[PushCondition | None], a_idx: list[int],
                 result: AnnealResult, density: FinalPoseDistribution) -> None:
        self._model, self._conditions, self._a_idx, self._result, self._density = (model, conditions, a_idx, result,
                                                                                   density)
        self._rows = {i: row for row, i in enumerate(i for i, c in enumerate(conditions) if c is not None)}

    def __len__(self) -> int:
        return len(self._conditions)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        i = range(len(self))[index]
        if self._conditions[i] is None:
            return None
        row = self._rows[i]
        part = self._result.take(row)
        return Prediction(self._model.name, self._model.motions[self._a_idx[i]].action, self._conditions[i],
                          part.best, part.best_log_prob, self._density[row], part.candidates, part.log_prob, part)


def _cat_poses(values: list) -> se3.Pose | torch.Tensor:
    """Chunks' poses or tensors joined along their leading (candidate) dim."""
    if isinstance(values[0], se3.Pose):
        return se3.Pose.unchecked(torch.cat([v.p for v in values]), torch.cat([v.q for v in values]))
    return torch.cat(values)


def predict_candidates(model: PushModel | ResidualModel | ModelLibrary, cloud: PointCloud | SurfaceFeatures,
                       robot_starts, actions, seed: int = 0, generator: torch.Generator | None = None,
                       chunk_size: int = 64, kernels: str = "full", normaliser_samples: int = PLANNER_NORMALISER_SAMPLES
                       ) -> CandidatePredictions | ResidualCandidates:
    """Many candidate pushes of one observed object, as a planner asks for them: each candidate is a robot start
    and an action, and the result scores any goal pose for all of them in one call
    (:meth:`CandidatePredictions.log_prob`).

    What depends on the cloud alone is computed once: its surface features, the library's choice of model, the
    object's pose estimate and each action's environment contacts
    (:func:`~pushtorch.models.push_condition.candidate_conditions`). Each candidate's product of experts is
    annealed in chunks of ``chunk_size`` candidates together (memory grows with the chunk). A start that touches
    nothing the camera saw, or overlaps the object, is flagged (``valid``, ``reasons``) rather than failing the call.
    A residual model (:mod:`pushtorch.prediction.residual`) gives :class:`ResidualCandidates`: the same push
    conditions made once, each candidate's ensemble rolled out with draws keyed by the candidate
    (:func:`~pushtorch.prediction.residual.residual_candidates`; a learned point's push-model predictions annealed
    here first), each density scored on its own.

    Args:
        model: a model (conditioned, pooled or residual) or a library (its model chosen once, by the cloud's
            ``H_r``).
        cloud: the observed cloud or its :class:`~pushtorch.features.SurfaceFeatures`.
        robot_starts: ``(C,)`` start poses (a batched :class:`~pushtorch.se3.Pose`) or a list of ``C`` poses.
        actions: ``(2,)`` for every candidate, or ``(C, 2)``; each one of ``model.actions``.
        seed: seeds the call: the per-cloud draws (a ``torch.Generator``) and each candidate's counter-based
            stream (:class:`~pushtorch.streams.KeyedStream`), keyed by the candidate's start and action, so that no
            chunk size, order or other candidate changes its prediction (beyond float rounding, 1e-4 m and rad).
        generator: a ``torch.Generator`` or seed to draw ``seed`` from instead.
        kernels: the density's kernels, ``"full"`` (finite everywhere: a planner's gradients) or ``"cut"``.
        normaliser_samples: the importance samples per expert of each candidate's normaliser, made on the first
            ``log_prob`` for every candidate at once, each from draws keyed by the candidate
            (:func:`~pushtorch.kde.normaliser.log_normalisers`; :data:`PLANNER_NORMALISER_SAMPLES`; a single
            prediction's density takes :data:`~pushtorch.distribution.NORMALISER_SAMPLES`).

    Raises:
        InvalidParameterError: no candidate, actions that do not match, an action the model lacks, a chunk size
            < 1, or an unknown ``kernels``.
        InvalidPoseError: a start that is not a finite pose.
        ModelError: a model that widens each prediction by its transfer distance (a calibrated pooled model,
            ``transfer_widening > 0``): its candidates' densities differ in bandwidth.
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise InvalidParameterError(f"chunk_size must be an integer >= 1, got {chunk_size!r}")
    if kernels not in ("full", "cut"):
        raise InvalidParameterError(f"kernels must be 'full' or 'cut', got {kernels!r}")
    if isinstance(normaliser_samples, bool) or not isinstance(normaliser_samples, int) or normaliser_samples < 1:
        raise InvalidParameterError(f"normaliser_samples must be an integer >= 1, got {normaliser_samples!r}")
    every = robot_starts.reshape(-1) if isinstance(robot_starts, se3.Pose) else None
    starts = [every.take(i) for i in range(every.batch_shape.numel())] if every is not None else list(robot_starts)
    if not starts:
        raise InvalidParameterError("predict_candidates needs at least one candidate start")
    actions = _check_actions(actions, len(starts))
    if generator is not None:  # the keyed streams' seed, drawn from it
        seed = int(torch.randint(0, 2**62, (1,), generator=as_generator(generator)))
    generator = torch.Generator().manual_seed(int(seed))  # the per-cloud draws, made once
    first = model.models[0] if isinstance(model, ModelLibrary) else model
    features = features_for(cloud, first.settings, first.position)
    chosen = model.select(features)[0] if isinstance(model, ModelLibrary) else model
    every = se3.Pose.stack(starts) if every is None else every
    identity = torch.cat([every.p.reshape(-1, 3), every.q.reshape(-1, 4), actions.to(every.p)], -1).detach().float()
    keys = content_keys(identity.cpu())  # each candidate's draws keyed by what it is (its start and action)
    a_idx = [chosen.action_index(a) for a in actions]
    if isinstance(chosen, ResidualModel):  # its push conditions made once; each candidate's own ensemble
        learned = None
        if chosen.needs_learned:  # the push model's candidate predictions: their conditions and points
            pushed = predict_candidates(chosen.model, features, starts, actions, seed, chunk_size=chunk_size)
            made = list(pushed.predictions)  # each built once
            conditions, reasons = [None if p is None else p.condition for p in made], pushed.reasons
            learned = [None if p is None else (p.condition.object_pose, p.final_pose) for p in made]
        else:
            conditions, reasons = candidate_conditions(chosen.model, features, starts, a_idx, generator)
        return residual_candidates(chosen, cloud, features, conditions, reasons, actions, keys, seed, learned)
    if chosen.settings.transfer_widening > 0:
        raise ModelError(
            f"model {chosen.name!r} widens each prediction by its own transfer distance (transfer_widening="
            f"{chosen.settings.transfer_widening:g}), so its candidates' densities do not share one bandwidth and "
            "cannot be one batched density; predict its candidates with predict(..., robot_start=...) one by one")
    conditions, reasons = candidate_conditions(chosen, features, starts, a_idx, generator)
    settings = chosen.settings
    schedule = anneal_schedule(settings, False, Evaluation.FAST)
    rows = [i for i, c in enumerate(conditions) if c is not None]
    valid = torch.tensor([c is not None for c in conditions], dtype=torch.bool)
    if not rows:
        return CandidatePredictions([None] * len(starts), valid, tuple(reasons), None)
    # each candidate's draws keyed by what it is: no order, chunk or company changes them
    stream = KeyedStream(int(seed), keys.to(chosen.device))
    parts, results = [], []
    for begin in range(0, len(rows), chunk_size):
        chunk = rows[begin:begin + chunk_size]
        draws = stream.take(chunk)  # the start candidates' phase, then the steps'
        stacked, init = _chunk_products(chosen, [conditions[i] for i in chunk], [a_idx[i] for i in chunk], draws)
        results.append(anneal_stacked(stacked, init, schedule, draws, False, settings.polish_steps))
        parts.append(stacked)
    result = AnnealResult(*(_cat_poses([getattr(r, f) for r in results]) for f in ("best", "best_log_prob",
                                                                                     "candidates", "log_prob")))
    base = FinalPoseDistribution.from_stacked(concat_products(parts), result.best, result.candidates,
                                              normaliser_samples=normaliser_samples,
                                              normaliser_keys=stream.keys[torch.tensor(rows, device=stream.device)])
    predictions = _CandidateList(chosen, conditions, a_idx, result, base)
    return CandidatePredictions(predictions, valid, tuple(reasons), base.with_kernels(kernels))
