"""Outputs of an experiment run: results.json, report.md with the paper's tables, PNG figures, checks.

Paper, Experimental Results: the report lays our numbers out as the paper's figures do (selection:
Fig. adaptive_results; pose: Fig. position_accuracy_results; biasing: the friction and mass results
figures, per model and test condition; per object: Fig. object_results, matched model and condition;
training pushes: the training-distribution figures) and puts the paper's own numbers beside ours where
it gives them (its figures carry no values; its text gives the linear errors below).

``results.json`` is ``{"experiment", "config", "overrides", "wall_s", "records", "model_bandwidths"}`` (the last:
per trained model, the bandwidths it chose from its training pushes); one record per group with the keys
``task, object, method, model, condition, n, hacc_mean, hacc_std, linear_cm, angular_deg`` (and
``selection_rate`` for the selection task), so ``pandas.DataFrame(json.load(f)["records"])`` is a tidy
table. ``hacc_std`` is the population standard deviation over the group's ``n`` comparisons.

``figure_data.npz`` keeps what the figures draw beyond the records (per-sample H_acc, training pushes), so
``tools/redraw_figures.py <run dir>`` redraws a run's figures from its outputs alone. The figures' rules
(one colour per method and per prior, intervals that cannot go below zero, when the axis is logarithmic,
n on every figure) are in the figures section below.
"""

from __future__ import annotations

import json
import math
import textwrap
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from statistics import NormalDist
from typing import Any

import numpy as np

from pushtorch.viz.colours import METHOD_COLOURS, PRIOR_COLOURS, colour_of  # re-exported: the figures' colours

