"""The online-adaptation experiment in the report: its tables, figure and checks (paper, §Conclusions and future
work; :mod:`pushtorch.experiments.online_adaptation`).

* a table per object: H_acc (and nll) of every predictor per test condition and number of observed pushes ``k``;
* the posterior's mean and spread of μ and log m against the truth;
* the separability of adjacent conditions (where the outcomes can tell them apart at all);
* a figure of H_acc against ``k``, a panel per object and condition, a line per predictor;
* the check: at the largest ``k``, ``online`` is within the equivalence margin of ``congruent`` (or better), in
  every condition (:func:`~pushtorch.experiments.statistics.equivalence_margin`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from pushtorch.experiments.statistics import equivalence_margin
from pushtorch.experiments.tables import ordered, select

__all__ = ["ONLINE_ORDER", "online_checks", "online_figure", "online_section"]

#: The predictors in tables and figures, in this order.
ONLINE_ORDER = ("online", "online_general", "general", "debiased", "congruent", "incongruent", "pushtorch_residual",
                "physics_from_cloud", "physics_from_cloud_online")


def _online(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The online-adaptation experiment's records."""
    return select(records, task="online")


def online_checks(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """``online`` ≤ ``congruent`` + the equivalence margin
    (:func:`~pushtorch.experiments.statistics.equivalence_margin`: 3 standard errors of the paired difference,
    or 5 % of congruent's H_acc), at the largest ``k``, per object and condition: conditioning on observed
    pushes must not make the prediction worse than the oracle's choice."""
    online = _online(records)
    if not online:
        return []
    k = max(r["observed"] for r in online)
    checks = []
    for r in online:
        if r["method"] != "online" or r["observed"] != k or "vs_congruent" not in r:
            continue
        diff, se = r["vs_congruent"]["difference"], r["vs_congruent"]["se"]
        congruent = next((c["hacc_mean"] for c in online if c["method"] == "congruent" and c["observed"] == k
                          and c["object"] == r["object"] and c["condition"] == r["condition"]), 0.0)
        margin = equivalence_margin(se, congruent)
        checks.append({"check": f"online (k={k}) matches congruent", "object": f"{r['object']}, {r['condition']}",
                       "passed": diff <= margin,
                       "detail": f"H_acc difference {diff:+.4f}, margin {margin:.4f} (paired SE {se:.4f}, "
                                 f"n {r['n']})"})
    return checks


def online_section(records: Sequence[Mapping[str, Any]], figure_names: set[str],
                   separability: Sequence[Mapping[str, Any]] = ()) -> list[str]:
    """The report's lines for the online-adaptation experiment (none without its records)."""
    online = _online(records)
    if not online:
        return []
    lines = ["## Online adaptation: predictions conditioned on k observed pushes", "",
             "Mean H_acc (nll in brackets) per predictor and number of observed pushes k (rows) and test condition "
             "(columns), on the same scored pushes; the observed pushes are never scored. `congruent` is the "
             "biased model of the true condition: the oracle's choice of model. `online` conditions the library "
             "(general, low, medium, high) and predicts with the model of highest evidence; `online_general` "
             "conditions the general model alone; `debiased` (k = 0) re-weights the general model's kernels to "
             "its training prior (docs/method.md, \"Online adaptation\").", ""]
    conditions = ordered(r["condition"] for r in online)
    for obj in ordered(r["object"] for r in online):
        lines += [f"**{obj}**", ""]
        rows = []
        part = [r for r in online if r["object"] == obj]
        for method in ordered((r["method"] for r in part), ONLINE_ORDER):
            for k in sorted({r["observed"] for r in part if r["method"] == method}):
                cells = []
                for c in conditions:
                    hit = [r for r in part if r["method"] == method and r["observed"] == k and r["condition"] == c]
                    cells.append(f"{hit[0]['hacc_mean']:.4f} ({hit[0]['nll_mean']:.1f})" if hit else "—")
                rows.append([method, k, *cells])
        lines += ["| predictor | k | " + " | ".join(conditions) + " |",
                  "|" + "---|" * (2 + len(conditions))]
        lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
        lines.append("")
    lines += _gap_table(online)
    posterior = [r for r in online if r["method"] in ("online", "online_general") and r["observed"] > 0]
    if posterior:
        lines += ["Posterior against the truth (means over the cases of each posterior's mean ± spread; μ on its "
                  "own scale, mass as the natural log of kg):", "",
                  "| object | condition | predictor | k | μ | μ true | log m | log m true |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in posterior:
            lines.append(f"| {r['object']} | {r['condition']} | {r['method']} | {r['observed']} | "
                         f"{r['mu_mean']:.3f} ± {r['mu_std']:.3f} | {r['mu_true']:.3f} | "
                         f"{r['log_mass_mean']:.2f} ± {r['log_mass_std']:.2f} | {math.log(r['mass_true']):.2f} |")
        lines.append("")
    if separability:
        lines += ["Separability of adjacent conditions: the distance between their mean outcomes (the object's final "
                  "position in the robot's start frame, per action) over their pooled spread, averaged over the "
                  "actions. Below about 1 the outcomes cannot tell the two conditions apart push by push.", "",
                  "| object | parameter | conditions | separability | mean gap (cm) |", "|---|---|---|---|---|"]
        lines += [f"| {r['object']} | {r['parameter']} | {r['pair'].replace('|', ' / ')} | {r['separability']:.2f} | "
                  f"{r['mean_gap_cm']:.2f} |" for r in separability]
        lines.append("")
    if "online_adaptation.png" in figure_names:
        lines += ["![online adaptation](figures/online_adaptation.png)", ""]
    return lines


def _gap_table(online: Sequence[Mapping[str, Any]]) -> list[str]:
    """At k = 3 (or the largest k below it): how much of the gap from ``general`` to ``congruent`` the conditioned
    general model closes, and ``online`` over ``congruent``, per object and condition; the gap counts where it
    exceeds two standard errors of the difference."""
    ks = sorted({r["observed"] for r in online if r["observed"] > 0})
    if not ks:
        return []
    k = 3 if 3 in ks else ks[-1]
    by = {(r["object"], r["condition"], r["method"], r["observed"]): r for r in online}
    rows = []
    for obj, condition in dict.fromkeys((r["object"], r["condition"]) for r in online):
        cells = [by.get((obj, condition, m, k)) for m in ("general", "congruent", "online_general", "online")]
        if None in cells:
            continue
        general, congruent, conditioned, chosen = cells
        gap = general["hacc_mean"] - congruent["hacc_mean"]
        se = math.sqrt(general["hacc_std"] ** 2 / general["n"] + congruent["hacc_std"] ** 2 / congruent["n"])
        closed = (general["hacc_mean"] - conditioned["hacc_mean"]) / gap if gap else math.nan
        rows.append(f"| {obj} | {condition} | {general['hacc_mean']:.4f} | {congruent['hacc_mean']:.4f} | "
                    f"{gap:+.4f} | {2 * se:.4f} | {'yes' if gap > 2 * se else 'no'} | {conditioned['hacc_mean']:.4f} | "
                    f"{closed:+.2f} | {chosen['hacc_mean'] / congruent['hacc_mean']:.3f} |")
    return [f"At k = {k}: the share of the gap from `general` to `congruent` that `online_general` closes, and "
            "`online` over `congruent`. A gap counts where it exceeds two standard errors of the difference.", "",
            "| object | condition | general | congruent | gap | 2 SE | counts | online_general | closed | "
            "online / congruent |", "|---|---|---|---|---|---|---|---|---|---|", *rows, ""]


def online_figure(plt, records: Sequence[Mapping[str, Any]]):
    """H_acc against k: a panel per object and condition, a line per predictor; None without online records."""
    from pushtorch.viz.colours import colour_of

    online = _online(records)
    if not online:
        return None
    objects = ordered(r["object"] for r in online)
    conditions = ordered(r["condition"] for r in online)
    methods = ordered((r["method"] for r in online), ONLINE_ORDER)
    fig, axes = plt.subplots(len(objects), len(conditions), figsize=(2.6 * len(conditions) + 1.8, 2.3 * len(objects)),
                             squeeze=False, layout="constrained")
    for a, obj in enumerate(objects):
        for b, c in enumerate(conditions):
            ax = axes[a][b]
            for m in methods:
                pts = sorted((r["observed"], r["hacc_mean"]) for r in online
                             if r["object"] == obj and r["condition"] == c and r["method"] == m)
                if pts:
                    ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", ms=3, label=m,
                            color=colour_of(m))
            ax.set_title(f"{obj}, {c}", fontsize=8)
            ax.tick_params(labelsize=7)
            if b == 0:
                ax.set_ylabel("H_acc", fontsize=8)
            if a == len(objects) - 1:
                ax.set_xlabel("observed pushes k", fontsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", fontsize=7, title="predictor", title_fontsize=8)
    fig.suptitle("Online adaptation: H_acc against the number of observed pushes", fontsize=10)
    return fig
