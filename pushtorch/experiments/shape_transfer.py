"""Transfer from many shapes: one model pooled over a family of generated shapes against the paper's two-object
model, on the six test objects and the held-out shapes (paper, §Test Set and §Prediction Accuracy on Novel
Contexts for the protocol; §Conclusion's transfer by local contact models for the thesis tested).

Training (``model``): the general friction prior with the mass at the paper's default (friction biasing's
general model). ``model.training_objects`` names the pooled model's shapes (catalogue names, mesh files,
``shapes:<kind>:<count>`` entries, :func:`pushtorch.objects.shapes.resolve_training_objects`), and
``model.training_pushes`` the pushes they share in all; the paper's model trains on the cube and the cylinder
with ``model.samples_per_action`` as always. The pooled model never trains on a test object: no catalogue
object may be in its list, and generated training seeds stay below the held-out set's.

Predictors, on the same test poses and seeds (records ``task: "transfer"``, ``model`` the training set):

* ``pushtorch_shapes``: the pooled model (:mod:`pushtorch.models.pooled`), with its ``mean_motion`` and
  ``nearest_push`` fit on the same pushes, ``physics_from_cloud``, ``physics_ensemble`` (the cloud's body rolled
  out ``ensemble`` times under the training prior, a density) and ``oracle_physics`` (the true mesh: an oracle);
  with ``residual: true``, ``pushtorch_residual``: the pooled model's residual model (its residuals taken on every
  shape's pushes, its widening chosen across them, :func:`~pushtorch.experiments.training.train_pooled_residual`),
  from the pooled model's robot start;
* ``pushtorch_library``: the same shapes' per-shape models, one chosen per cloud by ``H_r`` (paper, §Model
  Selection);
* ``pushtorch``: the paper's two-object model (``training_object_of``; held-out shapes by ``H_r``), with its own
  ``mean_motion`` and ``nearest_push``.

Test conditions are friction biasing's (friction low / medium / high, mass at the default). Every record has
``hacc_mean``, ``hacc_std``, ``n``, ``nll_mean`` and, for a method with a density, ``coverage_50`` and
``coverage_90``. The recording logs the pooled model's examples (``recording.conditions``), each with its residual
model's prediction of the same push beside it. Run: ``python -m pushtorch experiment=shape_transfer``; a part of
the quickstart at small sizes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.common import (
    ExperimentContext,
    as_names,
    compare,
    compare_displacement,
    entity_label,
    likelihood_scores,
    load_test_objects,
    log_examples,
    plain,
    predict_set,
    prior_pairs,
    progress_bar,
    sample_test_poses,
    simulate_truth,
    stable_seed,
    summarise,
    train_model,
    train_pooled,
    train_pooled_residual,
    truth_fingerprint,
)
from pushtorch.experiments.statistics import sample_entry
from pushtorch.experiments.suite import run_suite
from pushtorch.models.residual import DEFAULT_ENSEMBLE
from pushtorch.objects import catalogue_names, load_object
from pushtorch.objects.shapes import held_out_shapes, resolve_training_objects

__all__ = ["GROUPS", "run", "run_part"]

#: Each training set's predictions: its pushtorch's method name and the baselines recorded with it.
GROUPS = {
    "shapes": ("pushtorch_shapes", ("mean_motion", "nearest_push", "physics_from_cloud", "physics_ensemble",
                                    "oracle_physics")),
    "library": ("pushtorch_library", ()),
    "paper": ("pushtorch", ("mean_motion", "nearest_push")),
}


def _training_shapes(model_cfg: Mapping[str, Any], test_names: set[str]):
    entries = model_cfg.get("training_objects")
    if not entries:
        raise InvalidParameterError("shape_transfer needs model.training_objects (e.g. [shapes:mixed:24])")
    entries = [entries] if isinstance(entries, str) else list(entries)
    catalogue = [e for e in entries if str(e) in catalogue_names()]
    if catalogue:
        raise InvalidParameterError(f"model.training_objects names the catalogue objects {catalogue}: the many-shape "
                                    "model never trains on a test object")
    shapes = resolve_training_objects(entries)
    clash = sorted({s.name for s in shapes} & test_names)
    if clash:
        raise InvalidParameterError(f"model.training_objects holds the test objects {clash}")
    return shapes


def run_part(cfg, part: Mapping[str, Any], ctx: ExperimentContext,
             model_cfg: Mapping[str, Any]) -> tuple[list[dict], dict]:
    """Train the three training sets' models, predict every test object and score every method.

    Args:
        part: ``name``, ``objects``, ``held_out`` (how many held-out shapes join the test set),
            ``training_object_of`` (the paper model's), ``conditions``, ``test_conditions``, ``truth_samples``,
            ``yaw_range_deg``, ``ensemble`` (physics_ensemble's rollouts), ``widening_pushes`` (held-out pushes
            per shape that choose the widening), ``library`` (false: leave ``pushtorch_library`` out),
            ``residual`` (true: the pooled model's residual model too, ``pushtorch_residual``, with
            ``residual_ensemble`` rollouts per prediction).
        model_cfg: ``friction``, ``mass`` (the training prior's names), ``training_objects``, ``training_pushes``
            (default: as many as the paper model's), ``samples_per_action`` (the paper model's).

    Returns:
        The records (``task: "transfer"``, both metrics) and extras: ``thrown``, ``hacc_samples`` and
        ``transfer`` (the coverage band the checks use, the transfer objects, the widening chosen).
    """
    part, model_cfg = plain(part), plain(model_cfg)
    name = str(part.get("name", "shape_transfer"))
    objects = load_test_objects(cfg, as_names(part["objects"])) + held_out_shapes(int(part.get("held_out", 0)))
    test_names = {o.name for o in objects}
    shapes = _training_shapes(model_cfg, test_names)
    friction, mass = str(model_cfg["friction"]), str(model_cfg["mass"])
    actions = int(ctx.actions.shape[0])
    training_of = {str(k): str(v) for k, v in (part.get("training_object_of") or {}).items()}
    paper_names = sorted(set(training_of.values()))
    if not paper_names:
        raise InvalidParameterError("shape_transfer needs training_object_of: the paper model's training objects")
    # by default the pooled model gets as many pushes as the paper's model: the same budget, spread
    budget = model_cfg.get("training_pushes") or len(paper_names) * ctx.samples_per_action * actions
    per_action = max(1, round(int(budget) / (len(shapes) * actions)))
    shape_ctx = replace(ctx, samples_per_action=per_action)
    groups = {g: v for g, v in GROUPS.items() if g != "library" or part.get("library", True)}
    conditions = prior_pairs(part["conditions"], "shape_transfer's conditions")
    samples = int(part["truth_samples"])

    pooled = train_pooled(shape_ctx, shapes, friction, mass, int(part.get("widening_pushes", 6)))
    residual = None
    if part.get("residual"):  # pushtorch_residual: the pooled model's residual model, widened across the shapes
        residual = train_pooled_residual(shape_ctx, shapes, friction, mass, int(part.get("widening_pushes", 6)),
                                         int(part.get("residual_ensemble") or DEFAULT_ENSEMBLE))
    library = [train_model(shape_ctx, s, friction, mass) for s in shapes] if "library" in groups else []
    paper = {t: train_model(ctx, load_object(t), friction, mass) for t in paper_names}
    friction_prior, mass_prior = ctx.prior("friction", friction), ctx.prior("mass", mass)
    physics = (mass_prior.mean, friction_prior.mean)
    ensemble = (friction_prior, mass_prior, int(part.get("ensemble", 32)))

    records: list[dict] = []
    thrown: list[dict] = []
    hacc_samples: list[dict] = []
    total = len(objects) * len(groups) * int(part["test_conditions"]) * actions
    bar = progress_bar(ctx, total, f"{name}: predictions")
    for obj in objects:
        poses = sample_test_poses(obj, int(part["test_conditions"]), part["yaw_range_deg"],
                                  stable_seed(ctx.seed, "poses", obj.name))
        seed_key = f"{name}_{obj.name}"
        truth_key = truth_fingerprint(ctx, conditions, samples, seed_key)
        for group, (ours, baselines) in groups.items():
            if group == "shapes":
                candidates, adaptive, label = [pooled], False, "shapes"
            elif group == "library":
                candidates, adaptive, label = library, True, "library"
            elif obj.name in training_of:
                candidates, adaptive, label = [paper[training_of[obj.name]]], False, "+".join(paper_names)
            else:
                candidates, adaptive, label = [paper[t] for t in paper_names], True, "+".join(paper_names)
            key = f"{name}_{obj.name}_{group}"
            predictions, examples = predict_set(
                shape_ctx if group != "paper" else ctx, key, obj, candidates, poses, truth=truth_key,
                adaptive=adaptive, physics=physics if group == "shapes" else None,
                ensemble=ensemble if group == "shapes" else None, seed_key=seed_key, bar=bar,
                residual={pooled.name: residual} if group == "shapes" and residual is not None else None,
                examples=ctx.log_examples if group == "shapes" else None)  # the pooled model's, and its residual's
            truth, broken = simulate_truth(ctx, key, obj, predictions, conditions, samples, seed_key=seed_key)
            scores = likelihood_scores(ctx, key, obj, predictions, truth, truth_key)
            methods = predictions.methods()
            for c, (cf, cm) in enumerate(conditions):
                condition = f"friction:{cf}" if len(set(m for _, m in conditions)) == 1 else f"friction:{cf},mass:{cm}"
                thrown.append({"part": name, "object": obj.name, "method": ours, "model": label, "condition": condition,
                               "thrown": int(broken[c].sum()), "pushes": broken[c].numel(),
                               "invalid_starts": predictions.invalid_starts if c == 0 else 0,
                               "starts": predictions.backoff.numel() if c == 0 else 0})
                shown_methods = ("pushtorch", *baselines, *(("pushtorch_residual",) if "pushtorch_residual" in methods
                                                             else ()))
                for method in shown_methods:
                    start, final = methods[method]
                    acc = compare_displacement(start, final, predictions.truth_initial, truth.take(c), obj)
                    inside = scores.get(f"coverage:{method}")
                    shown = ours if method == "pushtorch" else method
                    records.append(summarise("transfer", obj.name, shown, acc, label, condition,
                                             metric="displacement", nll=scores[method][c],
                                             coverage=None if inside is None else inside[c]))
                    hacc_samples.append(sample_entry(records[-1], acc.hacc.reshape(-1, samples)))
                    records.append(summarise("transfer", obj.name, shown, compare(final, truth.take(c), obj),
                                             label, condition, metric="frame"))
            if examples:
                log_examples(ctx, entity_label(name, obj.name, ours), obj, examples, predictions, truth.take(0),
                             nll=scores["pushtorch"][0])
    bar.close()
    band = [float(v) for v in part.get("coverage_band", [0.80, 0.97])]
    transfer = {"coverage_band": band, "transfer_objects": as_names(part.get("transfer_objects") or []),
                "held_out": [o.name for o in objects if o.name not in catalogue_names()],
                "widening": pooled.meta.get("widening", {}).get("chosen"), "training_shapes": len(shapes),
                "training_pushes_per_action_and_shape": per_action}
    return records, {"thrown": thrown, "hacc_samples": hacc_samples, "transfer": transfer}


def run(cfg, out_dir, overrides=()) -> dict:
    """``python -m pushtorch experiment=shape_transfer`` with its report."""
    return run_suite(cfg, out_dir, [("shape_transfer", cfg.experiment, cfg.model)], overrides)
