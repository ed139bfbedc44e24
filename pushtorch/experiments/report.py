"""Outputs of an experiment run: results.json, report.md with the paper's tables, PNG figures, checks.

Paper, Experimental Results: the report lays our numbers out as the paper's figures do (selection:
Fig. adaptive_results; pose: Fig. position_accuracy_results; biasing: the friction and mass results
figures, per model and test condition; per object: Fig. object_results, matched model and condition;
training pushes: the training-distribution figures) and puts the paper's own numbers beside ours where
it gives them (its figures carry no values; its text gives the linear errors below).

``results.json`` is ``{"experiment", "config", "wall_s", "records"}``; one record per group with the keys
``task, object, method, model, condition, n, hacc_mean, hacc_std, linear_cm, angular_deg`` (and
``selection_rate`` for the selection task), so ``pandas.DataFrame(json.load(f)["records"])`` is a tidy
table. ``hacc_std`` is the population standard deviation over the group's ``n`` comparisons.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "PAPER_LINEAR_CM",
    "PAPER_POSE_LINEAR_CM",
    "acceptance_checks",
    "make_figures",
    "pool",
    "write_outputs",
    "write_report",
    "write_results",
]

#: The paper's raw linear prediction errors per object (cm), matched model and condition (§Results).
PAPER_LINEAR_CM = {
    "cube": 1.68, "prism_thin": 1.97, "prism_long": 2.86,
    "cylinder": 4.04, "cylinder_wide": 8.14, "hybrid": 3.96,
}
#: The paper's mean linear pose errors (cm) over the cube, cylinder and modified cube (§Pose Estimation).
PAPER_POSE_LINEAR_CM = {"position_model": 1.41, "centroid": 7.06}

_PRIOR_COLOURS = {"general": "#2ca02c", "low": "#1f77b4", "medium": "#ff7f0e", "high": "#d62728"}
_METHOD_ORDER = ("pushtorch", "no_motion", "mean_motion", "nominal_physics")
_SELECTION_ORDER = ("congruent", "incongruent", "adaptive")
_POSE_ORDER = ("position_model", "centroid")


def pool(records: Iterable[Mapping[str, Any]]) -> dict[str, float]:
    """Pool groups into one: n-weighted means and the exact population std of the union of their samples.

    Returns:
        ``{"n", "hacc_mean", "hacc_std", "linear_cm", "angular_deg"}`` (NaN means for no records).
    """
    records = list(records)
    n = sum(int(r["n"]) for r in records)
    if n == 0:
        return {"n": 0, **dict.fromkeys(("hacc_mean", "hacc_std", "linear_cm", "angular_deg"), math.nan)}
    mean = sum(r["n"] * r["hacc_mean"] for r in records) / n
    second = sum(r["n"] * (r["hacc_std"] ** 2 + r["hacc_mean"] ** 2) for r in records) / n
    return {
        "n": n,
        "hacc_mean": mean,
        "hacc_std": math.sqrt(max(second - mean**2, 0.0)),
        "linear_cm": sum(r["n"] * r["linear_cm"] for r in records) / n,
        "angular_deg": sum(r["n"] * r["angular_deg"] for r in records) / n,
    }


def _select(records: Iterable[Mapping[str, Any]], **keys: Any) -> list[Mapping[str, Any]]:
    return [r for r in records if all(r.get(k) == v for k, v in keys.items())]


def _ordered(values: Iterable[str], order: Sequence[str] = ()) -> list[str]:
    seen = list(dict.fromkeys(values))
    return [v for v in order if v in seen] + [v for v in seen if v not in order]


def _bias_of(label: str | None) -> str:
    return (label or "").split(":", 1)[0]


def _prior_name(label: str) -> str:
    return label.split(":", 1)[-1]


def acceptance_checks(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The quickstart's acceptance checks on whatever tasks the records hold.

    * prediction: on every object, our H_acc (pooled over models and conditions) is below no-motion's;
    * pose: on every object, the position model's mean H_acc is below the centroid's;
    * selection: on every object, adaptive and congruent differ by at most two standard errors of the
      difference (within noise).
    """
    checks = []
    for obj in _ordered(r["object"] for r in _select(records, task="prediction")):
        ours = pool(_select(records, task="prediction", object=obj, method="pushtorch"))
        still = pool(_select(records, task="prediction", object=obj, method="no_motion"))
        checks.append({"check": "pushtorch beats no-motion", "object": obj,
                       "passed": ours["hacc_mean"] < still["hacc_mean"],
                       "detail": f"H_acc {ours['hacc_mean']:.3f} vs {still['hacc_mean']:.3f}"})
    for obj in _ordered(r["object"] for r in _select(records, task="pose")):
        ours = pool(_select(records, task="pose", object=obj, method="position_model"))
        centroid = pool(_select(records, task="pose", object=obj, method="centroid"))
        checks.append({"check": "position model beats centroid", "object": obj,
                       "passed": ours["hacc_mean"] < centroid["hacc_mean"],
                       "detail": f"H_acc {ours['hacc_mean']:.3f} vs {centroid['hacc_mean']:.3f}"})
    for obj in _ordered(r["object"] for r in _select(records, task="selection")):
        adaptive = pool(_select(records, task="selection", object=obj, method="adaptive"))
        congruent = pool(_select(records, task="selection", object=obj, method="congruent"))
        if adaptive["n"] == 0 or congruent["n"] == 0:
            continue
        se = math.sqrt(adaptive["hacc_std"] ** 2 / adaptive["n"]
                       + congruent["hacc_std"] ** 2 / congruent["n"])
        diff = adaptive["hacc_mean"] - congruent["hacc_mean"]
        checks.append({"check": "adaptive matches congruent", "object": obj,
                       "passed": abs(diff) <= 2 * se + 1e-9,
                       "detail": f"H_acc {adaptive['hacc_mean']:.3f} vs {congruent['hacc_mean']:.3f} "
                                 f"(difference {diff:+.3f}, 2 SE {2 * se:.3f})"})
    return checks


