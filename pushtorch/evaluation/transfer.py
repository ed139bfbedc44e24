"""How much a pooled model's density widens on a contact unlike its training ones, chosen by held-out
likelihood across training shapes (paper, §Motion Model's kernel densities; beyond the paper: many shapes).

A model pooled over many shapes (:mod:`pushtorch.models.pooled`) predicts a new object's motion from the
training pushes whose contact resembles its own. When no training contact is close, the kernels that still
weigh in move as *their* objects moved, and a density as narrow as the training spread is confidently wrong.
The prediction therefore scales its motion kernels by ``sqrt(s0² + κ·d²)``, ``d`` the manipulator contact's
distance to the nearest training contact in contact-kernel stds
(:func:`pushtorch.prediction.forward.transfer_bandwidth`).

``s0`` (which may also narrow a pool whose within-pool bandwidths are wider than transfer needs) and ``κ`` are
chosen here, never on a test object: each training shape in turn is held out, the other
shapes are pooled, and a sample of the held-out shape's own training pushes is predicted from its single-shot
cloud at the push's robot start; the pair with the lowest mean negative log-likelihood of those pushes' true
outcomes (displacement sense, :func:`pushtorch.evaluation.likelihood.nll`) is kept. The same predictions serve
every pair: only the motion bandwidth of the scored density changes.

A pooled residual model (:mod:`pushtorch.models.residual`) widens its residual kernels the same way, by
``sqrt(1 + κ·d²)`` (its base widths are chosen on its own pushes, leave one push out), and
:func:`choose_residual_widening` chooses its ``κ`` the same way: each shape held out in turn
(:meth:`~pushtorch.models.residual.ResidualModel.without_shape`), its pushes predicted and rolled out once, every
``κ`` scored on the same rollouts.

A residual model's density also has a defensive part (:class:`~pushtorch.distribution.DefensiveMixture`): a share
of the same kernels, centimetres wider, growing with the prediction's outcome novelty, chosen with ``κ``
(:func:`choose_residual_widening`) or with the novelty widening ``ν`` (:func:`choose_novelty_widening`) on the
same held-out pushes of shapes the model did not see and the same rollouts, every pair scored. So is its
uncorrected share (:data:`~pushtorch.models.residual.UNCORRECTED_RATES`), the rollouts themselves keeping a share
that grows with novelty: every combination is scored from the log densities of the corrected kernels and of the
rollouts at each distinct width, at the truth's symmetric copies, mixed at each combination's weights
(:func:`residual_nll_grid`). Across training objects, the combinations that held-out likelihood cannot tell apart
are told apart by calibration, then sharpness, for each model on its pushes (:func:`choose_novelty_widening`).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import replace

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.evaluation.likelihood import (
    calibrated_choice,
    covered,
    hdr_thresholds,
    nll,
    product_density,
    truth_copies,
)
from pushtorch.evaluation.metrics import displaced, hacc
from pushtorch.models.model import PushModel
from pushtorch.models.pooled import ShapeParts, pool_parts
from pushtorch.models.residual import (
    DEFENSIVE_PARTS,
    DISAGREEMENT_WEIGHTS,
    NOVELTY_FORM,
    NOVELTY_WIDENINGS,
    UNCORRECTED_RATES,
    defensive_share,
    uncorrected_share,
)
from pushtorch.objects import ObjectModel

__all__ = ["HEDGE_LEVEL", "RESIDUAL_SCALES", "RESIDUAL_SCALE_PUSHES", "RESIDUAL_WIDENINGS", "SCALES", "WIDENINGS",
           "choose_novelty_widening", "choose_residual_scale", "choose_residual_widening", "choose_widening",
           "own_held_out_pushes", "residual_nll_grid"]

log = logging.getLogger(__name__)

#: The grids searched: the base scale ``s0`` and the widening per squared contact distance ``κ``.
SCALES = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
WIDENINGS = (0.0, 0.1, 0.3, 1.0, 3.0)
#: The residual model's grid of ``κ``: corrections learnt on other shapes may be far off (measured on the engine
#: gap's cube and cylinder, each one's residuals scored on the other's pushes: best at 10 and 30)
RESIDUAL_WIDENINGS = (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
#: The factors tried on a residual model's kernel stds after training (:func:`choose_residual_scale`), and the
#: training pushes per action it holds out to choose one
RESIDUAL_SCALES = (0.125, 0.18, 0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 3.0)
RESIDUAL_SCALE_PUSHES = 8
#: The region whose held-out coverage breaks a tie in the choice of a residual model's hedges
#: (:func:`choose_novelty_widening`): the 90 % the reports' coverage names
HEDGE_LEVEL = 0.9
#: Importance samples per expert of each scored density's normaliser in the search (the scores' default is 64): a
#: quarter of the cost; the search compares means over many pushes, not single scores
SEARCH_SAMPLES = 16


def choose_widening(model: PushModel, objects: list[ObjectModel], records: list, parts: list[ShapeParts],
                    pushes_per_shape: int = 6, generator: torch.Generator | None = None,
                    scales=SCALES, widenings=WIDENINGS) -> PushModel:
    """The pooled ``model`` with ``transfer_scale`` and ``transfer_widening`` chosen by leave-one-shape-out
    likelihood (module docstring); the search is kept in ``meta["widening"]``.

    Args:
        model: the pooled model (its bandwidths already chosen); objects, records, parts: its training
            shapes, their push records and fitted parts (:func:`pushtorch.models.pooled.fit_shape_parts`).
        pushes_per_shape: held-out pushes predicted per shape (drawn among its valid pushes).

    Raises:
        InvalidParameterError: fewer than two shapes, or no held-out push could be predicted.
    """
    from pushtorch.features import compute_surface_features
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.prediction import predict, transfer_distance

    if len(parts) < 2:
        raise InvalidParameterError("choosing the widening holds one shape out: it needs at least two shapes")
    if isinstance(pushes_per_shape, bool) or int(pushes_per_shape) != pushes_per_shape or pushes_per_shape < 1:
        raise InvalidParameterError(f"widening_pushes must be a whole number >= 1, got {pushes_per_shape!r}")
    generator = generator or torch.Generator().manual_seed(0)
    settings = replace(model.settings, transfer_scale=1.0, transfer_widening=0.0)
    grid = list(itertools.product([float(s) for s in scales], [float(k) for k in widenings]))
    unchanged = grid.index((1.0, 0.0)) if (1.0, 0.0) in grid else None
    scores: list[torch.Tensor] = []
    skipped = 0
    for s, (obj, shape_records) in enumerate(zip(objects, records, strict=True)):
        rest = parts[:s] + parts[s + 1:]
        contact, position, motions = pool_parts(rest, settings, generator)
        held_out = PushModel(f"without_{obj.name}", "shapes", settings, contact, position, motions)
        valid = shape_records.take(shape_records.valid)
        pick = torch.randperm(len(valid), generator=generator)[:pushes_per_shape]
        for i in pick.tolist():
            push = valid.take(torch.tensor([i]))
            start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
            robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
            cloud = capture_partial_cloud(obj, start, voxel_size=settings.voxel_size)
            features = compute_surface_features(cloud, radius=settings.feature_radius)
            try:
                prediction = predict(held_out, features, push.action[0].float(), generator, robot_start=robot)
            except (ModelError, InvalidPoseError):  # the bumper meets no observed feature there
                skipped += 1
                continue
            condition, density = prediction.condition, prediction.motion_density
            a = held_out.action_index(push.action[0].float())
            d2 = float(transfer_distance(held_out, condition, a))
            means, log_weights = density.shared_kernels()
            base = density.experts.bandwidth
            rounds = density.experts.trial_rounds[0]
            truth = se3.Pose.unchecked(push.object_final.p.float(), push.object_final.q.float())
            row = []
            for s0, kappa in grid:
                scale = math.sqrt(s0**2 + kappa * d2)
                scored = product_density(means, log_weights, base.p_std * scale, base.rot_std * scale, rounds,
                                         base.alpha_t, generator, prediction.candidates, SEARCH_SAMPLES,
                                         exponent=density.expert_exponent)
                row.append(float(nll(scored, truth, start, condition.object_pose, obj.symmetry)[0]))
            scores.append(torch.tensor(row, dtype=torch.float64))
    if not scores:
        raise InvalidParameterError("no held-out push of any training shape could be predicted to choose the "
                                    "widening")
    table = torch.stack(scores)  # (pushes, grid)
    mean = table.mean(0)
    best = int(mean.argmin())
    s0, kappa = grid[best]
    log.info("widening: s0=%.2f kappa=%.3f (held-out nll %.2f against %s as trained, %d pushes)", s0, kappa,
             float(mean[best]), "—" if unchanged is None else f"{float(mean[unchanged]):.2f}", table.shape[0])
    meta = dict(model.meta)
    meta["widening"] = {
        "start": {"transfer_scale": model.settings.transfer_scale,
                  "transfer_widening": model.settings.transfer_widening},
        "chosen": {"transfer_scale": s0, "transfer_widening": kappa},
        "grid": [list(g) for g in grid], "nll": mean.tolist(), "pushes": int(table.shape[0]), "skipped": skipped,
    }
    return replace(model, settings=replace(model.settings, transfer_scale=s0, transfer_widening=kappa), meta=meta)


def _held_out_pushes(obj: ObjectModel, records, count: int, voxel_size: float, generator: torch.Generator):
    """Up to ``count`` of ``obj``'s valid pushes in ``records``, drawn at random: each ``(cloud, action, robot
    start, start, truth)``, the single-shot cloud at the push's start."""
    valid = records.take(records.valid)
    for i in torch.randperm(len(valid), generator=generator)[:count].tolist():
        yield _push_case(obj, valid.take(torch.tensor([i])), voxel_size)


