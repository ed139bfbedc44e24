"""The prediction app: predict pushes of an object with trained models, checked against the simulator.

Paper, Fig. pipeline (prediction) and Fig. prediction_accuracy_methodology: capture the object's
single-shot cloud, generate the push condition (robot start pose, contact frames, initial-pose estimate)
and predict the final pose for each action (:func:`pushtorch.prediction.forward`); then simulate
``truth_samples`` ground-truth pushes per action from the predicted robot start pose, with mass and
friction drawn from the chosen priors, and measure H_acc. Usage::

    pushtorch-predict 'models=[runs/train_cube/model.npz]' object=prism_long yaw_deg=20
    pushtorch-predict 'models=[cube.npz,cylinder.npz]' object=mesh object.path=part.stl

A residual model's file (:meth:`pushtorch.models.residual.ResidualModel.save`) predicts as a residual model:
its rollouts are kept in ``predictions.json`` and drawn beside its density. (``python -m pushtorch.predict_cli``
is the same app.) Output in the run directory: ``predictions.json``
(each action's H_acc and ``nll``, the negative log-likelihood of each ground truth under the predicted
density, as results.json's), ``resolved_config.yaml`` and ``recording.rrd``: every prediction
(:func:`pushtorch.viz.predictions.log_prediction`, at ``world/model/prediction/action_<j>``, its density's draws
at ``.../density``) with its first ground-truth push playing on ``sim_time``, a markdown summary with each
action's H_acc and nll at ``metrics/summary``, and a blueprint with a tab per action
(:func:`pushtorch.viz.blueprint.predict_blueprint`).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, exit_without_collecting, run_stage
from pushtorch.apps.config_check import check_config
from pushtorch.errors import InvalidParameterError

__all__ = ["main", "predict_from_config"]

log = logging.getLogger("pushtorch.apps.predict")


def _pose_dict(pose) -> dict[str, list[float]]:
    return {"p": [round(v, 6) for v in pose.p.reshape(3).tolist()],
            "q_wxyz": [round(v, 6) for v in pose.q.reshape(4).tolist()]}


def predict_from_config(cfg: Mapping[str, Any] | DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Predict (and check) the pushes a ``conf/predict.yaml``-shaped config describes.

    Args:
        cfg: keys ``models`` (files), ``object``, ``x``, ``y``, ``yaw_deg``, ``actions`` (``all`` or
            indices), ``truth_samples``, ``friction``, ``mass`` (priors), ``sim``, ``duration``, ``seed``,
            ``recording``.
        out_dir: the run directory.

    Returns:
        A summary dict; the full per-action results are in ``out_dir/predictions.json``.

    Raises:
        InvalidParameterError: no model, an action index the model lacks, or a bad setting.
        RecordFormatError: an unreadable model file.
    """
    import torch

    from pushtorch import se3
    from pushtorch.evaluation.metrics import accuracy, displaced
    from pushtorch.experiments.common import as_names, observe, plain, stable_seed
    from pushtorch.models.library import ModelLibrary
    from pushtorch.models.residual_file import load_any_model
    from pushtorch.objects import load_object
    from pushtorch.prediction import predict
    from pushtorch.prediction.residual import ResidualPrediction
    from pushtorch.sim.priors import prior_from_config
    from pushtorch.sim.runner import simulate_pushes
    from pushtorch.sim.settings import settings_from_config

    check_config(cfg, "predict")  # types and bounds first, as the command line does
    c = plain(cfg)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        paths = as_names(c.get("models"))
        obj_cfg = c["object"]
        obj = load_object(obj_cfg["name"], obj_cfg.get("path"), float(obj_cfg.get("scale", 1.0)),
                          up=obj_cfg.get("up", "z"))
        truth_initial = obj.resting_pose(float(c.get("x", 0.0)), float(c.get("y", 0.0)),
                                         math.radians(float(c.get("yaw_deg", 0.0))))
        samples = int(c.get("truth_samples", 3))
        mass_prior, friction_prior = prior_from_config(c["mass"]), prior_from_config(c["friction"])
        sim = settings_from_config(c, "world")
        seed = int(c.get("seed", 0))
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"predict config is missing or mistypes a key: {exc}") from exc
    if not paths:
        raise InvalidParameterError("no model: set models=[<model.npz>, ...]")
    if samples < 0:
        raise InvalidParameterError(f"truth_samples must be >= 0, got {samples}")
    models = [load_any_model(p) for p in paths]
    _, features = observe(obj, truth_initial, models[0].settings)
    chosen, distances = (models[0], None) if len(models) == 1 else ModelLibrary(models).select(features)
    wanted = c.get("actions", "all")
    if wanted in (None, "all"):
        indices = list(range(len(chosen.motions)))
    else:
        indices = [int(i) for i in (wanted if isinstance(wanted, list) else [wanted])]
    for i in indices:
        if not 0 <= i < len(chosen.motions):
            raise InvalidParameterError(
                f"model {chosen.name!r} has actions 0..{len(chosen.motions) - 1}, not {i}"
            )
    rec = None
    if c.get("recording", True):
        from pushtorch.viz.core import open_recording

        rec = open_recording(out_dir / "recording.rrd", "pushtorch_predict")
    results = []
    logged: list[str] = []
    generator = torch.Generator().manual_seed(stable_seed(seed, "truth"))
    try:
        for i in indices:
            action = chosen.motions[i].action
            generator_i = torch.Generator().manual_seed(stable_seed(seed, i))
            prediction = predict(chosen, features, action, generator_i, record_history=rec is not None)
            entry: dict[str, Any] = {
                "action_index": i, "action": action.tolist(), "model": chosen.name,
                "robot_start": _pose_dict(prediction.condition.robot_start),
                "initial_estimate": _pose_dict(prediction.condition.object_pose),
                "final_predicted": _pose_dict(prediction.final_pose),
                "initial_estimate_accuracy": _accuracy_dict(accuracy(prediction.condition.object_pose,
                                                                     truth_initial, obj)),
            }
            truth_final = records = None
            if samples:
                records = simulate_pushes(
                    obj, prediction.condition.robot_start, truth_initial.expand(samples), action,
                    mass_prior.sample((samples,), generator), friction_prior.sample((samples,), generator),
                    sim, duration=float(c.get("duration", 4.0)),
                )
                finals = se3.Pose.unchecked(records.object_final.p.float(), records.object_final.q.float())
                if isinstance(prediction, ResidualPrediction):  # its body's frame is not the object's
                    moved = displaced(prediction.start, prediction.final_pose, truth_initial)
                else:
                    moved = prediction.final_pose
                acc = accuracy(moved.expand(samples), finals, obj)
                entry["truth_final"] = [_pose_dict(finals.take(k)) for k in range(samples)]
                entry["nll"] = [round(float(v), 4) for v in _nll(prediction, finals, truth_initial, obj,
                                                                   stable_seed(seed, i, "likelihood"))]
                entry["touched"] = records.touched.tolist()
                # a ground truth that tipped or left the ground is no fair score for a planar prediction
                entry["tipped_or_left_ground"] = (records.tipped | records.left_ground).tolist()
                entry["accuracy"] = _accuracy_dict(acc)
                truth_final = finals.take(0)
            if isinstance(prediction, ResidualPrediction):
                entry["rollouts"] = [_pose_dict(prediction.rollouts.take(k)) for k in range(len(prediction.physics))]
                entry["rollout_physics"] = [[round(v, 6) for v in row] for row in prediction.physics.tolist()]
                entry["rollouts_thrown"] = prediction.thrown
            results.append(entry)
            if rec is not None:
                from pushtorch.viz.predictions import log_prediction

                logged.append(log_prediction(rec, prediction, truth_initial, truth_final, obj,
                                             label=f"action_{i}", cloud=features, truth_push=records))
    finally:
        if rec is not None:
            from pushtorch.viz.blueprint import predict_blueprint
            from pushtorch.viz.scores import SUMMARY, log_markdown

            log_markdown(rec, SUMMARY, _summary_markdown(obj.name, chosen.name, paths, distances, results))
            rec.send_blueprint(predict_blueprint(logged, summary=SUMMARY))
            rec.disconnect()  # completes the file
    payload = {
        "object": obj.name, "truth_initial": _pose_dict(truth_initial), "models": paths,
        "selected": chosen.name,
        "feature_distances": None if distances is None else dict(zip([m.name for m in models],
                                                                     distances.tolist(), strict=True)),
        "predictions": results,
    }
    (out_dir / "predictions.json").write_text(json.dumps(payload, indent=1))
    summary: dict[str, Any] = {"object": obj.name, "model": chosen.name, "predictions": len(results),
                               "results": str(out_dir / "predictions.json")}
    if samples:
        summary["hacc_mean"] = round(sum(r["accuracy"]["hacc_mean"] for r in results) / len(results), 4)
    if rec is not None:
        summary["recording"] = str(out_dir / "recording.rrd")
    return summary


