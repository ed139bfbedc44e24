"""An experiment's recording: the example predictions logged to Rerun with their ground-truth pushes,
densities and scores (no paper section: review of every prediction).
"""

from __future__ import annotations

import logging

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.evaluation.metrics import accuracy, displaced
from pushtorch.experiments.context import ExperimentContext
from pushtorch.experiments.prediction_sets import Example, Examples, PredictionSet
from pushtorch.experiments.scoring import compare_displacement
from pushtorch.objects import ObjectModel

__all__ = [
    "entity_label",
    "log_examples",
]

log = logging.getLogger("pushtorch.experiments")


def entity_label(*parts: str) -> str:
    """A prediction's entity path below ``world/model/prediction`` from words, one level each:
    ``entity_label("model_selection", "cube", "adaptive")`` is ``model_selection/cube/adaptive``. Within a
    level, anything outside ``[A-Za-z0-9_.-]`` (a ``/`` too) becomes ``_``
    (:func:`pushtorch.viz.core.entity_name`)."""
    from pushtorch.viz.core import entity_name

    return "/".join(entity_name(str(p).replace("/", "_")) for p in parts)


def _one_push(plan, k: int):
    """Push ``k`` of a :class:`~pushtorch.sim.plan.PushPlan` as a plan of its own (same index and seed)."""
    from pushtorch.sim.plan import PushPlan

    one = slice(k, k + 1)
    return PushPlan(
        object_name=plan.object_name,
        robot_start=se3.Pose.unchecked(plan.robot_start.p[one], plan.robot_start.q[one]),
        object_initial=se3.Pose.unchecked(plan.object_initial.p[one], plan.object_initial.q[one]),
        action=plan.action[one], mass=plan.mass[one], ground_friction=plan.ground_friction[one],
        action_index=plan.action_index[one], index=plan.index[one], seed=plan.seed, duration=plan.duration,
    )


def _truth_push(ctx: ExperimentContext, obj: ObjectModel, predictions: PredictionSet, i: int, j: int):
    """The ground-truth push shown with example ``(i, j)``: test condition 0, sample 0, re-simulated here
    with its trajectory (its final pose is compared with the recorded one by :func:`log_examples`: since
    every push rebuilds the object's shape they agree bit for bit; the check guards that); None if
    :func:`~pushtorch.experiments.scoring.simulate_truth` did not run for these predictions while recording."""
    from pushtorch.sim.runner import simulate_plan
    from pushtorch.sim.settings import object_spec

    if ctx._truth_plan is None or ctx._truth_plan[0] != predictions.fingerprint:
        log.warning("no ground-truth plan for %s: its pushes are not animated", predictions.fingerprint[:8])
        return None
    _, plan, (_, n, a_count, samples) = ctx._truth_plan
    return simulate_plan(object_spec(obj), _one_push(plan, (i * a_count + j) * samples), ctx.sim)


def _condition_hacc(predictions: PredictionSet, truth_final: se3.Pose, obj: ObjectModel) -> torch.Tensor:
    """Each test condition's H_acc ``(N,)``: the group's primary score (displacement) against the ground truth
    ``(N, A, S)``, averaged over actions and truth samples (what ``worst:k`` and ``best:k`` rank by)."""
    n, a_count = predictions.final.batch_shape
    acc = compare_displacement(predictions.estimate, predictions.final, predictions.truth_initial, truth_final, obj)
    return acc.hacc.double().reshape(n, a_count, -1).mean((1, 2))


def _chosen_examples(predictions: PredictionSet, examples: Examples, truth_final: se3.Pose,
                    obj: ObjectModel) -> tuple[list[Example], dict[int, float]]:
    """The examples ``examples.choice`` picks, in its order (each condition's actions in order), and each
    chosen condition's mean H_acc (:func:`_condition_hacc`; the ranking of ``worst`` and ``best``)."""
    choice = examples.choice
    if choice is None:
        return [], {}
    n = int(predictions.final.batch_shape[0])
    hacc = _condition_hacc(predictions, truth_final, obj)
    indices = choice.choose(hacc)
    if choice.rule == "list" and len(indices) < len(choice.indices):
        log.warning("recording.conditions %s: this group has test conditions 0..%d only; logging %s",
                    choice, n - 1, indices)
    if choice.by_hacc:
        if examples.again is None:
            raise InvalidParameterError("these examples cannot be predicted again: no predict_set behind them")
        picked = [e for i in indices for e in examples.again(i)]
    else:
        by_condition: dict[int, list[Example]] = {}
        for e in examples.kept:
            by_condition.setdefault(e.condition, []).append(e)
        picked = [e for i in indices for e in sorted(by_condition.get(i, []), key=lambda e: e.action)]
    return picked, {i: float(hacc[i]) for i in indices}


