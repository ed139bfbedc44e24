"""Prediction accuracy on novel contexts under biased and generalising priors (paper, §Prediction Accuracy on
Novel Contexts; §Biasing Transferable Push Manipulation Models).

Paper, Experimental Results (tables friction_biasing_experiment_parameters and
mass_biasing_experiment_parameters, the friction/mass results figures, Fig. object_results): models are
trained on the cube (used for the cube and both prisms) and on the cylinder (used for both cylinders
and the hybrid) under a *general* prior (uniform) and *low*, *medium*, *high* biased priors (narrow
normals) on one physical parameter; every model predicts the same test poses of every test object (with
the same seeds: a paired comparison of the models), and each prediction is compared with ground truths
simulated under the *low*, *medium* and *high* test
conditions ("144 sets of simulated ground truths compared with 48 sets of generated predictions").
Baselines on the same pushes (:mod:`pushtorch.evaluation.baselines`): no motion, the training pushes' mean motion, the
nearest training push, physics on a body reconstructed from the cloud, and oracle physics (the true mesh at
the true pose) — the last two with the training prior's mean mass and friction. Every prediction is scored
on its displacement (H_acc) and by the likelihood of the truth under its density (``nll_mean``).

One module serves both experiments (``experiment=friction_biasing``, ``experiment=mass_biasing``): the
config names the biased parameter (``bias``), the trained priors (``model.friction`` × ``model.mass``,
names in ``priors``) and the test conditions (``conditions.friction`` × ``conditions.mass``). A test
object missing from ``training_object_of`` (e.g. ``object=mesh``) gets the model selected by ``H_r``
among the training objects' models of the same prior.

Run: ``python -m pushtorch experiment=friction_biasing``; one model per job:
``python -m pushtorch experiment=friction_biasing -m model.friction=general,low,medium,high
hydra/launcher=joblib``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
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
    training_records,
    truth_fingerprint,
)
from pushtorch.experiments.statistics import sample_entry
from pushtorch.experiments.suite import run_suite
from pushtorch.experiments.tasks import prefetched
from pushtorch.experiments.training import train_models, train_residual, widen_residuals_by_novelty
from pushtorch.models.residual import DEFAULT_ENSEMBLE
from pushtorch.objects import load_object

__all__ = ["prior_label", "run", "run_part"]


def prior_label(bias: str, friction: str, mass: str) -> str:
    """The name of a (friction, mass) prior pair in results: ``"friction:low"``, ``"mass:high"`` (the biased
    parameter's prior) or ``"friction:a,mass:b"`` when ``bias`` is neither."""
    if bias == "friction":
        return f"friction:{friction}"
    if bias == "mass":
        return f"mass:{mass}"
    return f"friction:{friction},mass:{mass}"


def _plan(cfg, part: Mapping[str, Any], model_cfg: Mapping[str, Any]):
    part, model_cfg = plain(part), plain(model_cfg)
    objects = load_test_objects(cfg, as_names(part["objects"]))
    training_of = {str(k): str(v) for k, v in (part.get("training_object_of") or {}).items()}
    training = sorted(set(training_of.values())) or as_names(part.get("training_objects"))
    if not training:
        raise InvalidParameterError("the biasing experiment needs training_object_of (or training_objects)")
    return (part, objects, training_of, training, prior_pairs(model_cfg, "model"),
            prior_pairs(part["conditions"], "conditions"))


def run_part(cfg, part: Mapping[str, Any], ctx: ExperimentContext,
             model_cfg: Mapping[str, Any]) -> tuple[list[dict], dict]:
    """Train, predict and compare one biasing experiment; return its records and training scatters.

    Args:
        cfg: the whole composed config (``object=...`` replaces the test objects).
        part: keys ``name``, ``bias``, ``objects``, ``training_object_of``, ``conditions``,
            ``test_conditions``, ``truth_samples``, ``yaw_range_deg``; optional ``ensemble`` (the
            ``physics_ensemble`` density peer's rollouts), ``residual`` (true: the ``pushtorch_residual`` model
            too), ``residual_ensemble`` (its rollouts per prediction), ``residual_scale_pushes`` (held-out
            training pushes per action that choose its kernels' scale), ``residual_novelty_pushes`` and
            ``residual_novelty_shapes`` (generated shapes, ``shapes:<kind>:<count>``, whose pushes join the
            choice of the novelty widening and defensive part).
        ctx: the experiment context (model settings of this part).
        model_cfg: ``friction``, ``mass``: the trained priors (a name or a list each; their product).

    Returns:
        Two records (``metric`` displacement and frame) per method (pushtorch and the five baselines),
        object, model and condition; extras
        ``{"training_scatter": {name: {training object: {prior label: [[dx, dy], ...]}}}}``, the action
        index of each of those pushes (``training_actions``, same layout), the thrown pushes, and each
        record's per-comparison H_acc for the figures' intervals (``hacc_samples``, see
        :func:`pushtorch.experiments.statistics.sample_entry`).
    """
    part, objects, training_of, training, model_priors, conditions = _plan(cfg, part, model_cfg)
    name = part.get("name", "biasing")
    bias = str(part.get("bias", "friction"))
    samples = int(part["truth_samples"])
    needed = {training_of[o.name] for o in objects if o.name in training_of}
    if any(o.name not in training_of for o in objects):
        needed |= set(training)
    trained = [(t, f, m) for t in sorted(needed) for f, m in model_priors]
    models = train_models(ctx, trained)
    # the density peers: physics_ensemble (rollouts under the model's training prior) and the residual model
    ensemble_size = part.get("ensemble")
    residuals = None
    if part.get("residual"):
        size = int(part.get("residual_ensemble") or DEFAULT_ENSEMBLE)
        scale_pushes = part.get("residual_scale_pushes")
        fitted = {tfm: train_residual(ctx, load_object(tfm[0]), *tfm[1:], size, scale_pushes) for tfm in trained}
        if int(part.get("residual_novelty_pushes", 0)) > 0:  # each model's hedges on the other training objects
            fitted = widen_residuals_by_novelty(ctx, fitted, int(part["residual_novelty_pushes"]),
                                                part.get("residual_novelty_shapes"))
        residuals = {models[tfm].name: fitted[tfm] for tfm in trained}
    records: list[dict] = []
    thrown: list[dict] = []
    hacc_samples: list[dict] = []
    per_group = int(part["test_conditions"]) * int(ctx.actions.shape[0])
    bar = progress_bar(ctx, len(objects) * len(model_priors) * per_group, f"{name}: predictions")
    groups = []
    for obj in objects:
        poses = sample_test_poses(obj, int(part["test_conditions"]), part["yaw_range_deg"],
                                  stable_seed(ctx.seed, "poses", obj.name))
        for k, (f, m) in enumerate(model_priors):
            if obj.name in training_of:
                candidates, adaptive = [models[(training_of[obj.name], f, m)]], False
            else:
                candidates, adaptive = [models[(t, f, m)] for t in training], True
            groups.append((obj, poses, k, f, m, candidates, adaptive))

    def scored(group_ctx: ExperimentContext, group: tuple, group_bar=None, log: bool = False):
        """One object and model prior: predictions (with the peers), ground truth and scores, each cached."""
        obj, poses, k, f, m, candidates, adaptive = group
        key = f"{name}_{obj.name}_{f}_{m}"
        physics = (group_ctx.prior("mass", m).mean, group_ctx.prior("friction", f).mean)
        truth_key = truth_fingerprint(group_ctx, conditions, samples, f"{name}_{obj.name}")
        ensemble = None if not ensemble_size else (group_ctx.prior("friction", f), group_ctx.prior("mass", m),
                                                   int(ensemble_size))
        predictions, examples = predict_set(
            group_ctx, key, obj, candidates, poses, truth=truth_key, adaptive=adaptive, physics=physics,
            ensemble=ensemble, residual=residuals,
            seed_key=f"{name}_{obj.name}", bar=group_bar,
            examples=group_ctx.log_examples if (log or group_ctx.keep_examples) and k == 0 else None,
        )
        truth, broken = simulate_truth(group_ctx, key, obj, predictions, conditions, samples,
                                       seed_key=f"{name}_{obj.name}")
        return predictions, examples, truth, broken, likelihood_scores(group_ctx, key, obj, predictions, truth,
                                                                       truth_key)

    # every group in worker processes, where there are cores to spare: the loop below reads each group's caches
    # as soon as its task ended, while the later ones run
    ahead = prefetched(ctx, scored, groups, on_done=lambda _: bar.update(per_group),
                       warm=next(iter(models.values())), what="groups predicted, pushed and scored")
    scatter: dict[str, dict[str, list]] = {}
    scatter_actions: dict[str, dict[str, list]] = {}  # the figures draw one row of panels per action
    for t in sorted(needed):
        for f, m in model_priors:
            pushes = training_records(ctx, load_object(t), f, m, progress=False)  # cached by train_model
            motion = pushes.object_final.p[:, :2] - pushes.object_initial.p[:, :2]
            scatter.setdefault(t, {})[prior_label(bias, f, m)] = motion.tolist()
            scatter_actions.setdefault(t, {})[prior_label(bias, f, m)] = pushes.action_index.tolist()
    for group, done in ahead:
        obj, _, _, f, m, _, _ = group
        model_name = prior_label(bias, f, m)
        predictions, examples, truth, broken, nll = scored(ctx, group, None if done else bar, log=True)
        for c, (cf, cm) in enumerate(conditions):
            condition = prior_label(bias, cf, cm)
            thrown.append({"object": obj.name, "method": "pushtorch", "model": model_name,
                           "condition": condition, "thrown": int(broken[c].sum()),
                           "pushes": broken[c].numel(),
                           # the starts are the conditions': counted once, not once per truth condition
                           "invalid_starts": predictions.invalid_starts if c == 0 else 0,
                           "starts": predictions.backoff.numel() if c == 0 else 0})
            # every method predicts the displacement from its own start pose: the estimate, the
            # reconstructed body (physics from the cloud) or the true pose (the oracle)
            for method, (start, final) in predictions.methods().items():
                acc = compare_displacement(start, final, predictions.truth_initial, truth.take(c), obj)
                inside = nll.get(f"coverage:{method}")
                records.append(summarise("prediction", obj.name, method, acc, model_name, condition,
                                         metric="displacement", nll=nll[method][c],
                                         coverage=None if inside is None else inside[c]))
                hacc_samples.append(sample_entry(records[-1], acc.hacc.reshape(-1, samples)))
                records.append(summarise("prediction", obj.name, method, compare(final, truth.take(c), obj),
                                         model_name, condition, metric="frame"))
        if examples:
            label = entity_label(name, obj.name, model_name)
            log_examples(ctx, label, obj, examples, predictions, truth.take(0),
                         nll=nll["pushtorch"][0])
    bar.close()
    return records, {"training_scatter": {name: scatter}, "training_actions": {name: scatter_actions},
                     "thrown": thrown, "hacc_samples": hacc_samples}


def run(cfg, out_dir: Path, overrides: Sequence[str] = ()) -> dict:
    """``python -m pushtorch experiment=friction_biasing`` (or ``mass_biasing``) with its report.

    Returns the summary :func:`pushtorch.experiments.suite.run_suite` gives.
    """
    return run_suite(cfg, out_dir, [("biasing", cfg.experiment, cfg.model)], overrides)