def _push_case(obj: ObjectModel, push, voxel_size: float):
    """One push's ``(cloud, action, robot start, start, truth)`` (``push``: records of one push), the single-shot
    cloud at its start."""
    from pushtorch.perception import capture_partial_cloud

    start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
    robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
    truth = se3.Pose.unchecked(push.object_final.p.float(), push.object_final.q.float())
    return capture_partial_cloud(obj, start, voxel_size=voxel_size), push.action[0].float(), robot, start, truth


def choose_residual_scale(residual, obj: ObjectModel, records, pushes_per_action: int = RESIDUAL_SCALE_PUSHES,
                          generator: torch.Generator | None = None, scales=RESIDUAL_SCALES):
    """The residual model of one object with its kernels' stds scaled by the factor of highest held-out
    *predictive* likelihood; the search is kept in ``meta["scale"]``.

    The kernels' stds are chosen in training by leave-one-push-out likelihood of each residual applied to its own
    push's rollout, at that push's own friction and mass. A prediction does not know them: it mixes an ensemble of
    rollouts at friction and mass drawn from the training pushes' with every residual kernel, and that mixture can
    be wider or narrower than the truths' spread. Here ``pushes_per_action`` training pushes of each action are
    each held out in turn (:meth:`~pushtorch.models.residual.ResidualModel.without_pushes`: their residuals and
    their manipulator kernels, so neither their correction nor their physics is drawn), predicted as a test push
    is, from the single-shot cloud at the push's start and its robot start, and the true outcome scored under the
    density with its stds times each of ``scales`` (one prediction per push, the same rollouts). The factor of
    lowest mean nll is kept. The same held-out pushes choose the model's point prediction
    (:data:`~pushtorch.models.residual.POINTS`): the corrected kernels' mode at that factor, their local mode at the
    motion kernels' width, or the held-out push model's own prediction from the same robot start, whichever has the
    lowest mean H_acc (kept in ``meta["scale"]["point"]``).

    Raises:
        InvalidParameterError: a pooled model, a model read from its file, records that are not its own, or no
            held-out push that could be predicted.
    """
    if residual.shapes is not None:
        raise InvalidParameterError("choosing the residual kernels' scale holds out pushes of one object's model; "
                                    "a pooled model holds out whole shapes (choose_residual_widening)")
    if isinstance(pushes_per_action, bool) or int(pushes_per_action) != pushes_per_action or pushes_per_action < 1:
        raise InvalidParameterError(f"the pushes held out per action must be a whole number >= 1, got "
                                    f"{pushes_per_action!r}")
    generator = generator or torch.Generator().manual_seed(0)
    grid = [float(f) for f in scales]
    unwidened = replace(residual, novelty_widening=0.0, defensive=(0.0, 0.0, 0.0), uncorrected=0.0,
                        point="corrected")  # as trained
    scores, cases, skipped = [], [], 0
    for _, held_out, case in own_held_out_pushes(unwidened, obj, records, pushes_per_action, generator,
                                                 "choosing the residual kernels' scale"):
        scored = None if held_out is None else _predicted_scores(
            held_out, obj, case, generator,
            lambda p, truth, start: residual_nll_grid(p, truth, start, obj, grid, [(0.0, 0.0, 0.0)], [0.0]))
        if scored is None:
            skipped += 1
            continue
        scores.append(scored[1])
        cases.append((scored[0], case[4], case[3], _learned_hacc(held_out, obj, case, generator), obj))
    if not scores:
        raise InvalidParameterError(f"no held-out push of {obj.name} could be predicted to choose the residual "
                                    "kernels' scale")
    mean = torch.stack(scores).mean(0)
    best = int(mean.argmin())
    point = _point_choice(cases, lambda p: grid[best], residual.settings.motion_bandwidth, obj.name)
    log.info("residual kernels' scale %g for %s (held-out nll %.2f against %s at 1, %d pushes)", grid[best],
             obj.name, float(mean[best]), f"{float(mean[grid.index(1.0)]):.2f}" if 1.0 in grid else "—", len(scores))
    bandwidth = replace(residual.bandwidth, p_std=residual.bandwidth.p_std * grid[best],
                        rot_std=residual.bandwidth.rot_std * grid[best])
    chosen = {"chosen": grid[best], "grid": grid, "nll": mean.tolist(), "pushes": len(scores), "skipped": skipped,
              "pushes_per_action": int(pushes_per_action), "point": point}
    return replace(residual, bandwidth=bandwidth, point=point["chosen"], meta={**residual.meta, "scale": chosen})


