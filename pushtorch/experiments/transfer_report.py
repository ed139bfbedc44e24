"""The shape-transfer experiment's part of the outputs: its research questions answered as findings (never
acceptance checks: "does the pooled model beat the two-object one" is a question, not a promise of the
software), its report section and the calibration figure (predicted against observed coverage) (paper, §Test
Set and §Prediction Accuracy on Novel Contexts for the protocol; §Conclusion's transfer by local contact models
for the thesis tested).
:mod:`pushtorch.experiments.shape_transfer` makes the records (``task: "transfer"``); this module only reads them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from pushtorch.experiments.statistics import pool
from pushtorch.experiments.tables import method_label, ordered, primary, select, table

__all__ = ["TRANSFER_ORDER", "coverage_figure", "transfer_findings", "transfer_section"]

#: The methods' order in tables and figures.
TRANSFER_ORDER = ("pushtorch_shapes", "pushtorch_residual", "pushtorch_library", "pushtorch", "mean_motion",
                  "nearest_push", "physics_from_cloud", "physics_ensemble", "oracle_physics")
#: Methods with a density of their own (coverage is theirs only).
DENSITY_METHODS = ("pushtorch_shapes", "pushtorch_residual", "pushtorch_library", "pushtorch", "mean_motion",
                   "physics_ensemble")


def _transfer(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The primary (displacement) records of the transfer task."""
    return select(primary(records), task="transfer")


def _pooled(records: Iterable[Mapping[str, Any]], **keys: Any) -> dict[str, float]:
    return pool(select(records, **keys))