def write_results(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]]) -> Path:
    """``results.json`` in the run directory (the layout in the module docstring)."""
    path = Path(out_dir) / "results.json"
    payload = {"experiment": experiment, "config": dict(config), "wall_s": float(wall_s),
               "records": list(records)}
    path.write_text(json.dumps(payload, indent=1, allow_nan=True))
    return path


# --- figures -------------------------------------------------------------------------------------------


def _bars(ax, groups: list[str], series: list[str], stats: dict[tuple[str, str], dict], colours=None) -> None:
    """Grouped bars: x = groups, one bar per series, height H_acc mean, error bar its std."""
    width = 0.8 / max(1, len(series))
    for k, s in enumerate(series):
        xs, heights, errors = [], [], []
        for g, group in enumerate(groups):
            st = stats.get((group, s))
            if st is None or st["n"] == 0:
                continue
            xs.append(g - 0.4 + width * (k + 0.5))
            heights.append(st["hacc_mean"])
            errors.append(st["hacc_std"])
        colour = (colours or {}).get(_prior_name(s)) if colours else None
        ax.bar(xs, heights, width, yerr=errors, capsize=2, label=s, color=colour)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels(groups, rotation=0, fontsize=8)
    ax.set_ylabel("H_acc (mean ± std)")
    ax.set_ylim(bottom=0)


