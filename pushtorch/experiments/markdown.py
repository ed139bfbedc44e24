"""An experiment's ``report.md``: the paper's tables with our numbers and the paper's own beside them, the
baselines, the thrown pushes and the acceptance checks (paper, Experimental Results).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pushtorch.experiments.online_report import online_section
from pushtorch.experiments.results import (
    METHOD_ORDER,
    PAPER_LINEAR_CM,
    PAPER_POSE_LINEAR_CM,
    SELECTION_ORDER,
    bias_of,
    thrown_counts,
)
from pushtorch.experiments.statistics import pool
from pushtorch.experiments.tables import frame_scores, method_label, ordered, primary, select, table
from pushtorch.experiments.transfer_report import transfer_section

__all__ = [
    "write_report",
]


def _nll_note(stats: Mapping[str, Any]) -> str:
    return "" if math.isnan(stats.get("nll_mean", math.nan)) else f", nll {stats['nll_mean']:.1f}"


def _cell(stats: Mapping[str, Any] | None) -> str:
    if not stats or stats["n"] == 0:
        return "—"
    return f"{stats['hacc_mean']:.3f} ± {stats['hacc_std']:.3f}"


def _score_text(score: float | None) -> str:
    """A bandwidth search's held-out score; None: stds leaving the manipulator expert too few pushes."""
    return "too few pushes" if score is None else f"{score:.1f}"