def transfer_findings(records: Sequence[Mapping[str, Any]], info: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    """The experiment's research questions and their measured answers, pooled over test conditions (each
    ``{"question", "object", "held", "detail"}``; report.md's "Research questions" table, results.json's
    ``findings``):

    * on every transfer object, ``pushtorch_shapes``'s H_acc ≤ ``pushtorch``'s + 2 standard errors of their
      difference;
    * on every catalogue object, ``pushtorch_shapes``'s nll below the ``mean_motion`` of its own training pushes;
    * on every catalogue object, ``pushtorch_shapes``'s 90 % coverage inside the run's ``coverage_band``;
    * on at least 75 % of the held-out shapes, ``pushtorch_shapes`` beats that ``mean_motion`` on H_acc.
    """
    transfer = _transfer(records)
    if not transfer or info is None:
        return []
    findings = []
    held_out = set(info.get("held_out") or [])
    objects = ordered(r["object"] for r in transfer)
    for obj in [o for o in objects if o in set(info.get("transfer_objects") or [])]:
        ours, paper = _pooled(transfer, object=obj, method="pushtorch_shapes"), _pooled(
            transfer, object=obj, method="pushtorch")
        if ours["n"] == 0 or paper["n"] == 0:
            continue
        se = math.sqrt(ours["hacc_std"] ** 2 / ours["n"] + paper["hacc_std"] ** 2 / paper["n"])
        diff = ours["hacc_mean"] - paper["hacc_mean"]
        findings.append({"question": "pushtorch_shapes within 2 SE of pushtorch or better", "object": obj,
                         "held": diff <= 2 * se + 1e-9,
                         "detail": f"H_acc {ours['hacc_mean']:.3f} vs {paper['hacc_mean']:.3f} (difference "
                                   f"{diff:+.3f}, 2 SE {2 * se:.3f})"})
    low, high = (info.get("coverage_band") or [0.80, 0.97])[:2]
    for obj in [o for o in objects if o not in held_out]:
        ours = _pooled(transfer, object=obj, method="pushtorch_shapes")
        mean = _pooled(transfer, object=obj, method="mean_motion", model="shapes")
        if ours["n"] and mean["n"]:
            findings.append({"question": "pushtorch_shapes nll below its mean_motion's", "object": obj,
                             "held": ours["nll_mean"] < mean["nll_mean"],
                             "detail": f"nll {ours['nll_mean']:.1f} vs {mean['nll_mean']:.1f}"})
        if ours["n"] and not math.isnan(ours["coverage_90"]):
            findings.append({"question": f"pushtorch_shapes 90 % coverage in [{low:.2f}, {high:.2f}]",
                             "object": obj, "held": low <= ours["coverage_90"] <= high,
                             "detail": f"coverage_90 {ours['coverage_90']:.2f}, coverage_50 "
                                       f"{ours['coverage_50']:.2f} (n {ours['n']})"})
    shapes = [o for o in objects if o in held_out]
    if shapes:
        wins = sum(_pooled(transfer, object=o, method="pushtorch_shapes")["hacc_mean"]
                   < _pooled(transfer, object=o, method="mean_motion", model="shapes")["hacc_mean"] for o in shapes)
        findings.append({"question": "pushtorch_shapes beats its mean_motion on >= 75 % of held-out shapes",
                         "object": f"{len(shapes)} held-out shapes", "held": wins >= 0.75 * len(shapes),
                         "detail": f"{wins} / {len(shapes)}"})
    return findings


def _number(value: float, digits: int) -> str:
    return "—" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def transfer_section(records: Sequence[Mapping[str, Any]], info: Mapping[str, Any] | None,
                     figure_names: set[str]) -> list[str]:
    """report.md's shape-transfer section: H_acc, nll and coverage per object and method."""
    transfer = _transfer(records)
    if not transfer:
        return []
    info = info or {}
    objects = ordered(r["object"] for r in transfer)
    methods = ordered((r["method"] for r in transfer), TRANSFER_ORDER)
    lines = ["## Transfer from many shapes", "",
             f"One model pooled over {info.get('training_shapes', '?')} generated shapes "
             f"({info.get('training_pushes_per_action_and_shape', '?')} training pushes per action and shape), "
             "the same shapes' per-shape models chosen by H_r, and the paper's two-object model; every test "
             "object is new to the pooled model. `mean_motion` and `nearest_push` are the pooled training set's. "
             f"Widening chosen across training shapes: {info.get('widening')}. Cells: H_acc mean ± std "
             "(displacement), pooled over the test conditions.", ""]
    rows = []
    for obj in objects:
        row = [obj]
        for m in methods:
            st = _pooled(transfer, object=obj, method=m, **({"model": "shapes"} if m in (
                "mean_motion", "nearest_push") else {}))
            row.append("—" if st["n"] == 0 else f"{st['hacc_mean']:.3f} ± {st['hacc_std']:.3f}")
        rows.append(row + [_pooled(transfer, object=obj, method=methods[0])["n"]])
    lines += table(["object"] + [method_label(m) for m in methods] + ["n"], rows)
    dense = [m for m in methods if m in DENSITY_METHODS]
    lines += ["Density scores per object: nll (nats, lower is better) and the share of true outcomes inside the "
              "predicted density's 50 % and 90 % highest-density regions (a calibrated density has 0.50 and "
              "0.90; docs/method.md, \"Likelihood score\").", ""]
    rows = []
    for obj in objects:
        row = [obj]
        for m in dense:
            st = _pooled(transfer, object=obj, method=m, **({"model": "shapes"} if m == "mean_motion" else {}))
            row.append("—" if st["n"] == 0 else f"{_number(st['nll_mean'], 1)} / {_number(st['coverage_50'], 2)}"
                                                 f" / {_number(st['coverage_90'], 2)}")
        rows.append(row)
    lines += table(["object"] + [f"{m}: nll / cov50 / cov90" for m in dense], rows)
    paper_mean = [r for r in transfer if r["method"] == "mean_motion" and r.get("model") != "shapes"]
    if paper_mean:
        rows = [[obj, _number(_pooled(paper_mean, object=obj)["hacc_mean"], 3),
                 _number(_pooled(transfer, object=obj, method="nearest_push",
                                 model=paper_mean[0]["model"])["hacc_mean"], 3)] for obj in objects]
        lines += [f"The two-object training set's own baselines ({paper_mean[0]['model']}): H_acc.", ""]
        lines += table(["object", "mean_motion", "nearest_push"], rows)
    if "coverage.png" in figure_names:
        lines += ["![predicted against observed coverage](figures/coverage.png)", ""]
    findings = transfer_findings(records, info)
    if findings:
        lines += ["### Research questions", "",
                  "What this run measured of the open questions about transfer from many shapes: findings with "
                  "their answers, not checks of the software (a question not held is a result, not a failure).", ""]
        lines += table(["question", "object", "held", "measured"],
                       [(f["question"], f["object"], "yes" if f["held"] else "no", f["detail"]) for f in findings])
    return lines


def coverage_figure(plt, records: Sequence[Mapping[str, Any]]):
    """Predicted against observed coverage of every method with a density, pooled over objects and conditions
    (one mark per method and level; the diagonal is calibration), or None without coverage records."""
    from pushtorch.viz.colours import colour_of

    scored = [r for r in records if r.get("metric", "displacement") == "displacement"
              and r.get("coverage_90") is not None and r.get("task") in ("transfer", "prediction")]
    if not scored:
        return None
    fig, ax = plt.subplots(figsize=(4.8, 4.2), layout="constrained")
    ax.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
    for m in ordered((r["method"] for r in scored), TRANSFER_ORDER):
        of_method = [r for r in scored if r["method"] == m]
        # a transfer baseline fit on each training set is drawn once per set
        models = ordered(r.get("model") or "" for r in of_method) if of_method[0]["task"] == "transfer" else [None]
        for model in models:
            group = [r for r in of_method if model is None or (r.get("model") or "") == model]
            n = sum(r["n"] for r in group)
            observed = [sum(r["n"] * r[k] for r in group) / n for k in ("coverage_50", "coverage_90")]
            label = m if len(models) == 1 else f"{m}, {model}"
            ax.plot([0.5, 0.9], observed, marker="o", color=colour_of(label), label=f"{label} (n {n})")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("predicted coverage (region's probability)")
    ax.set_ylabel("observed coverage (share of truths inside)")
    ax.set_title("Calibration of the predicted densities", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    return fig