def own_held_out_pushes(residual, obj: ObjectModel, records, per_action: int, generator: torch.Generator,
                        what: str = "holding a push out"):
    """Up to ``per_action`` of each action's training pushes of ``residual`` (a model of one object, trained in
    this session on ``records``), drawn at random by ``generator``: each ``(push, held_out, case)``, the push's
    index among its action's valid pushes, the model without that push's kernels
    (:meth:`~pushtorch.models.residual.ResidualModel.without_pushes`; None where the push gave every kernel of its
    action) and the push as ``(cloud, action, robot start, start, truth)``, its single-shot cloud at its start.
    What the choices of a model's scale and hedges predict as test pushes; ``what`` names the caller in the errors.

    Raises:
        InvalidParameterError: a model read from its file (its kernels no longer know their pushes), or records
            that are not its own."""
    valid = records.take(records.valid)
    for a, motion in enumerate(residual.model.motions):
        push = motion.manipulator.push
        if push is None:
            raise InvalidParameterError(f"{what} holds the model's own pushes out: it needs a model trained in this "
                                        "session (its kernels know their pushes), not a loaded one")
        action = motion.action.detach().double().cpu()
        pushes = valid.take((valid.action.double() - action).abs().amax(-1) <= 1e-6)
        if int(push.max()) >= len(pushes):
            raise InvalidParameterError(f"the records hold {len(pushes)} pushes of action {action.tolist()}, the "
                                        f"model's kernels come from {int(push.max()) + 1}: give the model's own")
        kept = push.cpu().unique()
        for p in kept[torch.randperm(len(kept), generator=generator)[:int(per_action)]].tolist():
            try:
                held_out = residual.without_pushes(a, torch.tensor([p]))
            except InvalidParameterError:  # its push gave every kernel of the action
                held_out = None
            yield p, held_out, _push_case(obj, pushes.take(torch.tensor([p])), residual.settings.voxel_size)