def log_examples(
    ctx: ExperimentContext,
    label: str,
    obj: ObjectModel,
    examples: Examples,
    predictions: PredictionSet,
    truth_final: se3.Pose,
    nll: torch.Tensor | None = None,
) -> None:
    """Log example predictions with their true initial and final poses, ground-truth push and density.

    The conditions logged are ``examples.choice`` (``recording.conditions``, :class:`LogConditions`), each
    with every action. Every example goes under ``world/model/prediction/<label>/c<i>a<j>`` (``label`` from
    :func:`entity_label`: ``<part>/<object>/<model or method>``; entities as in :mod:`pushtorch.viz.predictions`,
    the predicted density included), whose transform shifts it to a free cell of the recording's grid. Its
    ground-truth push (test condition 0, sample 0: the pose ``truth_final`` holds) is re-simulated in this
    process with its trajectory and played on ``sim_time`` at ``<root>/truth_push``; a re-simulated final
    pose that differs from the recorded one is reported in the log and the summary. ``<root>/summary``
    holds the example's scores as text, also kept in ``ctx.logged_predictions``: H_acc (displacement, the
    records' primary score, with the frame score beside it), ``nll`` (the records' score of that truth,
    :func:`~pushtorch.experiments.scoring.likelihood_scores`) and the raw errors. Where the group has a residual
    model (``pushtorch_residual``), its prediction of the same push goes to a cell of its own beside it, with its
    simulator rollouts (:func:`_log_residual`).

    Args:
        truth_final: ground-truth final poses ``(N, A, S)`` of test condition 0 (sample 0 is shown).
        nll: the group's ``pushtorch`` negative log-likelihoods ``(N, A, S)`` of the same truths
            (:func:`~pushtorch.experiments.scoring.likelihood_scores` of test condition 0), or None (the summary
            then has none).
    """
    from pushtorch.viz.predictions import PREDICTION, log_prediction

    if ctx.recording is None or not examples:
        return
    picked, condition_hacc = _chosen_examples(predictions, examples, truth_final, obj)
    for example in picked:
        i, j = example.condition, example.action
        root = _cell(ctx, f"{PREDICTION}/{label}/c{i}a{j}")
        truth = truth_final.take((i, j, 0))
        push = _truth_push(ctx, obj, predictions, i, j)
        replay = "ground-truth push not re-simulated"
        if push is not None:
            gap = float((push.object_final.p[0].to(truth.p) - truth.p.reshape(3)).abs().max())
            same = torch.equal(push.object_final.p[0].to(truth.p), truth.p.reshape(3)) and torch.equal(
                push.object_final.q[0].to(truth.q), truth.q.reshape(4))
            replay = ("re-simulated ground-truth push ends at the recorded final pose" if same else
                      f"re-simulated ground-truth push ends {gap:.2e} m from the recorded final pose")
            if not same:
                log.warning("%s/c%da%d: %s", label, i, j, replay)
        truth_initial = predictions.truth_initial.take(i)
        log_prediction(ctx.recording, example.prediction, truth_initial, truth, obj,
                       label=f"{label}/c{i}a{j}", cloud=example.features, truth_push=push, drawn=example.drawn)
        estimate, final = predictions.estimate.take((i, j)), predictions.final.take((i, j))
        acc = accuracy(displaced(estimate, final, truth_initial), truth, obj)
        frame = accuracy(final, truth, obj)
        score = "nll –" if nll is None else f"nll {float(nll[i, j, 0]):.2f} nats (of this truth, displacement)"
        why = ("" if not examples.choice.by_hacc else
               f" ({examples.choice}: mean H_acc {condition_hacc[i]:.3f} over its actions and truth samples)")
        summary = (f"`{label}/c{i}a{j}`: condition {i}{why}, action {ctx.actions[j].tolist()}: "
                   f"H_acc {float(acc.hacc):.3f} (displacement; frame {float(frame.hacc):.3f}), {score}, "
                   f"linear {float(acc.linear_cm):.2f} cm, angular {float(acc.angular_deg):.1f} deg; {replay}")
        _summary(ctx, root, summary)
        if example.residual is not None:
            _log_residual(ctx, label, example, truth_initial, truth, obj, push, replay)


def _log_residual(ctx: ExperimentContext, label: str, example: Example, truth_initial: se3.Pose, truth: se3.Pose,
                  obj: ObjectModel, push, replay: str) -> None:
    """The residual model's prediction of an example's push, in a grid cell of its own at
    ``world/model/prediction/<label>/pushtorch_residual/c<i>a<j>``: its simulator rollouts beside its density
    (:func:`pushtorch.viz.predictions.log_prediction`), the ground-truth push, and its scores as text."""
    from pushtorch.viz.predictions import PREDICTION, log_prediction

    i, j, residual = example.condition, example.action, example.residual
    path = f"{label}/pushtorch_residual/c{i}a{j}"
    root = _cell(ctx, f"{PREDICTION}/{path}")
    log_prediction(ctx.recording, residual, truth_initial, truth, obj, label=path, cloud=example.features,
                   truth_push=push, drawn=example.residual_drawn)
    acc = accuracy(displaced(residual.start, residual.final_pose, truth_initial), truth, obj)
    summary = (f"`{path}`: the residual model's prediction of condition {i}, action {ctx.actions[j].tolist()}: "
               f"H_acc {float(acc.hacc):.3f} (displacement), linear {float(acc.linear_cm):.2f} cm, angular "
               f"{float(acc.angular_deg):.1f} deg; {residual.rollouts.p.shape[0]} rollouts ({residual.thrown} "
               f"thrown), contact distance² {residual.contact_distance2:.2f}, kernels widened "
               f"×{residual.widened_by:.2f}; {replay}")
    _summary(ctx, root, summary)


def _cell(ctx: ExperimentContext, root: str) -> str:
    """``root``, moved to the recording's next free grid cell (a static transform); returns ``root``."""
    import rerun as rr

    x, y = ctx.next_slot()
    ctx.recording.log(root, rr.Transform3D(translation=[x, y, 0.0]), static=True)
    return root


def _summary(ctx: ExperimentContext, root: str, summary: str) -> None:
    """A logged example's scores as text at ``<root>/summary``, kept in ``ctx.logged_predictions`` too."""
    import rerun as rr

    ctx.recording.log(f"{root}/summary", rr.TextDocument(summary, media_type=rr.MediaType.MARKDOWN), static=True)
    ctx.logged_predictions.append((root, summary))