def _nll(prediction, finals, truth_initial, obj, seed: int):
    """Negative log-likelihoods (nats) of the true final poses ``(S,)`` under the prediction's density, in the
    displacement sense, nearest symmetric copy: the score of results.json's ``nll_mean``
    (:func:`pushtorch.evaluation.likelihood.nll`; its normaliser drawn from a generator seeded with ``seed``)."""
    import torch

    from pushtorch.evaluation.likelihood import motion_product_density, nll
    from pushtorch.prediction.residual import ResidualPrediction

    if isinstance(prediction, ResidualPrediction):  # a normalised mixture over its body's final pose
        return nll(prediction.density, finals, truth_initial, prediction.start, obj.symmetry)
    density = motion_product_density(prediction.motion_density, torch.Generator().manual_seed(seed),
                                     prediction.candidates)
    return nll(density, finals, truth_initial, prediction.condition.object_pose, obj.symmetry)


def _summary_markdown(object_name: str, model: str, paths: list[str], distances, results: list[dict]) -> str:
    """The recording's summary: what was predicted with which model, and each action's accuracy and nll."""
    lines = [f"# Predicted pushes of {object_name}", "", f"Model: `{model}` (of {len(paths)} given)."]
    if distances is not None:
        lines.append("Feature distances H_r: " + ", ".join(f"{d:.4f}" for d in distances.tolist()) + ".")
    lines += ["", "| action | (ẋ m/s, θ̇ rad/s) | H_acc (frame) | nll (nats) | linear cm | angular deg | touched |",
              "|---:|---|---:|---:|---:|---:|---|"]
    for entry in results:
        acc = entry.get("accuracy")
        nll = entry.get("nll")
        numbers = (f"{acc['hacc_mean']:.3f} | {sum(nll) / len(nll):.2f} | {acc['linear_cm']:.2f} | "
                   f"{acc['angular_deg']:.1f}" if acc else "– | – | – | –")
        action = ", ".join(f"{v:.3f}" for v in entry["action"])
        lines.append(f"| {entry['action_index']} | ({action}) | {numbers} | {entry.get('touched', '–')} |")
    lines += ["", "Means over the ground-truth samples. H_acc: the predicted final pose against the true one as it "
              "is (in the frame the model estimated; a residual model's: the displacement its cloud body's rollouts "
              "predict, applied to the true start, its rollouts at `.../rollouts`). nll: the negative "
              "log-likelihood of the true final pose "
              "under the predicted density, the true motion applied to the estimated start (displacement "
              "sense, nearest symmetric copy; `pushtorch.evaluation.likelihood.nll`, the score of results.json's "
              "`nll_mean`).",
              "", "Ground truth: the first sample of each action plays on `sim_time` at "
              "`world/model/prediction/action_<j>/truth_push`; the predicted density is drawn at "
              "`world/model/prediction/action_<j>/density` (draws, 90 % region, mode, the truth)."]
    return "\n".join(lines) + "\n"


def _accuracy_dict(acc) -> dict[str, float]:
    return {"hacc_mean": float(acc.hacc.mean()), "linear_cm": float(acc.linear_cm.mean()),
            "angular_deg": float(acc.angular_deg.mean())}


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="predict")
def _app(cfg: DictConfig) -> dict[str, Any]:
    return run_stage("pushtorch-predict", cfg, predict_from_config)


def main() -> None:
    """Entry point of ``pushtorch-predict`` (a user error exits with status 2 and one line)."""
    compose_or_exit("pushtorch-predict", "predict")
    _app()
    exit_without_collecting()


if __name__ == "__main__":
    main()