def _learned_hacc(held_out, obj: ObjectModel, case, generator: torch.Generator) -> float:
    """H_acc of the held-out push model's own prediction of push ``case`` (:func:`_push_case`) from its robot
    start (nan where it cannot be predicted there)."""
    from pushtorch.prediction import predict

    cloud, action, robot, start, truth = case
    try:
        own = predict(held_out.model, cloud, action, generator, robot_start=robot)
    except (ModelError, InvalidPoseError):
        return math.nan
    return _hacc_of(own.condition.object_pose, own.final_pose, start, truth, obj)


def _hacc_of(estimate: se3.Pose, final: se3.Pose, start: se3.Pose, truth: se3.Pose, obj: ObjectModel) -> float:
    """H_acc of the displacement ``estimate → final`` applied to the true ``start``, against ``truth``."""
    moved = displaced(estimate.to(torch.float64), final.to(torch.float64), start.to(torch.float64))
    return float(hacc(moved, truth.to(torch.float64), obj.dimensions, obj.symmetry).reshape(-1)[0])


def _point_choice(cases: list, factor, motion_bandwidth, of: str) -> dict:
    """The point prediction (:data:`~pushtorch.models.residual.POINTS`) of lowest mean H_acc over the held-out
    ``cases`` ``(prediction, truth, start, H_acc of the push model's own, object)``: the corrected kernels' mode
    with their stds times ``factor(prediction)`` (the chosen scale or widening), their local mode at the push
    model's ``motion_bandwidth``, the push model's own; pushes the push model could not predict are left out of
    every mean. ``se``: the paired SE of each point's difference from the corrected mode's; ``of`` names the
    pushes in the log."""
    from pushtorch.models.residual import POINTS
    from pushtorch.prediction.residual import corrected_mode, narrow_density, shifted_mode

    rows = []
    for p, truth, start, learned, obj in cases:
        if math.isfinite(learned):
            points = {"corrected": corrected_mode(p, factor(p)), "shifted": shifted_mode(narrow_density(p),
                                                                                           motion_bandwidth)}
            rows.append([learned if name == "learned" else _hacc_of(p.start, points[name], start, truth, obj)
                         for name in POINTS])
    if not rows:
        return {"chosen": "corrected", "points": list(POINTS), "hacc": [math.nan] * len(POINTS),
                "se": [math.nan] * len(POINTS), "pushes": 0}
    table = torch.tensor(rows, dtype=torch.float64)
    mean = table.mean(0)
    se = ((table - table[:, :1]).std(0) / math.sqrt(len(rows))).tolist() if len(rows) > 1 else [math.nan] * len(POINTS)
    chosen = POINTS[int(mean.argmin())]
    log.info("residual point prediction for %s: %s (held-out H_acc %s, paired SE against the corrected mode %s, "
             "%d pushes)", of, chosen, ", ".join(f"{n} {float(v):.4f}" for n, v in zip(POINTS, mean, strict=True)),
             ", ".join(f"{v:.4f}" for v in se[1:]), len(rows))
    return {"chosen": chosen, "points": list(POINTS), "hacc": mean.tolist(), "se": se, "pushes": len(rows)}


