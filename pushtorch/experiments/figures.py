"""An experiment's figures, laid out as the paper's (paper, Experimental Results: Fig. adaptive_results,
position_accuracy_results, the biasing figures, object_results, the training distributions).

``results.json`` is ``{"experiment", "world", "physics", "config", "overrides", "wall_s", "records",
"model_bandwidths"}`` (``world`` and ``physics``: ``{"engine": ...}``, where the truth and the physics peers ran;
the last: per trained model, the bandwidths it chose from its training pushes); one record per group with the keys
``task, object, method, model, condition, n, hacc_mean, hacc_std, linear_cm, angular_deg`` (and
``selection_rate`` for the selection task), so ``pandas.DataFrame(json.load(f)["records"])`` is a tidy
table. ``hacc_std`` is the population standard deviation over the group's ``n`` comparisons.
"""

from __future__ import annotations

import json
import math
import textwrap
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pushtorch.experiments.online_report import online_figure
from pushtorch.experiments.results import METHOD_ORDER, POSE_ORDER, SELECTION_ORDER, bias_of
from pushtorch.experiments.statistics import (
    BOOTSTRAP_RESAMPLES,
    SAMPLE_KEYS,
    group_stat,
    samples_by_record,
    stat_values,
    wants_log_axis,
)
from pushtorch.experiments.tables import method_label, ordered, select
from pushtorch.experiments.transfer_report import coverage_figure
from pushtorch.viz.colours import colour_of  # re-exported: the figures' colours

__all__ = [
    "FIGURE_DATA",
    "draw_figure",
    "figure_jobs",
    "make_figures",
    "read_figure_data",
    "write_figure_data",
]


#: The run-directory file holding the per-sample values the figures draw (see write_figure_data).
FIGURE_DATA = "figure_data.npz"


_WHISKER_COLOUR = "#222222"


_CAPTION_COLOUR = "#444444"


def _draw_marks(ax, groups: Sequence[str], series: Sequence[str], stats: Mapping[tuple[str, str], Any],
                kind: str, log: bool) -> None:
    """x = groups, one mark per series in its colour: a bar from zero with black whiskers on a linear axis,
    a dot with whiskers in its colour on a log axis (see wants_log_axis)."""
    width = 0.8 / max(1, len(series))
    for k, name in enumerate(series):
        marks = [(g - 0.4 + width * (k + 0.5), st) for g, group in enumerate(groups)
                 if (st := stats.get((group, name))) is not None]
        if not marks:
            continue
        xs = [x for x, _ in marks]
        means = np.array([st["mean"] for _, st in marks])
        whiskers = np.array([[st["mean"] - st["low"] for _, st in marks],
                             [st["high"] - st["mean"] for _, st in marks]])
        colour = colour_of(name, kind)
        label = method_label(name) if kind == "method" else name
        if log:
            ax.errorbar(xs, means, yerr=whiskers, fmt="o", ms=6, color=colour, ecolor=colour, elinewidth=1.5,
                        capsize=3, label=label)
        else:
            ax.bar(xs, means, width * 0.92, color=colour, label=label)
            ax.errorbar(xs, means, yerr=whiskers, fmt="none", ecolor=_WHISKER_COLOUR, elinewidth=1, capsize=2)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels(groups, fontsize=8)
    ax.set_xlim(-0.5, len(groups) - 0.5)
    ax.grid(axis="y", which="major", alpha=0.3)
    ax.set_axisbelow(True)


def _set_y_scale(ax, log: bool, values: Sequence[float]) -> None:
    """Log: limits around the positive values (an interval end at zero runs to the floor); linear: from 0."""
    import matplotlib.ticker as ticker

    if not log:
        ax.set_ylim(bottom=0)
        return
    positive = [v for v in values if math.isfinite(v) and v > 0]
    ax.set_yscale("log")
    if positive:
        low, high = min(positive) / 1.6, max(positive) * 1.6
        ax.set_ylim(low, high)
        # ticks at 1, 2, 5 × 10^k over short spans (a lone 0.1 and 1 are hard to read between)
        subs = (1.0, 2.0, 5.0) if math.log10(high / low) <= 2.5 else (1.0,)
        ax.yaxis.set_major_locator(ticker.LogLocator(base=10, subs=subs))
        ax.yaxis.set_minor_formatter(ticker.NullFormatter())
    # plain numbers (0.1, 1, 10) rather than powers of ten: read at a glance
    ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))


