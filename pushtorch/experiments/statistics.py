"""Statistics of an experiment's records: groups pooled into one, intervals of the mean (bootstrap over
clusters of samples, or from a record's n, mean and std), per-sample values behind each record, when an axis is
logarithmic (paper, Experimental Results: the numbers behind its tables and figures, with their uncertainty).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from statistics import NormalDist
from typing import Any

import numpy as np

from pushtorch.experiments.tables import select

__all__ = [
    "EQUIVALENCE_SE",
    "EQUIVALENCE_SHARE",
    "equivalence_margin",
    "BOOTSTRAP_RESAMPLES",
    "LOG_AXIS_RATIO",
    "SAMPLE_KEYS",
    "group_stat",
    "mean_interval",
    "pool",
    "record_key",
    "sample_entry",
    "samples_by_record",
    "stat_values",
    "summary_interval",
    "wants_log_axis",
]


#: A figure gets a log y axis when its positive values span more than this ratio (see wants_log_axis).
LOG_AXIS_RATIO = 20.0


#: Bootstrap resamples behind every interval drawn from per-sample values.
BOOTSTRAP_RESAMPLES = 2000


#: The record keys that name a group's per-sample values (:func:`sample_entry`, :func:`record_key`).
SAMPLE_KEYS = ("task", "object", "method", "model", "condition")
#: "X matches Y" holds when their difference in H_acc is within max(EQUIVALENCE_SE × its standard error,
#: EQUIVALENCE_SHARE × Y's H_acc) (docs/experiments.md, "Claims and findings"): three standard errors keep a
#: true claim from failing on noise (two-sided 0.27 % per check, where two SE failed 5 % of true checks and a
#: main job of 20 checks then failed one in three runs); 5 % of the reference's H_acc is the practical margin,
#: far below the 30-100 % gaps that tell a wrong model from the right one (the incongruent and general models).
EQUIVALENCE_SE = 3.0
EQUIVALENCE_SHARE = 0.05


def equivalence_margin(se: float, reference_hacc: float) -> float:
    """How far "X matches Y" lets X's H_acc differ from Y's: ``max(3 SE, 5 % of Y's H_acc)``
    (:data:`EQUIVALENCE_SE`, :data:`EQUIVALENCE_SHARE`), plus float slack."""
    return max(EQUIVALENCE_SE * float(se), EQUIVALENCE_SHARE * float(reference_hacc)) + 1e-9


def pool(records: Iterable[Mapping[str, Any]]) -> dict[str, float]:
    """Pool groups into one: n-weighted means and the exact population std of the union of their samples.

    Returns:
        ``{"n", "hacc_mean", "hacc_std", "linear_cm", "angular_deg", "nll_mean", "coverage_50", "coverage_90"}``
        (NaN means for no records; ``nll_mean`` and the coverages are NaN unless every record has one).
    """
    records = list(records)
    n = sum(int(r["n"]) for r in records)
    if n == 0:
        return {"n": 0, **dict.fromkeys(("hacc_mean", "hacc_std", "linear_cm", "angular_deg", "nll_mean",
                                         "coverage_50", "coverage_90"), math.nan)}
    scored = all(r.get("nll_mean") is not None for r in records)

    def covered(key: str) -> float:
        if not all(r.get(key) is not None for r in records):
            return math.nan
        return sum(r["n"] * r[key] for r in records) / n

    mean = sum(r["n"] * r["hacc_mean"] for r in records) / n
    second = sum(r["n"] * (r["hacc_std"] ** 2 + r["hacc_mean"] ** 2) for r in records) / n
    return {
        "n": n,
        "hacc_mean": mean,
        "hacc_std": math.sqrt(max(second - mean**2, 0.0)),
        "linear_cm": sum(r["n"] * r["linear_cm"] for r in records) / n,
        "angular_deg": sum(r["n"] * r["angular_deg"] for r in records) / n,
        "nll_mean": sum(r["n"] * r["nll_mean"] for r in records) / n if scored else math.nan,
        "coverage_50": covered("coverage_50"),
        "coverage_90": covered("coverage_90"),
    }


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
    return {**{k: record.get(k) for k in SAMPLE_KEYS}, "hacc": rows}


def record_key(record: Mapping[str, Any]) -> tuple:
    """A record's (or a sample entry's) :data:`SAMPLE_KEYS` values: what its per-sample values are found by."""
    return tuple(record.get(k) for k in SAMPLE_KEYS)


def samples_by_record(records: Sequence[Mapping[str, Any]],
                      extras: Mapping[str, Any]) -> dict[tuple, list]:
    """Per-sample H_acc rows by record key, from what the run kept: extras ``hacc_samples`` (selection and
    prediction), ``pose_hacc`` (the position model's runs) and any n = 1 record (its value is its sample).
    A record whose samples do not number its n gets none (stale data): its figure falls back to the
    summary interval rather than drawing an interval of other numbers."""
    found: dict[tuple, list] = {}
    for entry in extras.get("hacc_samples") or []:
        found[record_key(entry)] = [row if isinstance(row, list) else [row] for row in entry["hacc"]]
    for obj, values in (extras.get("pose_hacc") or {}).items():
        found[("pose", obj, "position_model", None, None)] = [[float(v)] for v in values]
    by_record = {}
    for r in records:
        key = record_key(r)
        if key in found and sum(len(row) for row in found[key]) == r["n"]:
            by_record[key] = found[key]
        elif r["n"] == 1:
            by_record[key] = [[r["hacc_mean"]]]
    return by_record


def group_stat(records: Sequence[Mapping[str, Any]], samples: Mapping[tuple, list],
               **keys: Any) -> dict[str, Any] | None:
    """The mean H_acc of the records matching ``keys`` pooled, its 95 % interval and n (None: no data).

    The interval is the bootstrap one when every pooled record's samples were kept, else the summary one;
    ``"interval"`` says which."""
    chosen = select(records, **keys)
    pooled = pool(chosen)
    if pooled["n"] == 0:
        return None
    clusters = None  # how many whole predictions (or estimates) the bootstrap resampled
    if pooled["n"] == 1:  # one value (the centroid's one estimate): no interval to draw or describe
        mean = low = high = pooled["hacc_mean"]
        kind = "single"
    elif all(record_key(r) in samples for r in chosen):
        rows = [row for r in chosen for row in samples[record_key(r)]]
        mean, low, high = mean_interval(rows)
        kind = "bootstrap"
        clusters = len(rows)
    else:
        mean, low, high = summary_interval(pooled["n"], pooled["hacc_mean"], pooled["hacc_std"])
        kind = "summary"
    if not math.isfinite(mean):
        return None
    return {"n": pooled["n"], "mean": mean, "low": low, "high": high, "interval": kind, "clusters": clusters}


def stat_values(stats: Iterable[Mapping[str, Any] | None], lows: bool = True) -> list[float]:
    """The values a figure draws of :func:`group_stat`'s results: means and interval ends (``lows=False``:
    without the lower ends, which :func:`wants_log_axis` leaves out)."""
    keys = ("mean", "low", "high") if lows else ("mean", "high")
    return [st[k] for st in stats if st for k in keys]