def _residual_scores(residual, obj: ObjectModel, records, count: int, generator: torch.Generator,
                     factors, weights=(0.0,)) -> tuple[list[torch.Tensor], int, list]:
    """Each held-out push's nll under ``residual``'s prediction at every combination of the disagreement
    ``weights`` (unless ``(0,)``, each push predicted from its push model's push condition), the narrow widenings
    ``factors(prediction)``, the defensive parts and the uncorrected shares (:func:`residual_nll_grid`), from one
    prediction per push (the same rollouts), how many pushes could not be predicted, and each predicted push's
    ``(case, prediction)`` (:func:`_push_case`)."""
    scores, skipped, predicted = [], 0, []
    for case in _held_out_pushes(obj, records, count, residual.settings.voxel_size, generator):
        scored = _predicted_scores(residual, obj, case, generator, lambda p, truth, start: _weighed_scores(
            p, truth, start, obj, factors, weights), tuple(weights) != (0.0,))
        if scored is None:
            skipped += 1
        else:
            scores.append(scored[1])
            predicted.append((case, scored[0]))
    return scores, skipped, predicted


def _weighed_scores(prediction, truth: se3.Pose, start: se3.Pose, obj: ObjectModel, factors, weights) -> torch.Tensor:
    """:func:`residual_nll_grid` of ``prediction`` at each disagreement weight of ``weights`` in turn (weight-major;
    the narrow widenings ``factors(prediction)`` at each)."""
    from pushtorch.prediction.residual import disagreeing

    return torch.cat([residual_nll_grid(p, truth, start, obj, factors(p))
                      for p in (disagreeing(prediction, w) for w in weights)])


def _predicted_scores(residual, obj: ObjectModel, case, generator: torch.Generator, score, learned: bool = False):
    """One push ``case`` (:func:`_push_case`) predicted by ``residual`` from its cloud and robot start (with
    ``learned``, from its push model's push condition, the prediction knowing that model's disagreement), and
    ``score(prediction, truth, start)``: ``(prediction, (F,))``, or None where the push cannot be predicted (no
    body, or the bumper meets no observed feature there)."""
    from pushtorch.prediction import predict
    from pushtorch.prediction.residual import predict_residual

    cloud, action, robot, start, truth = case
    unhedged = replace(residual, point="corrected", disagreement=0.0)  # the density is scored, unhedged by ξ
    try:
        if learned:
            own = predict(residual.model, cloud, action, generator, robot_start=robot)
            prediction = predict_residual(unhedged, cloud, action, generator, condition=own.condition,
                                          learned=(own.condition.object_pose, own.final_pose))
        else:
            prediction = predict_residual(unhedged, cloud, action, generator, robot_start=robot)
    except (ModelError, InvalidPoseError):
        return None
    return prediction, score(prediction, truth, start)