def _caption(stats: Iterable[Mapping[str, Any] | None], unit: str, cluster: str, log: bool,
             series_of: Mapping[int, str] | None = None) -> str:
    """The line under a figure: n per bar (or dot) and how the whiskers were computed."""
    stats = [st for st in stats if st]
    mark = "dot" if log else "bar"
    ns = sorted({st["n"] for st in stats})
    if len(ns) == 1:
        n_text = f"n = {ns[0]:,} {unit} per {mark}"
        clusters = {st["clusters"] for st in stats}
        if len(clusters) == 1 and None not in clusters and clusters != {ns[0]}:
            # the bootstrap's unit: a few predictions behind many comparisons make a rough interval
            n_text = f"n = {ns[0]:,} {unit} ({clusters.pop():,} {cluster}) per {mark}"
    elif series_of:
        n_text = f"n per {mark}: " + ", ".join(f"{name} {n:,}" for n, name in series_of.items())
    else:
        n_text = f"n = {ns[0]:,}–{ns[-1]:,} {unit} per {mark}"
    kinds = {st["interval"] for st in stats} - {"single"}
    bootstrap = f"95 % bootstrap CI of the mean ({BOOTSTRAP_RESAMPLES} resamples of whole {cluster})"
    summary = ("95 % CI of the mean from n, mean and std (log-scale normal approximation treating the "
               f"{unit} as independent: the run kept no per-sample values)")
    if kinds == {"bootstrap"}:
        whiskers = bootstrap
    elif kinds == {"summary"}:
        whiskers = summary
    else:
        whiskers = f"{bootstrap} where per-sample values were kept, else {summary}"
    text = f"{n_text}. Whiskers: {whiskers}." if kinds else f"{n_text}."
    if any(st["interval"] == "single" for st in stats):
        text += " n = 1: a single value, no interval."
    return text + " Each group's std is in report.md."


def _n_by_series(series: Sequence[str], stats: Mapping[tuple[str, str], Any]) -> dict[int, str] | None:
    """``{n: series}`` when each series has one n of its own (pose: position model 100, centroid 1)."""
    by_series = {}
    for name in series:
        ns = {st["n"] for (_, s), st in stats.items() if s == name and st}
        if len(ns) != 1:
            return None
        by_series[name] = ns.pop()
    if len(set(by_series.values())) != len(by_series):
        return None
    return {n: name for name, n in by_series.items()}


def _put_caption(fig, text: str, width_in: float) -> None:
    fig.supxlabel("\n".join(textwrap.wrap(text, max(60, int(width_in * 15)))), fontsize=7,
                  color=_CAPTION_COLOUR)


def _legend(fig, axes, title: str | None = None) -> None:
    """One legend for the figure, outside the axes on the right (constrained layout makes room for it)."""
    handles, labels = {}, []
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in handles:
                handles[label] = handle
                labels.append(label)
    if labels:
        fig.legend([handles[label] for label in labels], labels, loc="outside right upper", fontsize=8,
                   title=title, title_fontsize=8, frameon=False)