def write_report(out_dir: Path, experiment: str, wall_s: float, records: Sequence[Mapping[str, Any]],
                 extras: Mapping[str, Any], figures: Sequence[Path],
                 checks: Sequence[Mapping[str, Any]], test_placement: Mapping[str, Any] | None = None,
                 engines: Mapping[str, Mapping[str, str]] | None = None) -> Path:
    """``report.md``: the paper's tables with our numbers (and the paper's where it gives them).

    ``records`` may hold both metrics: the tables read the primary (displacement) records, and the
    per-object table adds the frame score as a labelled secondary column. ``test_placement``: the run's
    ``test_placement`` config; a spread one is stated at the top (the starts are not the model's). ``engines``:
    where the world and the physics peers ran (:func:`pushtorch.experiments.results.engines`), stated at the
    top."""
    out_dir = Path(out_dir)
    frame = frame_scores(records)
    records = primary(records)
    figure_names = {p.name for p in figures}
    lines = [f"# pushtorch report: {experiment}", "",
             f"Wall time {wall_s / 60:.1f} min ({wall_s:.0f} s). H_acc is the paper's Eq. pam (0 is a "
             "perfect prediction; 1 ≈ an error of one object size or of 180°); cells are mean ± std over "
             "the group's comparisons (each prediction against each ground-truth sample). Predictions are "
             "scored on the **displacement** they predict: the predicted motion from the estimated start "
             "pose to the predicted final pose, applied to the true start pose, against the true final "
             "pose, with the test object's own dimensions and symmetries (docs/method.md). The *frame* "
             "score (the predicted final pose as it is, in the frame the model estimated) is the secondary "
             "column of the per-object table. *nll* is the mean negative log-likelihood (nats) of the true "
             "outcome under the method's predicted density, in the same displacement sense (lower is better; "
             "point predictions are scored as one kernel of the model's motion bandwidth; docs/method.md, "
             "\"Likelihood score\"). `oracle_physics` simulates the true mesh from the true pose, which the "
             "method never sees: it is an oracle, not a peer. Every number is in `results.json`; the "
             "resolved configuration is in `resolved_config.yaml`.", ""]
    world = (engines or {}).get("world", {}).get("engine", "pybullet")
    physics = (engines or {}).get("physics", {}).get("engine", "pybullet")
    lines += [f"**World: {world}. Physics peers: {physics}.** The training pushes and the ground truth ran in "
              f"{world}; `physics_from_cloud` and `oracle_physics` rolled out in {physics}"
              + (" (the same engine as the truth: the inverse crime, peers that know the truth's own contact "
                 "model, which no robot has)." if world == physics else
                 ", across the gap between the two engines (docs/method.md \"Two engines\")."), ""]
    if test_placement and test_placement.get("spread"):
        yaw, lateral = test_placement["yaw_jitter_deg"], test_placement["lateral_jitter"]
        lines += [f"**Test set: placement_spread.** Every test push starts where the experimenter placed the "
                  f"robot, not where the model's contact model would: heading ±{yaw}° about the object's own x "
                  f"axis, the bumper's centre line up to ±{lateral} m off the object's centre; the model "
                  "predicts from that start (docs/experiments.md).", ""]

    def figure(name: str, caption: str) -> None:
        if name in figure_names:
            lines.extend([f"![{caption}](figures/{name})", ""])

    if checks:
        lines += ["## Acceptance checks", ""]
        lines += table(["check", "object", "result", "numbers"],
                        [(c["check"], c["object"], "✓" if c["passed"] else "✗", c["detail"]) for c in checks])

    selection = select(records, task="selection")
    if selection:
        objects = ordered(r["object"] for r in selection)
        methods = ordered((r["method"] for r in selection), SELECTION_ORDER)
        lines += ["## Contact model selection (paper: Fig. adaptive_results)", "",
                  "Mean H_acc ± std. The paper's figure gives no values; its finding is congruent ≈ adaptive "
                  "< incongruent. *Selected* is the share of predictions made with the congruent model.", ""]
        rows = []
        for obj in objects:
            row = [obj] + [_cell(pool(select(selection, object=obj, method=m))) for m in methods]
            adaptive = select(selection, object=obj, method="adaptive")
            rate = adaptive[0].get("selection_rate") if adaptive else None
            n = pool(select(selection, object=obj, method=methods[0]))["n"]
            rows.append(row + [f"{rate:.0%}" if rate is not None else "—", n])
        lines += table(["object"] + methods + ["adaptive: selected congruent", "n per method"], rows)
        figure("model_selection.png", "model selection")

    pose = select(records, task="pose")
    if pose:
        objects = ordered(r["object"] for r in pose)
        lines += ["## Pose estimation (paper: Fig. position_accuracy_results)", ""]
        rows = []
        for obj in objects:
            ours = pool(select(pose, object=obj, method="position_model"))
            centroid = pool(select(pose, object=obj, method="centroid"))
            rows.append([obj, _cell(ours), _cell(centroid), f"{ours['linear_cm']:.2f}",
                         f"{centroid['linear_cm']:.2f}", f"{ours['angular_deg']:.1f}",
                         f"{centroid['angular_deg']:.1f}", ours["n"]])
        lines += table(["object", "position model H_acc", "centroid H_acc", "position model cm",
                         "centroid cm", "position model deg", "centroid deg", "runs"], rows)
        ours = pool(select(pose, method="position_model"))
        centroid = pool(select(pose, method="centroid"))
        lines += table(["mean linear error (cm)", "ours", "paper"], [
            ["position model", f"{ours['linear_cm']:.2f}", PAPER_POSE_LINEAR_CM["position_model"]],
            ["centroid", f"{centroid['linear_cm']:.2f}", PAPER_POSE_LINEAR_CM["centroid"]],
        ])
        worst = max((h for hs in (extras.get("pose_hacc") or {}).values() for h in hs), default=math.nan)
        best_centroid = min((r["hacc_mean"] for r in select(pose, method="centroid")), default=math.nan)
        lines += [f"Worst position-model H_acc over all runs: {worst:.3f}; best centroid H_acc: "
                  f"{best_centroid:.3f} (the paper: the worst position-model run was under half the best "
                  "centroid).", ""]
        figure("pose_estimation.png", "pose estimation")

    prediction = select(records, task="prediction")
    for bias in ordered(bias_of(r["model"]) for r in prediction):
        part = [r for r in prediction if bias_of(r["model"]) == bias]
        objects = ordered(r["object"] for r in part)
        models = ordered(r["model"] for r in part)
        conditions = ordered(r["condition"] for r in part)
        title = f"{bias.capitalize()} biasing" if bias else "Prediction accuracy"
        lines += [f"## {title} (paper: the {bias} results figure)", "",
                  "Mean H_acc ± std of our predictor per trained model (rows) and test condition (columns). "
                  "The paper's figure gives no values.", ""]
        for obj in objects:
            lines += [f"**{obj}**", ""]
            rows = [[m] + [_cell(pool(select(part, object=obj, method="pushtorch", model=m, condition=c)))
                           for c in conditions] for m in models]
            lines += table(["model \\ condition"] + conditions, rows)
        figure(f"{bias or 'prediction'}_biasing.png", f"{bias} biasing")
        methods = ordered((r["method"] for r in part), METHOD_ORDER)
        lines += [f"Baselines on the same pushes, pooled over models and conditions ({title.lower()}):", ""]
        rows = []
        for obj in objects:
            cells = [pool(select(part, object=obj, method=m)) for m in methods]
            rows.append([obj] + [f"{_cell(c)} ({c['linear_cm']:.1f} cm{_nll_note(c)})" for c in cells])
        lines += table(["object"] + [f"{method_label(m)} H_acc (linear, nll)" for m in methods], rows)
        figure(f"{bias or 'prediction'}_baselines.png", f"{bias} baselines")

    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        objects = ordered(r["object"] for r in matched)
        lines += ["## Per object, model prior = test condition (paper: Fig. object_results)", "",
                  "Pooled over both biasing experiments where the test condition is the model's training "
                  "prior; the paper's raw linear errors beside ours.", ""]
        matched_frame = [r for r in frame if r["method"] == "pushtorch" and r["model"] == r["condition"]]
        rows = []
        for obj in objects:
            st = pool(select(matched, object=obj))
            fr = pool(select(matched_frame, object=obj))
            paper = PAPER_LINEAR_CM.get(obj)
            rows.append([obj, _cell(st), f"{st['linear_cm']:.2f}", paper if paper is not None else "—",
                         f"{st['angular_deg']:.1f}", f"{st['nll_mean']:.1f}",
                         f"{_cell(fr)}, {fr['linear_cm']:.2f} cm, {fr['angular_deg']:.1f}°" if fr["n"] else "—",
                         st["n"]])
        header = ["object", "H_acc (displacement)", "linear cm (ours)", "linear cm (paper)", "angular deg",
                  "nll", "frame score (secondary): H_acc, cm, deg", "n"]
        lines += table(header, rows)
        figure("objects.png", "per object")

    lines += online_section(records, figure_names, extras.get("online_separability") or ())
    lines += transfer_section(records, extras.get("transfer"), figure_names)

    counts = thrown_counts(extras.get("thrown") or [])
    if counts:
        from pushtorch.prediction import MAX_BACKOFF

        lines += ["## Ground-truth pushes that threw the object, and starts backed off", "",
                  "Per part and method: pushes in which the object tipped or left the ground (the physics engine "
                  "throws an object the robot starts inside), and predicted robot starts that had to be backed "
                  f"off more than {100 * MAX_BACKOFF:g} cm to clear the observed cloud (invalid conditions, still "
                  "pushed from the cleared start). Thrown pushes are included in the numbers above, as the "
                  "protocol compares against every ground truth.", ""]
        lines += table(["part", "method", "thrown / pushes", "invalid starts / starts"],
                        [(part, method, f"{c['thrown']} / {c['pushes']}",
                          f"{c['invalid_starts']} / {c['starts']}" if c["starts"] else "—")
                         for (part, method), c in counts.items()])

    bandwidths = extras.get("model_bandwidths") or {}
    if bandwidths:
        lines += ["## Kernel bandwidths chosen from data", "",
                  "Each model chooses its motion and contact-kernel stds by 5-fold held-out likelihood on its own "
                  "training pushes, from the configured values (docs/method.md, \"Bandwidths from data\"). The "
                  "score is the held-out pool's log-likelihood in nats per push (higher is better). The density's "
                  "motion stds are chosen last, from the motion stds down: the density a prediction returns, "
                  "while its mode is annealed with the motion stds (\"Two widths: the mode and the density\"); "
                  "then the evidence's outlier share ε (\"The evidence's outlier share\").", ""]
        names = ("motion_p_std", "motion_rot_std", "density_p_std", "density_rot_std", "density_outlier",
                 "contact_p_std", "contact_rot_std", "contact_robot_std", "contact_patch_std", "contact_patch_yaw_std")
        lines += table(["model", "motion p (m)", "motion rot (rad)", "density p (m)", "density rot (rad)",
                         "evidence ε", "u p (m)", "u rot (rad)", "g (m)", "patch (m)", "patch heading (rad)",
                         "held-out score: configured → chosen → density → with ε"],
                        [(name, *(f"{b['chosen'].get(k, float('nan')):.3g}" for k in names),
                          f"{_score_text(b['score_start'])} → {_score_text(b['score_chosen'])} → "
                          f"{_score_text(b.get('score_density'))} → {_score_text(b.get('score_outlier'))}")
                         for name, b in sorted(bandwidths.items())])
        lines.append("")

    scatter = extras.get("training_scatter") or {}
    if scatter:
        lines += ["## Training pushes (paper: the training-distribution figures)", "",
                  "Final object positions relative to the start: one panel per training prior (columns, in "
                  "the prior's colour, over every prior's pushes in grey) and push direction (rows).", ""]
        for part_name, by_object in scatter.items():
            for obj in by_object:
                figure(f"training_{part_name}_{obj}.png", f"{part_name} {obj}")
    path = out_dir / "report.md"
    path.write_text("\n".join(lines))
    return path