def residual_nll_grid(prediction, truth: se3.Pose, start: se3.Pose, obj: ObjectModel, factors, parts=DEFENSIVE_PARTS,
                      rates=UNCORRECTED_RATES) -> torch.Tensor:
    """``(F·P·R,)`` float64 the nll of ``truth`` (moved from ``start``) under ``prediction``'s density at every
    combination (factor-major, then part, then rate) of its narrow kernels' stds times each of ``factors`` (a
    factor or ``(position, rotation)`` factors), each defensive part ``(ε0, λ, w)`` of ``parts`` and each
    uncorrected share's rate of ``rates``, as :func:`pushtorch.prediction.residual.predict_residual` would have
    made it from the same rollouts (``prediction`` made without either share). The log densities of the corrected
    kernels and of the rollouts are taken once per distinct width at the truth's symmetric copies
    (:func:`~pushtorch.evaluation.likelihood.truth_copies`, refined about the unwidened density's best), mixed at
    each combination's weights, and the best copy kept, as :func:`~pushtorch.evaluation.likelihood.nll` keeps it."""
    from pushtorch.prediction.residual import defensive_factors, narrow_density, scaled_parts

    values = truth_copies(narrow_density(prediction), truth, start, prediction.start, obj.symmetry).vector()
    parts_at: dict[tuple[float, float], tuple] = {}
    at: dict[tuple[tuple[float, float], int], torch.Tensor] = {}

    def log_p(f: tuple[float, float], part: int) -> torch.Tensor:  # part 0: the corrected kernels, 1: the rollouts
        if (f, part) not in at:
            if f not in parts_at:
                parts_at[f] = scaled_parts(prediction, f)
            at[(f, part)] = parts_at[f][part].log_prob(values).reshape(-1).double()
        return at[(f, part)]

    def mixed(f: tuple[float, float], share: float) -> torch.Tensor:
        if share == 0:
            return log_p(f, 0)
        return torch.logaddexp(math.log1p(-share) + log_p(f, 0), math.log(share) + log_p(f, 1))

    novelty, out = prediction.outcome_novelty, []
    for f in factors:
        f = (float(f[0]), float(f[1])) if isinstance(f, tuple) else (float(f), float(f))
        for part in parts:
            share = defensive_share(part, novelty)
            wide = defensive_factors(prediction, f, part[2]) if share > 0 else None
            for rate in rates:
                rho = uncorrected_share(rate, novelty)
                density = mixed(f, rho)
                if wide is not None:
                    density = torch.logaddexp(math.log1p(-share) + density, math.log(share) + mixed(wide, rho))
                out.append(-float(density.max()))
    return torch.tensor(out, dtype=torch.float64)


def choose_residual_widening(residual, objects: list[ObjectModel], records: list, pushes_per_shape: int = 6,
                             generator: torch.Generator | None = None, widenings=RESIDUAL_WIDENINGS):
    """The pooled ``residual`` model with its ``widening`` and its defensive part
    (:data:`~pushtorch.models.residual.DEFENSIVE_PARTS`) and uncorrected share
    (:data:`~pushtorch.models.residual.UNCORRECTED_RATES`) chosen together by leave-one-shape-out likelihood (module
    docstring); the search is kept in ``meta["widening"]``. The same held-out shapes' pushes choose its point
    prediction (:data:`~pushtorch.models.residual.POINTS`), as :func:`choose_residual_scale` chooses one object's:
    the corrected kernels' mode at the chosen widening, their local mode at the motion kernels' width, or the
    held-out pooled push model's own prediction, whichever has the lowest mean H_acc (``meta["widening"]["point"]``).

    Args:
        residual: a pooled :class:`~pushtorch.models.residual.ResidualModel`; objects, records: its training
            shapes and their push records, in its order (``residual.shape_names``).
        pushes_per_shape: held-out pushes predicted per shape (drawn among its valid pushes).

    Raises:
        InvalidParameterError: a residual model of one object, shapes that are not its own, or no held-out
            push that could be predicted.
    """
    if residual.shapes is None or [o.name for o in objects] != list(residual.shape_names) or len(objects) < 2:
        raise InvalidParameterError("choosing the residual's widening holds one of its pooled training shapes out: "
                                    f"it needs the model's own shapes ({residual.shape_names}), at least two, got "
                                    f"{[o.name for o in objects]}")
    _check_pushes(pushes_per_shape)
    generator = generator or torch.Generator().manual_seed(0)
    grid = [float(k) for k in widenings]
    base = replace(residual, widening=0.0, defensive=(0.0, 0.0, 0.0), uncorrected=0.0, point="corrected")
    scores, skipped, predicted = [], 0, []
    for s, (obj, shape_records) in enumerate(zip(objects, records, strict=True)):
        try:
            held_out = base.without_shape(s)
        except InvalidParameterError:  # the only shape of some action: nothing to hold it out against
            skipped += 1
            continue
        more, missed, made = _residual_scores(held_out, obj, shape_records, pushes_per_shape, generator,
                                              lambda p: [math.sqrt(1.0 + k * p.contact_distance2) for k in grid])
        scores += more
        skipped += missed
        predicted += [(held_out, obj, case, p) for case, p in made]
    if not scores:
        raise InvalidParameterError("no held-out push of any training shape could be predicted to choose the "
                                    "residual's widening")
    mean = torch.stack(scores).mean(0)
    best = int(mean.argmin())
    kappa, part, rate = _combination(grid, best)
    log.info("residual widening: kappa=%g, defensive part %s, uncorrected rate %g (held-out nll %.2f against %.2f "
             "unwidened, %d pushes)", kappa, part, rate, float(mean[best]), float(mean[0]) if grid[0] == 0.0
             else math.nan, len(scores))
    # the same held-out shapes' pushes choose the point; the held-out push model's own predictions draw from
    # generators of their own, so the choice of kappa draws what it drew before
    cases = [(p, case[4], case[3], _learned_hacc(held_out, obj, case, torch.Generator().manual_seed(k)), obj)
             for k, (held_out, obj, case, p) in enumerate(predicted)]
    point = _point_choice(cases, lambda p: math.sqrt(1.0 + kappa * p.contact_distance2),
                          residual.settings.motion_bandwidth, "the pooled model's held-out shapes")
    meta = dict(residual.meta)
    meta["widening"] = {"chosen": kappa, "defensive_chosen": list(part), "grid": grid,
                        "defensive": [list(d) for d in DEFENSIVE_PARTS], "uncorrected_chosen": rate,
                        "uncorrected": list(UNCORRECTED_RATES), "nll": mean.tolist(), "pushes": len(scores),
                        "skipped": skipped, "point": point}
    return replace(residual, widening=kappa, defensive=part, uncorrected=rate, point=point["chosen"], meta=meta)