def _view(points: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """Square x and y limits around the central 99 % of ``points`` (N, 2), padded: a thrown push metres
    away must not shrink the cluster of the others to a dot."""
    low, high = np.quantile(points, [0.005, 0.995], axis=0)
    centre = (low + high) / 2
    half = max(float((high - low).max()) / 2 * 1.25, 0.002)  # at least ±2 mm: a perfectly tight cluster
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _training_figure(plt, part_name: str, obj: str, by_prior: Mapping[str, Any],
                     actions_by_prior: Mapping[str, Any]):
    """Small multiples of the training pushes' final displacements: one row per action (a push direction
    puts its pushes in a cluster of its own, centimetres across and decimetres from the others), one
    column per prior, shared limits in a row. Each panel draws its prior over every prior's pushes of
    that action in grey, so each distribution and where it overlaps the others both show."""
    labels = [label for label, points in by_prior.items() if len(points)]
    points = {label: np.asarray(by_prior[label], dtype=float).reshape(-1, 2) for label in labels}
    actions = {}
    for label in labels:
        given = np.asarray(actions_by_prior.get(label, ()), dtype=int).reshape(-1)
        # no (or mismatched) action indices, e.g. data saved before they were kept: one row for all
        actions[label] = given if len(given) == len(points[label]) else np.zeros(len(points[label]), int)
    action_ids = sorted({int(a) for label in labels for a in actions[label]})
    rows, cols = len(action_ids), len(labels)
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols + 0.4, 2.2 * rows + 1.0), squeeze=False,
                             layout="constrained")
    outside = 0
    for row, action in enumerate(action_ids):
        every = np.concatenate([points[label][actions[label] == action] for label in labels])
        (x0, x1), (y0, y1) = _view(every)
        for col, label in enumerate(labels):
            ax = axes[row, col]
            mine = points[label][actions[label] == action]
            colour = colour_of(label, "prior")
            ax.scatter(every[:, 0], every[:, 1], s=3, color="#cccccc", linewidths=0)
            ax.scatter(mine[:, 0], mine[:, 1], s=5, color=colour, alpha=0.7, linewidths=0)
            outside += int(((mine[:, 0] < x0) | (mine[:, 0] > x1) | (mine[:, 1] < y0) | (mine[:, 1] > y1)).sum())
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            ax.set_aspect("equal", adjustable="box")
            ax.tick_params(labelsize=7)
            ax.locator_params(nbins=4)
            if row == 0:
                ax.set_title(label, color=colour, fontsize=9, fontweight="bold")
            if col == 0:
                ax.set_ylabel(f"action {action}\nΔy (m)", fontsize=8)
            else:
                ax.tick_params(labelleft=False)
            if row == rows - 1:
                ax.set_xlabel("Δx (m)", fontsize=8)
    fig.suptitle(f"{part_name}: {obj} training pushes, final position relative to the start", fontsize=10)
    counts = sorted({len(points[label]) for label in labels})
    per_prior = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}–{counts[-1]}"
    text = (f"n = {per_prior} training pushes per prior, over {rows} action(s) (rows). Grey: every prior's "
            "pushes of that action. Each row's limits hold the central 99 % of that action's pushes, padded")
    text += f"; {outside} push(es) lie outside the view." if outside else "; none lies outside the view."
    _put_caption(fig, text, 2.2 * cols + 0.4)
    return fig


def _chart(plt, groups, series, stats, kind: str, title: str, unit: str, cluster: str, legend_title: str):
    """One axes of grouped marks with its legend and caption."""
    log = wants_log_axis(stat_values(stats.values(), lows=False))
    width = max(4.5, 1.3 * len(groups)) + (1.6 if len(series) > 1 else 0.0)  # + the legend's column
    fig, ax = plt.subplots(figsize=(width, 3.6), layout="constrained")
    _draw_marks(ax, groups, series, stats, kind, log)
    _set_y_scale(ax, log, stat_values(stats.values()))
    ax.set_ylabel("H_acc, mean (95 % CI)" + (", log scale" if log else ""))
    axes_width = width - (1.6 if len(series) > 1 else 0.0) - 0.8
    ax.set_title("\n".join(textwrap.wrap(title, max(30, int(axes_width * 11)))), fontsize=10)
    if len(series) > 1:
        _legend(fig, [ax], legend_title)
    _put_caption(fig, _caption(stats.values(), unit, cluster, log, _n_by_series(series, stats)), width)
    return fig


def _methods_figure(plt, part, samples, order, title: str, unit: str, cluster: str):
    """Every method's H_acc per object (model selection, pose estimation, a biasing part's baselines)."""
    objects = ordered(r["object"] for r in part)
    methods = ordered((r["method"] for r in part), order)
    stats = {(o, m): group_stat(part, samples, object=o, method=m) for o in objects for m in methods}
    return _chart(plt, objects, methods, stats, "method", title, unit, cluster, "method")


