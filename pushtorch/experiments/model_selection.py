"""Model selection: congruent, incongruent and adaptive contact and motion models (paper, §Model Selection).

Paper, Experimental Results, Contact Model Selection (table adaptive_model_experiment_parameters,
Fig. adaptive_results): models are trained on the cube and on the cylinder; each is tested on the cube
and the cylinder with the model of its own shape (*congruent*), of the other shape (*incongruent*), or
the one the system selects by the lowest surface-feature distance ``H_r`` (*adaptive*, paper, Model
Selection). Every method sees the same test poses and predicts each of them with the same seeds (common
random numbers: a method that picks the congruent model gives the congruent prediction), so the methods
differ only by the model they apply. The ground truth of each push condition is simulated
``truth_samples`` times per action. ``selection_rate`` is the share of predictions made with the
congruent model.

Decision: the paper's "Object Coefficient of Friction U(0.15, 0.35)" is sampled as our effective
object-ground coefficient (the simulator has one sampled friction per push).

Run: ``python -m pushtorch experiment=model_selection`` (sizes: ``experiment.test_conditions=...``).
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
    log_examples,
    plain,
    predict_set,
    progress_bar,
    sample_test_poses,
    simulate_truth,
    stable_seed,
    summarise,
    truth_fingerprint,
)
from pushtorch.experiments.statistics import sample_entry
from pushtorch.experiments.suite import run_suite
from pushtorch.experiments.tasks import prefetched
from pushtorch.experiments.training import train_models
from pushtorch.objects import load_object

__all__ = ["METHODS", "run", "run_part"]

METHODS = ("congruent", "incongruent", "adaptive")


def _single(model_cfg: Mapping[str, Any], kind: str) -> str:
    names = as_names(model_cfg.get(kind))
    if len(names) != 1:
        raise InvalidParameterError(f"model selection trains one {kind} prior, not model.{kind}={names}")
    return names[0]


def run_part(cfg, part: Mapping[str, Any], ctx: ExperimentContext,
             model_cfg: Mapping[str, Any]) -> tuple[list[dict], dict]:
    """Run the selection experiment described by ``part`` (the ``experiment`` node); return its records.

    Args:
        cfg: the whole composed config (unused here: the test objects are the training objects).
        part: keys ``name``, ``objects``, ``training_objects``, ``methods``, ``test_conditions``,
            ``truth_samples``, ``yaw_range_deg``, ``condition`` (``{friction, mass}`` names of the
            ground truth's priors).
        ctx: the experiment context (model settings of this part).
        model_cfg: the part's ``model`` config (``friction``, ``mass``: one training prior each).

    Raises:
        InvalidParameterError: a test object that is not a training object, or an unknown method.
    """
    part = plain(part)
    name = part.get("name", "model_selection")
    training = as_names(part["training_objects"])
    objects = as_names(part.get("objects", training))
    methods = as_names(part.get("methods", METHODS))
    for method in methods:
        if method not in METHODS:
            raise InvalidParameterError(f"unknown selection method {method!r}; use {', '.join(METHODS)}")
    for obj_name in objects:
        if obj_name not in training:
            raise InvalidParameterError(
                f"model selection tests the training objects ({', '.join(training)}), not {obj_name!r}"
            )
    if len(training) < 2 and "incongruent" in methods:
        raise InvalidParameterError("the incongruent method needs at least two training objects")
    friction, mass = _single(model_cfg, "friction"), _single(model_cfg, "mass")
    trained = train_models(ctx, [(t, friction, mass) for t in training])
    models = [trained[(t, friction, mass)] for t in training]
    condition = (str(part["condition"]["friction"]), str(part["condition"]["mass"]))
    samples = int(part["truth_samples"])
    records: list[dict] = []
    thrown: list[dict] = []
    hacc_samples: list[dict] = []  # per-comparison H_acc of each record, for the figures' intervals
    per_object = len(methods) * int(part["test_conditions"]) * int(ctx.actions.shape[0])
    bar = progress_bar(ctx, len(objects) * per_object, f"{name}: predictions")

    def scored(obj_ctx: ExperimentContext, obj_name: str, obj_bar=None, log: bool = False):
        """Every method's predictions of one object, ground truth and scores (each cached)."""
        obj = load_object(obj_name)
        poses = sample_test_poses(obj, int(part["test_conditions"]), part["yaw_range_deg"],
                                  stable_seed(obj_ctx.seed, "poses", obj.name))
        congruent = training.index(obj_name)
        others = [k for k in range(len(models)) if k != congruent]
        choices = {"congruent": lambda i, c=congruent: c,
                   "incongruent": lambda i, o=tuple(others): o[i % len(o)], "adaptive": None}
        memo: dict = {}  # every method predicts a condition with the same seeds: a model's answer is shared
        out = []
        for method in methods:
            key = f"{name}_{obj_name}_{method}"
            truth_key = truth_fingerprint(obj_ctx, [condition], samples, f"{name}_{obj_name}")
            predictions, examples = predict_set(
                obj_ctx, key, obj, models, poses, truth=truth_key, adaptive=method == "adaptive",
                choose=choices[method], seed_key=f"{name}_{obj_name}", memo=memo, bar=obj_bar,
                examples=obj_ctx.log_examples if (log or obj_ctx.keep_examples) and method == "adaptive" else None,
            )
            truth, broken = simulate_truth(obj_ctx, key, obj, predictions, [condition], samples,
                                           seed_key=f"{name}_{obj_name}")
            out.append((method, predictions, examples, truth, broken,
                        likelihood_scores(obj_ctx, key, obj, predictions, truth, truth_key)))
        return obj, congruent, out

    # every object in worker processes, where there are cores to spare: the loop below reads each object's caches
    # as soon as its task ended
    ahead = prefetched(ctx, scored, objects, on_done=lambda _: bar.update(per_object), warm=models[0],
                       what="objects predicted, pushed and scored")
    for obj_name, done in ahead:
        obj, congruent, per_method = scored(ctx, obj_name, None if done else bar, log=True)
        for method, predictions, examples, truth, broken, scores in per_method:
            nll = scores["pushtorch"]
            rate = float((predictions.selected == congruent).double().mean())
            acc = compare_displacement(predictions.estimate, predictions.final, predictions.truth_initial,
                                       truth.take(0), obj)
            records.append(summarise("selection", obj_name, method, acc, selection_rate=rate,
                                     metric="displacement", nll=nll[0], coverage=scores["coverage:pushtorch"][0]))
            hacc_samples.append(sample_entry(records[-1], acc.hacc.reshape(-1, samples)))
            records.append(summarise("selection", obj_name, method, compare(predictions.final, truth.take(0), obj),
                                     selection_rate=rate, metric="frame"))
            thrown.append({"object": obj_name, "method": method, "model": None, "condition": None,
                           "thrown": int(broken.sum()), "pushes": broken.numel(),
                           "invalid_starts": predictions.invalid_starts,
                           "starts": predictions.backoff.numel()})
            if examples:
                label = entity_label(name, obj_name, method)
                log_examples(ctx, label, obj, examples, predictions, truth.take(0), nll=nll[0])
    bar.close()
    return records, {"thrown": thrown, "hacc_samples": hacc_samples}


def run(cfg, out_dir: Path, overrides: Sequence[str] = ()) -> dict:
    """``python -m pushtorch experiment=model_selection``: the experiment alone, with its report."""
    return run_suite(cfg, out_dir, [("model_selection", cfg.experiment, cfg.model)], overrides)
