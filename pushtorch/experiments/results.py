"""An experiment's results: ``results.json`` and its records, the paper's own numbers beside ours, the
acceptance checks (paper, Experimental Results).

Paper, Experimental Results: the report lays our numbers out as the paper's figures do (selection:
Fig. adaptive_results; pose: Fig. position_accuracy_results; biasing: the friction and mass results
figures, per model and test condition; per object: Fig. object_results, matched model and condition;
training pushes: the training-distribution figures) and puts the paper's own numbers beside ours where
it gives them (its figures carry no values; its text gives the linear errors below).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pushtorch.experiments.online_report import online_checks
from pushtorch.experiments.statistics import equivalence_margin, pool
from pushtorch.experiments.tables import ordered, select

__all__ = [
    "METHOD_ORDER",
    "PAPER_LINEAR_CM",
    "PAPER_POSE_LINEAR_CM",
    "POSE_ORDER",
    "SELECTION_ORDER",
    "acceptance_checks",
    "bias_of",
    "engines",
    "thrown_counts",
    "write_results",
]


#: The paper's raw linear prediction errors per object (cm), matched model and condition (§Results).
PAPER_LINEAR_CM = {
    "cube": 1.68, "prism_thin": 1.97, "prism_long": 2.86,
    "cylinder": 4.04, "cylinder_wide": 8.14, "hybrid": 3.96,
}


#: The paper's mean linear pose errors (cm) over the cube, cylinder and modified cube (§Pose Estimation).
PAPER_POSE_LINEAR_CM = {"position_model": 1.41, "centroid": 7.06}


#: The prediction task's predictors in tables and figures, in this order (others follow as first seen).
METHOD_ORDER = ("pushtorch", "pushtorch_residual", "no_motion", "mean_motion", "nearest_push", "physics_from_cloud",
                "physics_ensemble", "oracle_physics", "nominal_physics")


#: The model-selection methods in tables and figures, in this order.
SELECTION_ORDER = ("congruent", "incongruent", "adaptive")


#: The pose estimators in tables and figures, in this order.
POSE_ORDER = ("position_model", "centroid")


def bias_of(label: str | None) -> str:
    """The biased parameter of a biasing record's model or condition label: ``"friction"`` of
    ``"friction:low"`` (:func:`pushtorch.experiments.biasing.prior_label`); ``""`` for None."""
    return (label or "").split(":", 1)[0]


def acceptance_checks(records: Sequence[Mapping[str, Any]],
                      thrown: Iterable[Mapping[str, Any]] = ()) -> list[dict[str, Any]]:
    """The acceptance checks on whatever tasks the records hold: what the software claims, each sized so that
    noise cannot decide it (docs/experiments.md, "Claims and findings"). Research questions (shape transfer's)
    are findings of their own report section, never checks.

    * prediction: on every object, our H_acc (pooled over models and conditions) is below no-motion's;
    * pose: on every object, the position model's mean H_acc is below the centroid's;
    * selection: on every object, adaptive matches congruent (:func:`matches`, both ways);
    * online: at the largest ``k``, online is no worse than congruent beyond the margin
      (:func:`~pushtorch.experiments.online_report.online_checks`);
    * thrown (``thrown``: the runs' thrown-push entries): no ground-truth push of a part and method other
      than the deliberately mismatched ``incongruent`` tipped or threw the object.
    """
    checks = []
    for obj in ordered(r["object"] for r in select(records, task="prediction")):
        ours = pool(select(records, task="prediction", object=obj, method="pushtorch"))
        still = pool(select(records, task="prediction", object=obj, method="no_motion"))
        checks.append({"check": "pushtorch beats no-motion", "object": obj,
                       "passed": ours["hacc_mean"] < still["hacc_mean"],
                       "detail": f"H_acc {ours['hacc_mean']:.3f} vs {still['hacc_mean']:.3f}"})
    for obj in ordered(r["object"] for r in select(records, task="pose")):
        ours = pool(select(records, task="pose", object=obj, method="position_model"))
        centroid = pool(select(records, task="pose", object=obj, method="centroid"))
        checks.append({"check": "position model beats centroid", "object": obj,
                       "passed": ours["hacc_mean"] < centroid["hacc_mean"],
                       "detail": f"H_acc {ours['hacc_mean']:.3f} vs {centroid['hacc_mean']:.3f}"})
    for obj in ordered(r["object"] for r in select(records, task="selection")):
        adaptive = pool(select(records, task="selection", object=obj, method="adaptive"))
        congruent = pool(select(records, task="selection", object=obj, method="congruent"))
        if adaptive["n"] == 0 or congruent["n"] == 0:
            continue
        se = math.sqrt(adaptive["hacc_std"] ** 2 / adaptive["n"]
                       + congruent["hacc_std"] ** 2 / congruent["n"])
        diff = adaptive["hacc_mean"] - congruent["hacc_mean"]
        margin = equivalence_margin(se, congruent["hacc_mean"])
        checks.append({"check": "adaptive matches congruent", "object": obj,
                       "passed": abs(diff) <= margin,
                       "detail": f"H_acc {adaptive['hacc_mean']:.3f} vs {congruent['hacc_mean']:.3f} "
                                 f"(difference {diff:+.3f}, margin {margin:.3f})"})
    checks += online_checks(records)
    for (part, method), count in thrown_counts(thrown).items():
        if method != "incongruent":
            checks.append({"check": "no ground-truth push thrown", "object": f"{part}: {method}",
                           "passed": count["thrown"] == 0, "detail": f"{count['thrown']} / {count['pushes']}"})
    return checks


def engines(config: Mapping[str, Any]) -> dict[str, dict[str, str]]:
    """``{"world": {"engine": ...}, "physics": {"engine": ...}}`` of a run's config (pybullet where it names
    none): where the training pushes and the ground truth ran, and where the physics peers rolled out."""
    return {which: {"engine": str((config.get(which) or {}).get("engine", "pybullet")).lower()}
            for which in ("world", "physics")}


def write_results(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]], overrides: Sequence[str] = (),
                  model_bandwidths: Mapping[str, Any] | None = None,
                  separability: Sequence[Mapping[str, Any]] = (), tasks: Mapping[str, int] | None = None) -> Path:
    """``results.json`` in the run directory (the layout in the module docstring).

    ``overrides`` are the run's command-line overrides (Hydra's task overrides), so a sweep's jobs can be
    told apart and tabulated by what was swept (``pushtorch-collect``). ``model_bandwidths``: per
    trained model, the bandwidths its search chose (``PushModel.meta["bandwidths"]``). ``separability``: the
    online-adaptation experiment's separability of adjacent test conditions (key ``separability``, when any).
    ``tasks``: ``{"<kind> | <where>": count}`` of the work that ran as tasks (local worker processes or a
    cluster's; key ``tasks``, when any).
    """
    path = Path(out_dir) / "results.json"
    payload = {"experiment": experiment, **engines(config), "config": dict(config), "overrides": list(overrides),
               "wall_s": float(wall_s), "records": list(records),
               "model_bandwidths": dict(model_bandwidths or {})}
    if separability:
        payload["separability"] = list(separability)
    if tasks:
        payload["tasks"] = dict(tasks)
    path.write_text(json.dumps(payload, indent=1, allow_nan=True))
    return path


def thrown_counts(thrown: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], dict[str, int]]:
    """Thrown pushes and invalid starts summed per (part, method), for the checks and report.md's table
    (keys ``thrown``, ``pushes``, ``invalid_starts``, ``starts``): the model-selection entries carry the
    selection method, the biasing entries ``pushtorch`` with the bias in the model label; an entry naming its
    ``part`` (shape transfer) is counted under it."""
    counts: dict[tuple[str, str], dict[str, int]] = {}
    for t in thrown:
        part = t.get("part") or ("model selection" if t.get("model") is None else f"{bias_of(t['model'])} biasing")
        entry = counts.setdefault((part, t["method"]), {"thrown": 0, "pushes": 0, "invalid_starts": 0,
                                                        "starts": 0})
        for key in entry:
            entry[key] += int(t.get(key) or 0)
    return counts