def _biasing_figure(plt, bias: str, part, samples):
    """Our predictor's H_acc per model (colours) and test condition (groups), a panel per object."""
    objects = ordered(r["object"] for r in part)
    models = ordered(r["model"] for r in part)
    conditions = ordered(r["condition"] for r in part)
    panels = {obj: {(c, m): group_stat(part, samples, object=obj, method="pushtorch", model=m, condition=c)
                    for c in conditions for m in models} for obj in objects}
    every = [st for stats in panels.values() for st in stats.values()]
    log = wants_log_axis(stat_values(every, lows=False))  # one rule for the whole figure: panels read alike
    cols = min(3, len(objects))
    rows = math.ceil(len(objects) / cols)
    width = 4.0 * cols + 1.6
    fig, axes = plt.subplots(rows, cols, figsize=(width, 3.0 * rows + 0.8), squeeze=False, layout="constrained")
    for k, (ax, obj) in enumerate(zip(axes.flat, objects, strict=False)):
        _draw_marks(ax, conditions, models, panels[obj], "prior", log)
        _set_y_scale(ax, log, stat_values(panels[obj].values()))
        ax.set_title(obj, fontsize=9)
        if k % cols == 0:
            ax.set_ylabel("H_acc, mean (95 % CI)" + (", log" if log else ""), fontsize=8)
        if k >= len(objects) - cols:
            ax.set_xlabel("test condition", fontsize=8)
    for ax in list(axes.flat)[len(objects):]:
        ax.axis("off")
    _legend(fig, list(axes.flat), "model (training prior)")
    fig.suptitle(f"{bias} biasing: our predictor's H_acc per model (colours) and test condition "
                 "(groups)", fontsize=10)
    _put_caption(fig, _caption(every, "comparisons", "predictions", log), width)
    return fig


def _objects_figure(plt, matched, samples):
    """pushtorch's H_acc per object where the model's prior is the test condition."""
    objects = ordered(r["object"] for r in matched)
    stats = {(o, "pushtorch"): group_stat(matched, samples, object=o) for o in objects}
    return _chart(plt, objects, ["pushtorch"], stats, "method", "pushtorch per object: model prior = test condition",
                  "comparisons", "predictions", "method")


def figure_jobs(records: Sequence[Mapping[str, Any]],
                extras: Mapping[str, Any]) -> list[tuple[str, Callable[..., Any], tuple]]:
    """What :func:`make_figures` draws: ``(file name, draw, arguments)`` per figure, where ``draw(plt, *arguments)``
    returns a matplotlib figure or None (nothing to draw). Each is independent of the others, and its function and
    arguments pickle, so the figures may be drawn in parallel."""
    samples = samples_by_record(records, extras)
    jobs: list[tuple[str, Callable[..., Any], tuple]] = []
    for task, order, title, filename, unit, cluster in (
        ("selection", SELECTION_ORDER, "Contact model selection", "model_selection.png", "comparisons",
         "predictions"),
        ("pose", POSE_ORDER, "Pose estimation", "pose_estimation.png", "estimates", "estimates"),
    ):
        part = select(records, task=task)
        if part:
            jobs.append((filename, _methods_figure, (part, samples, order, title, unit, cluster)))
    prediction = select(records, task="prediction")
    for bias in ordered(bias_of(r["model"]) for r in prediction):
        part = [r for r in prediction if bias_of(r["model"]) == bias]
        jobs.append((f"{bias or 'prediction'}_biasing.png", _biasing_figure, (bias, part, samples)))
        jobs.append((f"{bias or 'prediction'}_baselines.png", _methods_figure,
                     (part, samples, METHOD_ORDER,
                      f"{bias} biasing: pushtorch and baselines (pooled over models and conditions)", "comparisons",
                      "predictions")))
    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        jobs.append(("objects.png", _objects_figure, (matched, samples)))
    jobs.append(("online_adaptation.png", online_figure, (records,)))
    jobs.append(("coverage.png", coverage_figure, (records,)))
    actions = extras.get("training_actions") or {}
    for part_name, by_object in (extras.get("training_scatter") or {}).items():
        for obj, by_prior in by_object.items():
            if any(len(points) for points in by_prior.values()):
                jobs.append((f"training_{part_name}_{obj}.png", _training_figure,
                             (part_name, obj, by_prior, (actions.get(part_name) or {}).get(obj) or {})))
    return jobs