__all__ = [
    "FIGURE_DATA",
    "LOG_AXIS_RATIO",
    "METHOD_COLOURS",
    "PAPER_LINEAR_CM",
    "PAPER_POSE_LINEAR_CM",
    "PRIOR_COLOURS",
    "acceptance_checks",
    "colour_of",
    "make_figures",
    "mean_interval",
    "pool",
    "read_figure_data",
    "sample_entry",
    "summary_interval",
    "wants_log_axis",
    "write_figure_data",
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

_METHOD_ORDER = ("pushtorch", "no_motion", "mean_motion", "nearest_push", "physics_from_cloud", "oracle_physics",
                 "nominal_physics")
#: Baselines that see more than the method (the true mesh; the true pose): labelled so, never in "beats the
#: baselines". ``nominal_physics`` is the name runs before issue 15 gave the true-mesh baseline.
ORACLES = frozenset({"oracle_physics", "nominal_physics"})
_SELECTION_ORDER = ("congruent", "incongruent", "adaptive")
_POSE_ORDER = ("position_model", "centroid")


def primary(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The records every table, figure and check reads: pose records, and prediction and selection records
    scored on the predicted displacement (``metric: displacement``); ``metric: frame`` records (the
    estimated frame's final pose as it is) are the secondary score, shown beside the primary one."""
    return [r for r in records if r.get("metric", "displacement") == "displacement"]


def frame_scores(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The secondary (``metric: frame``) records."""
    return [r for r in records if r.get("metric") == "frame"]


def pool(records: Iterable[Mapping[str, Any]]) -> dict[str, float]:
    """Pool groups into one: n-weighted means and the exact population std of the union of their samples.

    Returns:
        ``{"n", "hacc_mean", "hacc_std", "linear_cm", "angular_deg", "nll_mean"}`` (NaN means for no records;
        ``nll_mean`` is NaN unless every record has one).
    """
    records = list(records)
    n = sum(int(r["n"]) for r in records)
    if n == 0:
        return {"n": 0, **dict.fromkeys(("hacc_mean", "hacc_std", "linear_cm", "angular_deg", "nll_mean"),
                                        math.nan)}
    scored = all(r.get("nll_mean") is not None for r in records)
    mean = sum(r["n"] * r["hacc_mean"] for r in records) / n
    second = sum(r["n"] * (r["hacc_std"] ** 2 + r["hacc_mean"] ** 2) for r in records) / n
    return {
        "n": n,
        "hacc_mean": mean,
        "hacc_std": math.sqrt(max(second - mean**2, 0.0)),
        "linear_cm": sum(r["n"] * r["linear_cm"] for r in records) / n,
        "angular_deg": sum(r["n"] * r["angular_deg"] for r in records) / n,
        "nll_mean": sum(r["n"] * r["nll_mean"] for r in records) / n if scored else math.nan,
    }


def _method_label(method: str) -> str:
    """A method's name in tables and legends: baselines that see more than the method are marked."""
    return f"{method} (oracle)" if method in ORACLES else method


def _select(records: Iterable[Mapping[str, Any]], **keys: Any) -> list[Mapping[str, Any]]:
    return [r for r in records if all(r.get(k) == v for k, v in keys.items())]


def _ordered(values: Iterable[str], order: Sequence[str] = ()) -> list[str]:
    seen = list(dict.fromkeys(values))
    return [v for v in order if v in seen] + [v for v in seen if v not in order]


def _bias_of(label: str | None) -> str:
    return (label or "").split(":", 1)[0]


def _prior_name(label: str) -> str:
    return label.split(":", 1)[-1]


def acceptance_checks(records: Sequence[Mapping[str, Any]],
                      thrown: Iterable[Mapping[str, Any]] = ()) -> list[dict[str, Any]]:
    """The quickstart's acceptance checks on whatever tasks the records hold.

    * prediction: on every object, our H_acc (pooled over models and conditions) is below no-motion's;
    * pose: on every object, the position model's mean H_acc is below the centroid's;
    * selection: on every object, adaptive and congruent differ by at most two standard errors of the
      difference (within noise);
    * thrown (``thrown``: the runs' thrown-push entries): no ground-truth push of a part and method other
      than the deliberately mismatched ``incongruent`` tipped or threw the object.
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
    for (part, method), count in _thrown_counts(thrown).items():
        if method != "incongruent":
            checks.append({"check": "no ground-truth push thrown", "object": f"{part}: {method}",
                           "passed": count["thrown"] == 0, "detail": f"{count['thrown']} / {count['pushes']}"})
    return checks


def write_results(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]], overrides: Sequence[str] = (),
                  model_bandwidths: Mapping[str, Any] | None = None) -> Path:
    """``results.json`` in the run directory (the layout in the module docstring).

    ``overrides`` are the run's command-line overrides (Hydra's task overrides), so a sweep's jobs can be
    told apart and tabulated by what was swept (``python -m pushtorch.collect``). ``model_bandwidths``: per
    trained model, the bandwidths its search chose (``PushModel.meta["bandwidths"]``).
    """
    path = Path(out_dir) / "results.json"
    payload = {"experiment": experiment, "config": dict(config), "overrides": list(overrides),
               "wall_s": float(wall_s), "records": list(records),
               "model_bandwidths": dict(model_bandwidths or {})}
    path.write_text(json.dumps(payload, indent=1, allow_nan=True))
    return path


# --- figures -------------------------------------------------------------------------------------------
#
# Every figure follows the same rules, so a reader can trust it at a glance: one colour per method and per
# prior across all figures (METHOD_COLOURS, PRIOR_COLOURS), whiskers that are 95 % intervals of the mean and
# cannot go below zero (mean_interval, summary_interval), a log axis only where the values span decades
# (wants_log_axis), legends outside the data, and a caption line under each figure with n and how the
# whiskers were computed.


#: A figure gets a log y axis when its positive values span more than this ratio (see wants_log_axis).
LOG_AXIS_RATIO = 20.0
#: Bootstrap resamples behind every interval drawn from per-sample values.
BOOTSTRAP_RESAMPLES = 2000
#: The run-directory file holding the per-sample values the figures draw (see write_figure_data).
FIGURE_DATA = "figure_data.npz"

_SAMPLE_KEYS = ("task", "object", "method", "model", "condition")
_WHISKER_COLOUR = "#222222"
_CAPTION_COLOUR = "#444444"


def _cluster_sums(values: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per-cluster sums and sizes: a flat sequence is one cluster per value, a sequence of sequences (or a
    2-D array) one cluster per row; empty clusters are dropped."""
    if isinstance(values, np.ndarray) and values.ndim == 2:
        rows = values.astype(float)
        return rows.sum(axis=1), np.full(rows.shape[0], float(rows.shape[1]))
    items = list(values)
    if all(np.ndim(v) == 0 for v in items):
        flat = np.asarray(items, dtype=float).reshape(-1)
        return flat, np.ones_like(flat)
    rows = [np.asarray(v, dtype=float).reshape(-1) for v in items]
    rows = [r for r in rows if r.size]
    return np.array([r.sum() for r in rows]), np.array([float(r.size) for r in rows])


def mean_interval(values: Any, confidence: float = 0.95, resamples: int = BOOTSTRAP_RESAMPLES,
                  seed: int = 0) -> tuple[float, float, float]:
    """The mean of ``values`` and a percentile-bootstrap confidence interval of it: ``(mean, low, high)``.

    ``values`` is either flat (each value resampled on its own) or a sequence of clusters (rows), each
    resampled whole: a prediction's comparisons with its ``truth_samples`` ground truths share the one
    prediction, so they are not independent, and resampling them one by one would understate the
    uncertainty. Every bootstrap mean is a mean of the data, so the interval lies within the data's range
    (never below zero for non-negative errors); it is widened to contain the mean if it does not (possible
    only for extremely skewed data). Seeded: the same values give the same interval. NaNs for no values.
    """
    sums, counts = _cluster_sums(values)
    if counts.sum() == 0:
        return math.nan, math.nan, math.nan
    mean = float(sums.sum() / counts.sum())
    rng = np.random.default_rng(seed)
    boot = np.empty(resamples)
    chunk = max(1, 2_000_000 // len(sums))  # bounded memory for the paper's 10,000-comparison groups
    for start in range(0, resamples, chunk):
        picks = rng.integers(0, len(sums), size=(min(chunk, resamples - start), len(sums)))
        boot[start:start + len(picks)] = sums[picks].sum(axis=1) / counts[picks].sum(axis=1)
    low, high = np.quantile(boot, [(1 - confidence) / 2, (1 + confidence) / 2])
    return mean, min(float(low), mean), max(float(high), mean)


def summary_interval(n: int, mean: float, std: float, confidence: float = 0.95) -> tuple[float, float, float]:
    """A confidence interval of a non-negative mean from its summary alone: ``(mean, low, high)``.

    For runs whose per-sample values were not saved (a results.json without figure_data.npz, such as the
    committed paper runs). The normal approximation on the log scale (delta method):
    ``mean · exp(±z · se / mean)`` with ``se = std / sqrt(n - 1)`` (``std`` is the population std). It
    is positive, asymmetric like the errors' distribution, and agrees with ``mean ± z · se`` for large n.
    It treats the n comparisons as independent, so it is narrower than the bootstrap over predictions.
    A single value (n = 1, e.g. the centroid) or no spread gives the point itself.
    """
    if n <= 0 or not math.isfinite(mean):
        return math.nan, math.nan, math.nan
    if n == 1 or std <= 0 or mean <= 0:
        return mean, mean, mean
    z = NormalDist().inv_cdf((1 + confidence) / 2)
    # se / mean is at most 1 for non-negative values (all of the sum in one of n values); the cap keeps
    # summaries no non-negative sample could give (hand-made ones) from overflowing
    spread = math.exp(z * min(std / math.sqrt(n - 1) / mean, 1.0))
    return mean, mean / spread, mean * spread


def wants_log_axis(values: Iterable[float], ratio: float = LOG_AXIS_RATIO) -> bool:
    """Whether a figure's y axis should be logarithmic: its positive values span more than ``ratio``.

    The rule, per figure (all panels of a figure share it): take every mean and every upper interval end
    the figure draws; if the largest positive one is more than ``ratio`` (20) times the smallest, the
    values span more than 1.3 decades and a linear axis would flatten the small means to nothing beside
    the large ones (model selection: 0.06 against 180), so the axis is logarithmic and the marks are dots
    (a bar on a log axis starts at an arbitrary floor, so its length means nothing). Otherwise the axis is
    linear from zero and the marks are bars, whose lengths then compare as ratios. Lower interval ends do
    not count: one near zero (few samples) is drawn as well on a linear axis as on a log one.
    """
    positive = [float(v) for v in values if math.isfinite(v) and v > 0]
    return len(positive) >= 2 and max(positive) / min(positive) > ratio


def sample_entry(record: Mapping[str, Any], hacc: Any) -> dict[str, Any]:
    """One record's per-sample H_acc for the figures' intervals (an item of extras ``hacc_samples``).

    Args:
        record: the results record the samples belong to (its task, object, method, model, condition).
        hacc: ``(predictions, truth samples)`` H_acc of each comparison (a tensor, array or nested list):
            one row per prediction, so the bootstrap resamples whole predictions.
    """
    rows = hacc.tolist() if hasattr(hacc, "tolist") else [list(r) for r in hacc]
    return {**{k: record.get(k) for k in _SAMPLE_KEYS}, "hacc": rows}


def _record_key(record: Mapping[str, Any]) -> tuple:
    return tuple(record.get(k) for k in _SAMPLE_KEYS)


def _samples_by_record(records: Sequence[Mapping[str, Any]],
                       extras: Mapping[str, Any]) -> dict[tuple, list]:
    """Per-sample H_acc rows by record key, from what the run kept: extras ``hacc_samples`` (selection and
    prediction), ``pose_hacc`` (the position model's runs) and any n = 1 record (its value is its sample).
    A record whose samples do not number its n gets none (stale data): its figure falls back to the
    summary interval rather than drawing an interval of other numbers."""
    found: dict[tuple, list] = {}
    for entry in extras.get("hacc_samples") or []:
        found[_record_key(entry)] = [row if isinstance(row, list) else [row] for row in entry["hacc"]]
    for obj, values in (extras.get("pose_hacc") or {}).items():
        found[("pose", obj, "position_model", None, None)] = [[float(v)] for v in values]
    by_record = {}
    for r in records:
        key = _record_key(r)
        if key in found and sum(len(row) for row in found[key]) == r["n"]:
            by_record[key] = found[key]
        elif r["n"] == 1:
            by_record[key] = [[r["hacc_mean"]]]
    return by_record


def _group_stat(records: Sequence[Mapping[str, Any]], samples: Mapping[tuple, list],
                **keys: Any) -> dict[str, Any] | None:
    """The mean H_acc of the records matching ``keys`` pooled, its 95 % interval and n (None: no data).

    The interval is the bootstrap one when every pooled record's samples were kept, else the summary one;
    ``"interval"`` says which."""
    chosen = _select(records, **keys)
    pooled = pool(chosen)
    if pooled["n"] == 0:
        return None
    clusters = None  # how many whole predictions (or estimates) the bootstrap resampled
    if pooled["n"] == 1:  # one value (the centroid's one estimate): no interval to draw or describe
        mean = low = high = pooled["hacc_mean"]
        kind = "single"
    elif all(_record_key(r) in samples for r in chosen):
        rows = [row for r in chosen for row in samples[_record_key(r)]]
        mean, low, high = mean_interval(rows)
        kind = "bootstrap"
        clusters = len(rows)
    else:
        mean, low, high = summary_interval(pooled["n"], pooled["hacc_mean"], pooled["hacc_std"])
        kind = "summary"
    if not math.isfinite(mean):
        return None
    return {"n": pooled["n"], "mean": mean, "low": low, "high": high, "interval": kind, "clusters": clusters}


def _stat_values(stats: Iterable[Mapping[str, Any] | None], lows: bool = True) -> list[float]:
    """The values a figure draws: means and interval ends (``lows=False``: without the lower ends, which
    wants_log_axis leaves out)."""
    keys = ("mean", "low", "high") if lows else ("mean", "high")
    return [st[k] for st in stats if st for k in keys]


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
        label = _method_label(name) if kind == "method" else name
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


def make_figures(out_dir: Path, records: Sequence[Mapping[str, Any]],
                 extras: Mapping[str, Any]) -> list[Path]:
    """PNG figures in ``out_dir/figures`` (matplotlib, Agg); returns their paths.

    ``extras`` may hold per-sample values (``hacc_samples``, ``pose_hacc``) for bootstrap intervals, and
    ``training_scatter`` (with ``training_actions``) for the training figures; without them the bar
    figures draw summary intervals and no training figure is drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(out_dir) / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    samples = _samples_by_record(records, extras)

    def save(fig, name: str) -> None:
        path = folder / name
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)

    def chart(groups, series, stats, kind: str, title: str, unit: str, cluster: str, name: str,
              legend_title: str) -> None:
        """One axes of grouped marks with its legend and caption."""
        log = wants_log_axis(_stat_values(stats.values(), lows=False))
        width = max(4.5, 1.3 * len(groups)) + (1.6 if len(series) > 1 else 0.0)  # + the legend's column
        fig, ax = plt.subplots(figsize=(width, 3.6), layout="constrained")
        _draw_marks(ax, groups, series, stats, kind, log)
        _set_y_scale(ax, log, _stat_values(stats.values()))
        ax.set_ylabel("H_acc, mean (95 % CI)" + (", log scale" if log else ""))
        axes_width = width - (1.6 if len(series) > 1 else 0.0) - 0.8
        ax.set_title("\n".join(textwrap.wrap(title, max(30, int(axes_width * 11)))), fontsize=10)
        if len(series) > 1:
            _legend(fig, [ax], legend_title)
        _put_caption(fig, _caption(stats.values(), unit, cluster, log, _n_by_series(series, stats)), width)
        save(fig, name)

    for task, order, title, filename, unit, cluster in (
        ("selection", _SELECTION_ORDER, "Contact model selection", "model_selection.png", "comparisons",
         "predictions"),
        ("pose", _POSE_ORDER, "Pose estimation", "pose_estimation.png", "estimates", "estimates"),
    ):
        part = _select(records, task=task)
        if not part:
            continue
        objects = _ordered(r["object"] for r in part)
        methods = _ordered((r["method"] for r in part), order)
        stats = {(o, m): _group_stat(part, samples, object=o, method=m) for o in objects for m in methods}
        chart(objects, methods, stats, "method", title, unit, cluster, filename, "method")

    prediction = _select(records, task="prediction")
    for bias in _ordered(_bias_of(r["model"]) for r in prediction):
        part = [r for r in prediction if _bias_of(r["model"]) == bias]
        objects = _ordered(r["object"] for r in part)
        models = _ordered(r["model"] for r in part)
        conditions = _ordered(r["condition"] for r in part)
        panels = {obj: {(c, m): _group_stat(part, samples, object=obj, method="pushtorch", model=m, condition=c)
                        for c in conditions for m in models} for obj in objects}
        every = [st for stats in panels.values() for st in stats.values()]
        log = wants_log_axis(_stat_values(every, lows=False))  # one rule for the whole figure: panels read alike
        cols = min(3, len(objects))
        rows = math.ceil(len(objects) / cols)
        width = 4.0 * cols + 1.6
        fig, axes = plt.subplots(rows, cols, figsize=(width, 3.0 * rows + 0.8), squeeze=False,
                                 layout="constrained")
        for k, (ax, obj) in enumerate(zip(axes.flat, objects, strict=False)):
            _draw_marks(ax, conditions, models, panels[obj], "prior", log)
            _set_y_scale(ax, log, _stat_values(panels[obj].values()))
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
        save(fig, f"{bias or 'prediction'}_biasing.png")

        methods = _ordered((r["method"] for r in part), _METHOD_ORDER)
        stats = {(o, m): _group_stat(part, samples, object=o, method=m) for o in objects for m in methods}
        chart(objects, methods, stats, "method",
              f"{bias} biasing: pushtorch and baselines (pooled over models and conditions)", "comparisons",
              "predictions", f"{bias or 'prediction'}_baselines.png", "method")

    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        objects = _ordered(r["object"] for r in matched)
        stats = {(o, "pushtorch"): _group_stat(matched, samples, object=o) for o in objects}
        chart(objects, ["pushtorch"], stats, "method", "pushtorch per object: model prior = test condition",
              "comparisons", "predictions", "objects.png", "method")

    actions = extras.get("training_actions") or {}
    for part_name, by_object in (extras.get("training_scatter") or {}).items():
        for obj, by_prior in by_object.items():
            if not any(len(points) for points in by_prior.values()):
                continue
            fig = _training_figure(plt, part_name, obj, by_prior, (actions.get(part_name) or {}).get(obj) or {})
            save(fig, f"training_{part_name}_{obj}.png")
    return paths


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
        index["hacc_samples"].append({**{k: entry.get(k) for k in _SAMPLE_KEYS}, "hacc": key})
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
            "hacc_samples": [{**{k: e[k] for k in _SAMPLE_KEYS}, "hacc": get(e["hacc"])}
                             for e in index.get("hacc_samples", [])],
            "pose_hacc": {obj: get(key) for obj, key in index.get("pose_hacc", {}).items()},
            **{name: {part: {obj: {label: get(key) for label, key in by_prior.items()}
                             for obj, by_prior in by_object.items()}
                      for part, by_object in index.get(name, {}).items()}
               for name in ("training_scatter", "training_actions")},
        }


# --- report.md -----------------------------------------------------------------------------------------


def _thrown_counts(thrown: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], dict[str, int]]:
    """Thrown pushes and invalid starts summed per (part, method): the model-selection entries carry the
    selection method, the biasing entries ``pushtorch`` with the bias in the model label."""
    counts: dict[tuple[str, str], dict[str, int]] = {}
    for t in thrown:
        part = "model selection" if t.get("model") is None else f"{_bias_of(t['model'])} biasing"
        entry = counts.setdefault((part, t["method"]), {"thrown": 0, "pushes": 0, "invalid_starts": 0,
                                                        "starts": 0})
        for key in entry:
            entry[key] += int(t.get(key) or 0)
    return counts


def _nll_note(stats: Mapping[str, Any]) -> str:
    return "" if math.isnan(stats.get("nll_mean", math.nan)) else f", nll {stats['nll_mean']:.1f}"


def _cell(stats: Mapping[str, Any] | None) -> str:
    if not stats or stats["n"] == 0:
        return "—"
    return f"{stats['hacc_mean']:.3f} ± {stats['hacc_std']:.3f}"


def _table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines + [""]


def _score_text(score: float | None) -> str:
    """A bandwidth search's held-out score; None: stds leaving the manipulator expert too few pushes."""
    return "too few pushes" if score is None else f"{score:.1f}"


def write_report(out_dir: Path, experiment: str, wall_s: float, records: Sequence[Mapping[str, Any]],
                 extras: Mapping[str, Any], figures: Sequence[Path],
                 checks: Sequence[Mapping[str, Any]], test_placement: Mapping[str, Any] | None = None) -> Path:
    """``report.md``: the paper's tables with our numbers (and the paper's where it gives them).

    ``records`` may hold both metrics: the tables read the primary (displacement) records, and the
    per-object table adds the frame score as a labelled secondary column. ``test_placement``: the run's
    ``test_placement`` config; a spread one is stated at the top (the starts are not the model's)."""
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
            rows.append([obj] + [f"{_cell(c)} ({c['linear_cm']:.1f} cm{_nll_note(c)})" for c in cells])
        lines += _table(["object"] + [f"{_method_label(m)} H_acc (linear, nll)" for m in methods], rows)
        figure(f"{bias or 'prediction'}_baselines.png", f"{bias} baselines")

    matched = [r for r in prediction if r["method"] == "pushtorch" and r["model"] == r["condition"]]
    if matched:
        objects = _ordered(r["object"] for r in matched)
        lines += ["## Per object, model prior = test condition (paper: Fig. object_results)", "",
                  "Pooled over both biasing experiments where the test condition is the model's training "
                  "prior; the paper's raw linear errors beside ours.", ""]
        matched_frame = [r for r in frame if r["method"] == "pushtorch" and r["model"] == r["condition"]]
        rows = []
        for obj in objects:
            st = pool(_select(matched, object=obj))
            fr = pool(_select(matched_frame, object=obj))
            paper = PAPER_LINEAR_CM.get(obj)
            rows.append([obj, _cell(st), f"{st['linear_cm']:.2f}", paper if paper is not None else "—",
                         f"{st['angular_deg']:.1f}", f"{st['nll_mean']:.1f}",
                         f"{_cell(fr)}, {fr['linear_cm']:.2f} cm, {fr['angular_deg']:.1f}°" if fr["n"] else "—",
                         st["n"]])
        header = ["object", "H_acc (displacement)", "linear cm (ours)", "linear cm (paper)", "angular deg",
                  "nll", "frame score (secondary): H_acc, cm, deg", "n"]
        lines += _table(header, rows)
        figure("objects.png", "per object")

    counts = _thrown_counts(extras.get("thrown") or [])
    if counts:
        from pushtorch.predict import MAX_BACKOFF

        lines += ["## Ground-truth pushes that threw the object, and starts backed off", "",
                  "Per part and method: pushes in which the object tipped or left the ground (the physics engine "
                  "throws an object the robot starts inside), and predicted robot starts that had to be backed "
                  f"off more than {100 * MAX_BACKOFF:g} cm to clear the observed cloud (invalid conditions, still "
                  "pushed from the cleared start). Thrown pushes are included in the numbers above, as the "
                  "protocol compares against every ground truth.", ""]
        lines += _table(["part", "method", "thrown / pushes", "invalid starts / starts"],
                        [(part, method, f"{c['thrown']} / {c['pushes']}",
                          f"{c['invalid_starts']} / {c['starts']}" if c["starts"] else "—")
                         for (part, method), c in counts.items()])

    bandwidths = extras.get("model_bandwidths") or {}
    if bandwidths:
        lines += ["## Kernel bandwidths chosen from data", "",
                  "Each model chooses its motion and contact-kernel stds by 5-fold held-out likelihood on its own "
                  "training pushes, from the configured values (docs/method.md, \"Bandwidths from data\"). The "
                  "score is the held-out pool's log-likelihood in nats per push (higher is better).", ""]
        names = ("motion_p_std", "motion_rot_std", "contact_p_std", "contact_rot_std", "contact_robot_std",
                 "contact_patch_std", "contact_patch_yaw_std")
        lines += _table(["model", "motion p (m)", "motion rot (rad)", "u p (m)", "u rot (rad)", "g (m)",
                         "patch (m)", "patch heading (rad)", "held-out score: configured → chosen"],
                        [(name, *(f"{b['chosen'].get(k, float('nan')):.3g}" for k in names),
                          f"{_score_text(b['score_start'])} → {_score_text(b['score_chosen'])}")
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


def write_outputs(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]], extras: Mapping[str, Any],
                  overrides: Sequence[str] = ()) -> dict[str, Any]:
    """results.json, figures, report.md; returns their paths and the acceptance checks."""
    results = write_results(out_dir, experiment, config, wall_s, records, overrides,
                            extras.get("model_bandwidths"))
    figures = make_figures(out_dir, primary(records), extras)
    figure_data = write_figure_data(out_dir, extras)  # what tools/redraw_figures.py redraws them from
    checks = acceptance_checks(primary(records), extras.get("thrown") or ())
    report = write_report(out_dir, experiment, wall_s, records, extras, figures, checks,
                          config.get("test_placement"))
    return {"results": results, "report": report, "figures": figures, "figure_data": figure_data,
            "checks": checks}