def _combination(grid: list[float], index: int) -> tuple[float, tuple[float, float, float], float]:
    """The ``(widening, defensive part, uncorrected rate)`` at ``index`` of :func:`residual_nll_grid`'s scores over
    ``grid`` × the defensive parts × the uncorrected rates (:mod:`pushtorch.models.residual`'s grids)."""
    rates, parts = len(UNCORRECTED_RATES), len(DEFENSIVE_PARTS)
    return grid[index // (parts * rates)], DEFENSIVE_PARTS[index // rates % parts], UNCORRECTED_RATES[index % rates]


def choose_novelty_widening(residuals: list, objects: list[ObjectModel], records: list, pushes_per_shape: int = 6,
                            generator: torch.Generator | None = None, widenings=NOVELTY_WIDENINGS,
                            shapes: list[ObjectModel] = (), shape_records: list = ()) -> list:
    """Residual models of one object each, trained on the same prior, each with its novelty widening ``ν`` and
    hedges chosen on held-out pushes: each model predicts ``pushes_per_shape`` of every *other* training object's
    pushes (a shape it never saw), of each of ``shapes`` (generated training shapes no model was trained on, with
    their ``shape_records``: rollouts of intermediate novelty) and of each action's own, each held out of it in
    turn (:meth:`~pushtorch.models.residual.ResidualModel.without_pushes`: small novelty, where widening costs),
    from its push model's push condition. Each prediction is hedged at every disagreement weight ``ξ`` of
    :data:`~pushtorch.models.residual.DISAGREEMENT_WEIGHTS` (its novelty ``n + ξ·δ²``), novelty widening ``ν``
    (:mod:`pushtorch.prediction.residual`), defensive part ``(ε0, λ, w)`` of
    :data:`~pushtorch.models.residual.DEFENSIVE_PARTS` and uncorrected share's rate ``τ`` of
    :data:`~pushtorch.models.residual.UNCORRECTED_RATES`. For each model, the combinations whose mean nll over
    the pushes it predicted is within 2 paired SE of the lowest are tied; of those whose 90 % regions hold the
    truths of the same pushes as near 90 % of the time as the nearest, within its SE, on average over the groups
    of pushes (the model on each shape, its own pushes one group), the sharpest is kept
    (:func:`~pushtorch.evaluation.likelihood.calibrated_choice`, each density drawn from as
    :func:`~pushtorch.prediction.residual.hedged_density` builds it; kept in ``meta["novelty"]``): how far a
    model's corrections carry to other shapes is its own. A single object keeps ``ν = ξ = 0``.

    Raises:
        InvalidParameterError: fewer than two models, objects or records not one per model, a model read from its
            file (its kernels no longer know their pushes), or no push predicted.
    """
    if len(residuals) < 2 or len(objects) != len(residuals) or len(records) != len(residuals) \
            or len(shapes) != len(shape_records):
        raise InvalidParameterError("choosing the residual's novelty widening holds each training object out of "
                                    f"another's model: it needs two models or more, one object and one set of "
                                    f"records each (and one set per extra shape), got {len(residuals)}, "
                                    f"{len(objects)} and {len(records)} ({len(shapes)} shapes, "
                                    f"{len(shape_records)} sets)")
    _check_pushes(pushes_per_shape)
    if any(m.manipulator.push is None for r in residuals for m in r.model.motions):
        raise InvalidParameterError("choosing the residual's novelty widening holds each model's own pushes out: it "
                                    "needs models trained in this session (their kernels know their pushes), not "
                                    "loaded ones")
    from pushtorch.prediction.residual import disagreeing, hedged_density, novelty_factors

    generator = generator or torch.Generator().manual_seed(0)
    grid, weights = [float(v) for v in widenings], [float(v) for v in DISAGREEMENT_WEIGHTS]

    def factors(p):
        return [novelty_factors(p, v) for v in grid]

    scores, cases, groups, owner, skipped = [], [], [], [], [0] * len(residuals)
    others = list(zip(objects, records, strict=True)) + list(zip(shapes, shape_records, strict=True))
    plain = [replace(r, novelty_widening=0.0, defensive=(0.0, 0.0, 0.0), uncorrected=0.0, disagreement=0.0)
             for r in residuals]
    for i, residual in enumerate(plain):
        for j, (obj, other) in enumerate(others):
            if j != i:
                more, missed, made = _residual_scores(residual, obj, other, pushes_per_shape, generator, factors,
                                                      weights)
                scores += more
                skipped[i] += missed
                cases += [(p, obj) for _, p in made]
                groups += [f"{objects[i].name}'s model on {obj.name}"] * len(made)
                owner += [(i, False)] * len(made)
    for i, (residual, obj, own) in enumerate(zip(plain, objects, records, strict=True)):  # own pushes, held out
        for _, held_out, case in own_held_out_pushes(residual, obj, own, pushes_per_shape, generator,
                                                     "choosing the residual's novelty widening"):
            scored = None if held_out is None else _predicted_scores(
                held_out, obj, case, generator,
                lambda p, truth, start, obj=obj: _weighed_scores(p, truth, start, obj, factors, weights), True)
            if scored is None:
                skipped[i] += 1
                continue
            scores.append(scored[1])
            cases.append((scored[0], obj))
            groups.append(f"{obj.name}'s model on its own")
            owner.append((i, True))
    block = len(grid) * len(DEFENSIVE_PARTS) * len(UNCORRECTED_RATES)

    def covered_at(keep: list[int], c: int) -> tuple[torch.Tensor, torch.Tensor]:
        nu, part, rate = _combination(grid, c % block)
        edge = torch.stack([hdr_thresholds(hedged_density(q, novelty_factors(q, nu), part, rate), (HEDGE_LEVEL,),
                                           generator=torch.Generator().manual_seed(k), symmetry=obj.symmetry,
                                           plane=p.start).reshape(-1)[0]
                            for k in keep for p, obj in [cases[k]] for q in [disagreeing(p, weights[c // block])]])
        return covered(rows[keep, c], edge.unsqueeze(-1)).reshape(-1), edge

    if len({o for o, _ in owner}) < len(residuals):
        raise InvalidParameterError("no held-out push could be predicted by a residual model to choose its hedges")
    rows, chosen = torch.stack(scores), []
    for i, residual in enumerate(residuals):  # each model's hedges on the pushes it predicted
        keep = [k for k, (o, _) in enumerate(owner) if o == i]
        best, calibration = calibrated_choice(rows[keep], lambda c, keep=keep: covered_at(keep, c), HEDGE_LEVEL,
                                              groups=[groups[k] for k in keep])
        mean, own = rows[keep].mean(0), sum(owner[k][1] for k in keep)
        xi, (nu, part, rate) = weights[best // block], _combination(grid, best % block)
        k, cov = calibration["candidates"].index(best), calibration["coverage"]
        log.info("%s's residual model: novelty widening %g, defensive part %s, uncorrected rate %g, disagreement "
                 "weight %g (held-out nll %.2f, 90 %% coverage %.2f, per group %s; %d tied in likelihood, %d "
                 "calibrated alike; %d pushes, %d its own)", objects[i].name, nu, part, rate, xi, float(mean[best]),
                 cov[k], " ".join(f"{g:.2f}" for g in calibration["group_coverage"][k]), len(cov),
                 len(calibration["calibrated_alike"]), len(keep), own)
        entry = dict(chosen=nu, defensive_chosen=list(part), across=[o.name for o in objects],
                     shapes=[o.name for o in shapes], grid=grid, defensive=[list(d) for d in DEFENSIVE_PARTS],
                     uncorrected_chosen=rate, uncorrected=list(UNCORRECTED_RATES), form=NOVELTY_FORM,
                     nll=mean.tolist(), disagreement=list(weights), disagreement_chosen=xi, pushes=len(keep) - own,
                     own_pushes=own, pushes_per_shape=int(pushes_per_shape), skipped=skipped[i],
                     calibration=calibration)
        chosen.append(replace(residual, novelty_widening=nu, defensive=part, uncorrected=rate, disagreement=xi,
                              meta={**residual.meta, "novelty": entry}))
    return chosen


def _check_pushes(pushes_per_shape) -> None:
    if isinstance(pushes_per_shape, bool) or int(pushes_per_shape) != pushes_per_shape or pushes_per_shape < 1:
        raise InvalidParameterError(f"widening_pushes must be a whole number >= 1, got {pushes_per_shape!r}")
