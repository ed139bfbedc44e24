"""An experiment's ground truth and scores: the pushes simulated from the starts a prediction set chose, the
likelihood of each truth under every predictor's density, and the results records that compare predictions with
the truth (paper, Experimental Setup, Fig. prediction_accuracy_methodology, ground truth; Eq. pam for H_acc).

:mod:`pushtorch.experiments.prediction_sets` makes the sets this module scores.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.evaluation.metrics import Accuracy, accuracy, displaced
from pushtorch.experiments.context import (
    ExperimentContext,
    fingerprint,
    load_arrays,
    save_arrays,
    scores_made_from,
    stable_seed,
)
from pushtorch.experiments.prediction_sets import PredictionSet, cache_name, scores_path
from pushtorch.objects import ObjectModel
from pushtorch.paths import contained_path

__all__ = [
    "METRICS",
    "compare",
    "compare_displacement",
    "likelihood_scores",
    "simulate_truth",
    "summarise",
    "truth_fingerprint",
]


def truth_fingerprint(ctx: ExperimentContext, conditions: Sequence[tuple[str, str]], samples: int,
                      seed_key: str) -> str:
    """What a group's ground truth is made from besides its predictions (conditions, priors, samples, seeds,
    simulator): the scores cached with a prediction set are reused only for the same truth."""
    priors = [(repr(ctx.prior("friction", f)), repr(ctx.prior("mass", m))) for f, m in conditions]
    return fingerprint(conditions=list(conditions), priors=priors, samples=samples, seed=ctx.seed,
                       seed_key=seed_key, sim=asdict(ctx.sim), duration=ctx.duration)


def likelihood_scores(ctx: ExperimentContext, key: str, obj: ObjectModel, predictions: PredictionSet,
                      truth_final: se3.Pose, truth: str) -> dict[str, torch.Tensor]:
    """Negative log-likelihoods (nats) of the ground truths ``(C, N, A, S)`` under every method's predicted
    density, in the displacement sense (:func:`pushtorch.evaluation.likelihood.nll`): ``{method: (C, N, A, S)}``;
    and for every method with a density of its own, ``{"coverage:<method>": (C, N, A, S, L)}``, 1 where the
    truth lies inside the density's highest-density region of each level of
    :data:`~pushtorch.evaluation.likelihood.COVERAGE_LEVELS` (:func:`~pushtorch.evaluation.likelihood.hdr_thresholds`).

    ``pushtorch``, ``mean_motion`` and ``physics_ensemble`` are scored under their own densities; the point
    predictions under one kernel of the model's motion bandwidth
    (:func:`pushtorch.evaluation.likelihood.point_density`), without coverage. Cached as
    ``<run_dir>/scores/<key>.npz`` with the set's and the truth's fingerprints (``truth``:
    :func:`truth_fingerprint`).

    Raises:
        RecordFormatError: the set came from the cache but its scores did not (they are written together).
    """
    from pushtorch.evaluation.likelihood import COVERAGE_LEVELS, covered, hdr_thresholds, nll, point_density

    path = scores_path(ctx, key)
    made_from = scores_made_from(predictions.fingerprint, truth)
    if predictions.densities is None:
        arrays, meta = load_arrays(path)
        if meta.get("made_from") != made_from:
            raise RecordFormatError(f"{path} holds the scores of another prediction set or ground truth")
        return arrays
    c_count, n, a_count, samples = truth_final.batch_shape
    p_std, rot_std = ctx.settings.motion_p_std, ctx.settings.motion_rot_std
    scores: dict[str, torch.Tensor] = {}
    for method, (start, final) in predictions.methods().items():
        out = torch.empty(c_count, n, a_count, samples)
        inside = torch.zeros(c_count, n, a_count, samples, len(COVERAGE_LEVELS))
        has_density = True
        for i in range(n):
            for j in range(a_count):
                own = predictions.densities[i][j].get(method)
                has_density = has_density and own is not None
                density = own or point_density(final.take((i, j)), p_std, rot_std)
                truths = se3.Pose.unchecked(truth_final.p[:, i, j].reshape(-1, 3),
                                            truth_final.q[:, i, j].reshape(-1, 4))
                values = nll(density, truths, predictions.truth_initial.take(i), start.take((i, j)),
                             obj.symmetry)
                out[:, i, j] = values.reshape(c_count, samples).float()
                if own is not None:
                    draws = torch.Generator().manual_seed(stable_seed(ctx.seed, key, method, i, j, "coverage"))
                    thresholds = hdr_thresholds(own, COVERAGE_LEVELS, generator=draws, symmetry=obj.symmetry,
                                                plane=start.take((i, j)))
                    inside[:, i, j] = covered(values, thresholds).reshape(c_count, samples, -1).float()
        scores[method] = out
        if has_density:
            scores[f"coverage:{method}"] = inside
    save_arrays(path, scores, {"made_from": made_from})
    return scores


def simulate_truth(
    ctx: ExperimentContext,
    key: str,
    obj: ObjectModel,
    predictions: PredictionSet,
    conditions: Sequence[tuple[str, str]],
    samples: int,
    seed_key: str | None = None,
) -> tuple[se3.Pose, torch.Tensor]:
    """Ground-truth final poses ``(C, N, A, S)`` of every condition, test pose, action and sample (cached).

    Each push starts from the robot start pose the model chose and the true initial pose; mass and
    friction are drawn from the test condition's priors (``conditions``: (friction name, mass name)),
    seeded by ``seed_key`` (default ``key``) and condition, so groups sharing a ``seed_key`` face the
    same physical parameters. Pushes run in parallel into ``<run_dir>/truth/<key>/``.

    Returns:
        The final poses, and ``(C, N, A, S)`` flags of pushes in which the object tipped or left the
        ground (in practice: the chosen robot start pose overlapped the object and the engine threw it).
    """
    from pushtorch.sim.plan import PushPlan
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import object_spec

    if samples < 1:
        raise InvalidParameterError(f"truth_samples must be >= 1, got {samples}")
    n, a_count = predictions.final.batch_shape
    c_count = len(conditions)
    shape = (c_count, n, a_count, samples)
    masses, frictions = [], []
    for friction, mass in conditions:
        seed = stable_seed(ctx.seed, "truth", seed_key or key, friction, mass)
        generator = torch.Generator().manual_seed(seed)
        masses.append(ctx.prior("mass", mass).sample((n, a_count, samples), generator))
        frictions.append(ctx.prior("friction", friction).sample((n, a_count, samples), generator))

    def spread(pose: se3.Pose, dims: tuple[int, ...]) -> se3.Pose:
        return se3.Pose.unchecked(pose.p.double().reshape(*dims, 3).expand(*shape, 3).reshape(-1, 3),
                        pose.q.double().reshape(*dims, 4).expand(*shape, 4).reshape(-1, 4))

    action_index = torch.arange(a_count).reshape(1, 1, a_count, 1).expand(shape).reshape(-1)
    plan = PushPlan(
        object_name=obj.name,
        robot_start=spread(predictions.robot_start, (1, n, a_count, 1)),
        object_initial=spread(predictions.truth_initial, (1, n, 1, 1)),
        action=ctx.actions.double()[action_index],
        mass=torch.stack(masses).reshape(-1),
        ground_friction=torch.stack(frictions).reshape(-1),
        action_index=action_index,
        seed=stable_seed(ctx.seed, "truth", key),
        duration=ctx.duration,
    )
    if ctx.recording is not None:
        ctx._truth_plan = (predictions.fingerprint, plan, shape)
    folder = contained_path(ctx.run_dir, "truth", cache_name(ctx, key), what="experiment, object or prior name")
    # small plans run in this process: a worker pool costs more than it saves
    small = len(plan) < 4 * ctx.shard_size
    run_plan(object_spec(obj), plan, folder, ctx.sim, workers=1 if small else ctx.workers, shard_size=ctx.shard_size,
             progress=False, executor=None if small else ctx.executor)
    records = load_records(folder)
    final = se3.Pose.unchecked(records.object_final.p.reshape(*shape, 3), records.object_final.q.reshape(*shape, 4))
    return final, (records.tipped | records.left_ground).reshape(shape)


#: The scores of a prediction record, primary first (see :func:`summarise`).
METRICS = ("displacement", "frame")


def compare_displacement(initial_estimate: se3.Pose, final_estimate: se3.Pose, truth_initial: se3.Pose,
                         truth_final: se3.Pose, obj: ObjectModel) -> Accuracy:
    """Accuracy of predicted displacements ``(N, A)`` (from ``initial_estimate`` to ``final_estimate``)
    applied to the true start poses ``(N,)``, against ground truths ``(N, A, S)``."""
    return compare(displaced(initial_estimate, final_estimate, truth_initial.unsqueeze(-1)), truth_final, obj)


def compare(estimate: se3.Pose, truth: se3.Pose, obj: ObjectModel) -> Accuracy:
    """Accuracy of estimates ``(...)`` against ground truths ``(..., S)`` (each estimate vs each sample)."""
    shape = truth.batch_shape
    est = se3.Pose.unchecked(estimate.p.unsqueeze(-2).expand(*shape, 3), estimate.q.unsqueeze(-2).expand(*shape, 4))
    flat = int(np.prod(shape))
    return accuracy(est.reshape(flat), truth.reshape(flat), obj)


def summarise(
    task: str,
    obj: str,
    predictor: str,
    acc: Accuracy,
    model: str | None = None,
    condition: str | None = None,
    selection_rate: float | None = None,
    metric: str | None = None,
    nll: torch.Tensor | None = None,
    coverage: torch.Tensor | None = None,
) -> dict[str, Any]:
    """One results.json record: a group's H_acc mean and std, and mean raw errors, over ``n`` comparisons.

    ``predictor`` is the record's ``method``: the predictor's name (``pushtorch``, ``no_motion``,
    ``physics_from_cloud``, a selection method, ``position_model`` …).

    ``metric`` (prediction and selection records): ``displacement``, the predicted motion applied to the
    true start pose (:func:`pushtorch.evaluation.metrics.displaced`, the primary score), or ``frame``, the predicted
    final pose as it is (the estimated frame against the test object's own); pose records carry none.
    ``nll`` (displacement records): the per-comparison negative log-likelihoods of the truth under the
    method's density (:func:`likelihood_scores`), summarised as ``nll_mean`` and ``nll_median`` (nats);
    ``coverage`` (displacement records of a method with a density): ``(..., 2)`` inside flags of the 50 % and
    90 % regions, summarised as ``coverage_50`` and ``coverage_90`` (None for a point prediction)."""
    h = acc.hacc.reshape(-1).double()
    record = {
        "task": task,
        "object": obj,
        "method": predictor,
        "model": model,
        "condition": condition,
        "n": int(h.numel()),
        "hacc_mean": float(h.mean()),
        "hacc_std": float(h.std(unbiased=False)) if h.numel() > 1 else 0.0,
        "linear_cm": float(acc.linear_cm.reshape(-1).double().mean()),
        "angular_deg": float(acc.angular_deg.reshape(-1).double().mean()),
    }
    if task == "selection":
        record["selection_rate"] = None if selection_rate is None else float(selection_rate)
    if metric is not None:
        if metric not in METRICS:
            raise InvalidParameterError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
        record["metric"] = metric
        # the likelihood is scored in the displacement sense only; frame records carry the key, empty
        record["nll_mean"] = None if nll is None else float(nll.double().mean())
        record["nll_median"] = None if nll is None else float(nll.double().median())
        flags = None if coverage is None else coverage.double().reshape(-1, coverage.shape[-1]).mean(0)
        record["coverage_50"] = None if flags is None else float(flags[0])
        record["coverage_90"] = None if flags is None else float(flags[1])
    return record