def make_figures(out_dir: Path, records: Sequence[Mapping[str, Any]],
                 extras: Mapping[str, Any]) -> list[Path]:
    """PNG figures in ``out_dir/figures`` (matplotlib, Agg); returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(out_dir) / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        path = folder / name
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)

    for task, order, title, filename in (
        ("selection", _SELECTION_ORDER, "Contact model selection", "model_selection.png"),
        ("pose", _POSE_ORDER, "Pose estimation", "pose_estimation.png"),
    ):
        part = _select(records, task=task)
        if not part:
            continue
        objects = _ordered(r["object"] for r in part)
        methods = _ordered((r["method"] for r in part), order)
        stats = {(o, m): pool(_select(part, object=o, method=m)) for o in objects for m in methods}
        fig, ax = plt.subplots(figsize=(5, 3.5))
        _bars(ax, objects, methods, stats)
        ax.set_title(title)
        ax.legend(fontsize=8)
        save(fig, filename)

    prediction = _select(records, task="prediction")
    for bias in _ordered(_bias_of(r["model"]) for r in prediction):
        part = [r for r in prediction if _bias_of(r["model"]) == bias]
        objects = _ordered(r["object"] for r in part)
        models = _ordered(r["model"] for r in part)
        conditions = _ordered(r["condition"] for r in part)
        cols = min(3, len(objects))
        rows = math.ceil(len(objects) / cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
        for ax, obj in zip(axes.flat, objects, strict=False):
            stats = {(c, m): pool(_select(part, object=obj, method="pushtorch", model=m, condition=c))
                     for c in conditions for m in models}
            _bars(ax, conditions, models, stats, _PRIOR_COLOURS)
            ax.set_title(obj, fontsize=9)
        for ax in list(axes.flat)[len(objects):]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=7, title="model", title_fontsize=7)
        fig.suptitle(f"{bias} biasing: H_acc per model (bars) and test condition (groups)", fontsize=10)
        save(fig, f"{bias or 'prediction'}_biasing.png")

        methods = _ordered((r["method"] for r in part), _METHOD_ORDER)
        stats = {(o, m): pool(_select(part, object=o, method=m)) for o in objects for m in methods}
        fig, ax = plt.subplots(figsize=(max(5, 1.3 * len(objects)), 3.5))
        _bars(ax, objects, methods, stats)
        ax.set_yscale("symlog", linthresh=0.1)
        ax.set_title(f"{bias} biasing: pushtorch and baselines (all models and conditions)")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        save(fig, f"{bias or 'prediction'}_baselines.png")

    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        objects = _ordered(r["object"] for r in matched)
        stats = {(o, "pushtorch"): pool(_select(matched, object=o)) for o in objects}
        fig, ax = plt.subplots(figsize=(max(5, 1.1 * len(objects)), 3.5))
        _bars(ax, objects, ["pushtorch"], stats)
        ax.set_title("Per object: model prior = test condition")
        save(fig, "objects.png")

    for part_name, by_object in (extras.get("training_scatter") or {}).items():
        for obj, by_prior in by_object.items():
            fig, ax = plt.subplots(figsize=(4.5, 4))
            for label, points in by_prior.items():
                if points:
                    xs, ys = zip(*points, strict=True)
                    colour = _PRIOR_COLOURS.get(_prior_name(label))
                    ax.scatter(xs, ys, s=4, alpha=0.6, label=label, color=colour)
            ax.scatter([0], [0], marker="+", color="k", s=60)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{part_name}: {obj} training final positions", fontsize=9)
            ax.legend(fontsize=7, markerscale=3)
            save(fig, f"training_{part_name}_{obj}.png")
    return paths


# --- report.md -----------------------------------------------------------------------------------------


def _cell(stats: Mapping[str, Any] | None) -> str:
    if not stats or stats["n"] == 0:
        return "—"
    return f"{stats['hacc_mean']:.3f} ± {stats['hacc_std']:.3f}"


def _table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines + [""]


def write_report(out_dir: Path, experiment: str, wall_s: float, records: Sequence[Mapping[str, Any]],
                 extras: Mapping[str, Any], figures: Sequence[Path],
                 checks: Sequence[Mapping[str, Any]]) -> Path:
    """``report.md``: the paper's tables with our numbers (and the paper's where it gives them)."""
    out_dir = Path(out_dir)
    figure_names = {p.name for p in figures}
    lines = [f"# pushtorch report: {experiment}", "",
             f"Wall time {wall_s / 60:.1f} min ({wall_s:.0f} s). H_acc is the paper's Eq. pam (0 is a "
             "perfect prediction; 1 ≈ an error of one object size or of 180°); cells are mean ± std over "
             "the group's comparisons (each prediction against each ground-truth sample). Every number is "
             "in `results.json`; the resolved configuration is in `resolved_config.yaml`.", ""]

    def figure(name: str, caption: str) -> None:
        if name in figure_names:
            lines.extend([f"![{caption}](figures/{name})", ""])

    if checks:
        lines += ["## Acceptance checks", ""]
        lines += _table(["check", "object", "result", "numbers"],
                        [(c["check"], c["object"], "✓" if c["passed"] else "✗", c["detail"]) for c in checks])

    selection = _select(records, task="selection")
    if selection:
        objects = _ordered(r["object"] for r in selection)
        methods = _ordered((r["method"] for r in selection), _SELECTION_ORDER)
        lines += ["## Contact model selection (paper: Fig. adaptive_results)", "",
                  "Mean H_acc ± std. The paper's figure gives no values; its finding is congruent ≈ adaptive "
                  "< incongruent. *Selected* is the share of predictions made with the congruent model.", ""]
        rows = []
        for obj in objects:
            row = [obj] + [_cell(pool(_select(selection, object=obj, method=m))) for m in methods]
            adaptive = _select(selection, object=obj, method="adaptive")
            rate = adaptive[0].get("selection_rate") if adaptive else None
            n = pool(_select(selection, object=obj, method=methods[0]))["n"]
            rows.append(row + [f"{rate:.0%}" if rate is not None else "—", n])
        lines += _table(["object"] + methods + ["adaptive: selected congruent", "n per method"], rows)
        figure("model_selection.png", "model selection")

    pose = _select(records, task="pose")
    if pose:
        objects = _ordered(r["object"] for r in pose)
        lines += ["## Pose estimation (paper: Fig. position_accuracy_results)", ""]
        rows = []
        for obj in objects:
            ours = pool(_select(pose, object=obj, method="position_model"))
            centroid = pool(_select(pose, object=obj, method="centroid"))
            rows.append([obj, _cell(ours), _cell(centroid), f"{ours['linear_cm']:.2f}",
                         f"{centroid['linear_cm']:.2f}", f"{ours['angular_deg']:.1f}",
                         f"{centroid['angular_deg']:.1f}", ours["n"]])
        lines += _table(["object", "position model H_acc", "centroid H_acc", "position model cm",
                         "centroid cm", "position model deg", "centroid deg", "runs"], rows)
        ours = pool(_select(pose, method="position_model"))
        centroid = pool(_select(pose, method="centroid"))
        lines += _table(["mean linear error (cm)", "ours", "paper"], [
            ["position model", f"{ours['linear_cm']:.2f}", PAPER_POSE_LINEAR_CM["position_model"]],
            ["centroid", f"{centroid['linear_cm']:.2f}", PAPER_POSE_LINEAR_CM["centroid"]],
        ])
        worst = max((h for hs in (extras.get("pose_hacc") or {}).values() for h in hs), default=math.nan)
        best_centroid = min((r["hacc_mean"] for r in _select(pose, method="centroid")), default=math.nan)
        lines += [f"Worst position-model H_acc over all runs: {worst:.3f}; best centroid H_acc: "
                  f"{best_centroid:.3f} (the paper: the worst position-model run was under half the best "
                  "centroid).", ""]
        figure("pose_estimation.png", "pose estimation")

    prediction = _select(records, task="prediction")
    for bias in _ordered(_bias_of(r["model"]) for r in prediction):
        part = [r for r in prediction if _bias_of(r["model"]) == bias]
        objects = _ordered(r["object"] for r in part)
        models = _ordered(r["model"] for r in part)
        conditions = _ordered(r["condition"] for r in part)
        title = f"{bias.capitalize()} biasing" if bias else "Prediction accuracy"
        lines += [f"## {title} (paper: the {bias} results figure)", "",
                  "Mean H_acc ± std of our predictor per trained model (rows) and test condition (columns). "
                  "The paper's figure gives no values.", ""]
        for obj in objects:
            lines += [f"**{obj}**", ""]
            rows = [[m] + [_cell(pool(_select(part, object=obj, method="pushtorch", model=m, condition=c)))
                           for c in conditions] for m in models]
            lines += _table(["model \\ condition"] + conditions, rows)
        figure(f"{bias or 'prediction'}_biasing.png", f"{bias} biasing")
        methods = _ordered((r["method"] for r in part), _METHOD_ORDER)
        lines += [f"Baselines on the same pushes, pooled over models and conditions ({title.lower()}):", ""]
        rows = []
        for obj in objects:
            cells = [pool(_select(part, object=obj, method=m)) for m in methods]
            rows.append([obj] + [f"{_cell(c)} ({c['linear_cm']:.1f} cm)" for c in cells])
        lines += _table(["object"] + [f"{m} H_acc (linear)" for m in methods], rows)
        figure(f"{bias or 'prediction'}_baselines.png", f"{bias} baselines")

    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        objects = _ordered(r["object"] for r in matched)
        lines += ["## Per object, model prior = test condition (paper: Fig. object_results)", "",
                  "Pooled over both biasing experiments where the test condition is the model's training "
                  "prior; the paper's raw linear errors beside ours.", ""]
        rows = []
        for obj in objects:
            st = pool(_select(matched, object=obj))
            paper = PAPER_LINEAR_CM.get(obj)
            rows.append([obj, _cell(st), f"{st['linear_cm']:.2f}", paper if paper is not None else "—",
                         f"{st['angular_deg']:.1f}", st["n"]])
        header = ["object", "H_acc", "linear cm (ours)", "linear cm (paper)", "angular deg", "n"]
        lines += _table(header, rows)
        figure("objects.png", "per object")

    thrown = [t for t in extras.get("thrown") or [] if t["thrown"]]
    if thrown:
        lines += ["## Ground-truth pushes that threw the object", "",
                  "Pushes in which the object tipped or left the ground: the robot start pose the model "
                  "chose overlapped the object, and the physics engine threw it (sometimes metres away). "
                  "They are included in the numbers above, as the protocol compares against every ground "
                  "truth; they explain very large H_acc means.", ""]
        lines += _table(["object", "method", "model", "condition", "thrown / pushes"],
                        [(t["object"], t["method"], t["model"] or "—", t["condition"] or "—",
                          f"{t['thrown']} / {t['pushes']}") for t in thrown])

    scatter = extras.get("training_scatter") or {}
    if scatter:
        lines += ["## Training pushes (paper: the training-distribution figures)", "",
                  "Final object positions relative to the start, one colour per training prior.", ""]
        for part_name, by_object in scatter.items():
            for obj in by_object:
                figure(f"training_{part_name}_{obj}.png", f"{part_name} {obj}")
    path = out_dir / "report.md"
    path.write_text("\n".join(lines))
    return path


def write_outputs(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]], extras: Mapping[str, Any]) -> dict[str, Any]:
    """results.json, figures, report.md; returns their paths and the acceptance checks."""
    results = write_results(out_dir, experiment, config, wall_s, records)
    figures = make_figures(out_dir, records, extras)
    checks = acceptance_checks(records)
    report = write_report(out_dir, experiment, wall_s, records, extras, figures, checks)
    return {"results": results, "report": report, "figures": figures, "checks": checks}