def draw_figure(folder: Path, name: str, draw: Callable[..., Any], arguments: tuple) -> Path | None:
    """One of :func:`figure_jobs`' figures drawn (matplotlib, Agg) and saved as ``folder / name``; its path, or None
    when it had nothing to draw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = draw(plt, *arguments)
    if fig is None:
        return None
    path = Path(folder) / name
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def make_figures(out_dir: Path, records: Sequence[Mapping[str, Any]], extras: Mapping[str, Any],
                 draw_all: Callable[[Callable, list[tuple]], list] | None = None) -> list[Path]:
    """PNG figures in ``out_dir/figures`` (matplotlib, Agg); returns their paths.

    ``extras`` may hold per-sample values (``hacc_samples``, ``pose_hacc``) for bootstrap intervals, and
    ``training_scatter`` (with ``training_actions``) for the training figures; without them the bar
    figures draw summary intervals and no training figure is drawn. ``draw_all(function, calls)`` returns
    ``[function(*call) for call in calls]``, in parallel where it can (an experiment's executor); by default one
    after the other here.
    """
    folder = Path(out_dir) / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    calls = [(folder, *job) for job in figure_jobs(records, extras)]
    drawn = draw_all(draw_figure, calls) if draw_all is not None else [draw_figure(*call) for call in calls]
    return [path for path in drawn if path is not None]


def write_figure_data(out_dir: Path, extras: Mapping[str, Any]) -> Path | None:
    """``figure_data.npz`` in the run directory: the per-sample values the figures draw, so
    ``tools/redraw_figures.py`` can redraw them from the run's outputs alone.

    Holds extras ``hacc_samples`` (as float32 arrays), ``pose_hacc``, ``training_scatter`` and
    ``training_actions``, indexed by a JSON string under ``index``; :func:`read_figure_data` reads them
    back as extras. Returns None (and writes nothing) when the extras hold none of them.
    """
    arrays: dict[str, np.ndarray] = {}

    def put(values: Any, dtype) -> str:
        key = f"a{len(arrays)}"
        arrays[key] = np.asarray(values, dtype=dtype)
        return key

    index: dict[str, Any] = {"hacc_samples": [], "pose_hacc": {}, "training_scatter": {}, "training_actions": {}}
    for entry in extras.get("hacc_samples") or []:
        try:
            key = put(entry["hacc"], np.float32)
        except ValueError:  # ragged rows: not kept; the figure falls back to the summary interval
            continue
        index["hacc_samples"].append({**{k: entry.get(k) for k in SAMPLE_KEYS}, "hacc": key})
    for obj, values in (extras.get("pose_hacc") or {}).items():
        index["pose_hacc"][obj] = put(values, np.float32)
    for name, dtype in (("training_scatter", np.float32), ("training_actions", np.int32)):
        for part_name, by_object in (extras.get(name) or {}).items():
            for obj, by_prior in by_object.items():
                index[name].setdefault(part_name, {})[obj] = {label: put(values, dtype)
                                                              for label, values in by_prior.items()}
    if not arrays:
        return None
    path = Path(out_dir) / FIGURE_DATA
    np.savez_compressed(path, index=np.array(json.dumps(index)), **arrays)
    return path


def read_figure_data(path: Path) -> dict[str, Any]:
    """The extras :func:`write_figure_data` saved (lists of floats and ints), ready for make_figures."""
    with np.load(Path(path), allow_pickle=False) as data:
        index = json.loads(str(data["index"]))

        def get(key: str) -> list:
            return data[key].tolist()

        return {
            "hacc_samples": [{**{k: e[k] for k in SAMPLE_KEYS}, "hacc": get(e["hacc"])}
                             for e in index.get("hacc_samples", [])],
            "pose_hacc": {obj: get(key) for obj, key in index.get("pose_hacc", {}).items()},
            **{name: {part: {obj: {label: get(key) for label, key in by_prior.items()}
                             for obj, by_prior in by_object.items()}
                      for part, by_object in index.get(name, {}).items()}
               for name in ("training_scatter", "training_actions")},
        }
