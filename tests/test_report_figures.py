"""The report's figures (pushtorch.experiments.report): one colour per method and per prior, intervals that
never go below zero, the log-axis rule, per-sample values kept for redrawing, and figures written from real
record dicts (made by the experiments' own compare and summarise from simulated-looking poses)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.experiments import report, statistics, tables
from pushtorch.experiments.common import compare, summarise
from pushtorch.objects import load_object
from pushtorch.viz import colours

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "docs" / "results" / "paper"
METHODS = ("pushtorch", "no_motion", "mean_motion", "nominal_physics", "centroid", "position_model", "congruent",
           "incongruent", "adaptive", "nearest_push", "physics_from_cloud", "oracle_physics", "online", "general")
PRIORS = ("general", "low", "medium", "high", "paper_default", "selection")
PNG = b"\x89PNG\r\n\x1a\n"


def test_every_method_and_prior_has_its_own_colour():
    method_colours = [report.colour_of(m, "method") for m in METHODS]
    prior_colours = [report.colour_of(p, "prior") for p in PRIORS]
    assert len(set(method_colours + prior_colours)) == len(METHODS) + len(PRIORS)
    assert set(METHODS) <= set(report.METHOD_COLOURS) and set(PRIORS) <= set(report.PRIOR_COLOURS)
    # "general" is both a (future) method and a prior: the two must not look alike
    assert report.colour_of("general", "method") != report.colour_of("general", "prior")
    # a prior is named by its results label in the biasing figures
    assert report.colour_of("friction:low", "prior") == report.colour_of("mass:low", "prior") == \
        report.PRIOR_COLOURS["low"]
    # spares for unknown names: none of them is a known method's or prior's colour
    known = set(report.METHOD_COLOURS.values()) | set(report.PRIOR_COLOURS.values())
    spares = set(colours._SPARE_METHOD_COLOURS) | set(colours._SPARE_PRIOR_COLOURS)
    assert not spares & known
    assert not set(colours._SPARE_METHOD_COLOURS) & set(colours._SPARE_PRIOR_COLOURS)
    with pytest.raises(ValueError):
        report.colour_of("pushtorch", "model")


def test_unknown_names_get_a_stable_colour_of_their_kind():
    method = report.colour_of("some_future_method", "method")
    prior = report.colour_of("friction:very_high", "prior")
    spare = colours._SPARE_METHOD_COLOURS
    assert method == spare[zlib.crc32(b"some_future_method") % len(spare)]
    assert prior in colours._SPARE_PRIOR_COLOURS
    # the same in another interpreter with another string-hash seed (Python's hash() would not be)
    code = ("import importlib.util as u, sys; spec = u.spec_from_file_location('report', sys.argv[1]); "
            "m = u.module_from_spec(spec); spec.loader.exec_module(m); "  # the module alone: no torch import
            "print(m.colour_of('some_future_method'), m.colour_of('friction:very_high', 'prior'))")
    out = subprocess.run([sys.executable, "-c", code, report.__file__], capture_output=True, text=True,
                         check=True, cwd=ROOT, env={**os.environ, "PYTHONHASHSEED": "12345"}).stdout.split()
    assert out == [method, prior]


non_negative = st.floats(0.0, 1e4, allow_nan=False, allow_infinity=False)


@given(st.lists(non_negative, min_size=1, max_size=40))
def test_bootstrap_interval_is_non_negative_and_covers_the_mean(values):
    mean, low, high = report.mean_interval(values, resamples=200)
    assert mean == pytest.approx(float(np.mean(values)), rel=1e-9, abs=1e-12)
    assert 0.0 <= low <= mean <= high
    assert high <= max(values) + 1e-9  # every bootstrap mean is a mean of the data
    assert report.mean_interval(values, resamples=200) == (mean, low, high)  # seeded


@given(st.lists(st.lists(non_negative, min_size=1, max_size=4), min_size=1, max_size=20))
def test_clustered_bootstrap_resamples_whole_rows(rows):
    mean, low, high = report.mean_interval(rows, resamples=200)
    flat = [v for row in rows for v in row]
    assert mean == pytest.approx(float(np.mean(flat)), rel=1e-9, abs=1e-12)
    assert 0.0 <= low <= mean <= high


def test_clusters_widen_the_interval_of_correlated_comparisons():
    rng = np.random.default_rng(3)
    predictions = rng.exponential(0.2, size=60)
    rows = np.repeat(predictions[:, None], 4, axis=1)  # each prediction compared with 4 near-equal truths
    rows = rows + rng.uniform(0.0, 0.001, size=rows.shape)
    _, low_rows, high_rows = report.mean_interval(rows)
    _, low_flat, high_flat = report.mean_interval(rows.reshape(-1))
    assert high_rows - low_rows > 1.5 * (high_flat - low_flat)


def test_heavy_tailed_errors_keep_the_interval_above_zero():
    values = [0.0] * 995 + [5000.0] * 5  # a few thrown pushes among perfect predictions
    mean, low, high = report.mean_interval(values)
    assert low >= 0.0 and low <= mean <= high


@given(st.integers(1, 5000), st.floats(0.0, 100.0), st.floats(0.0, 1000.0))
def test_summary_interval_is_positive_and_covers_the_mean(n, mean, std):
    m, low, high = report.summary_interval(n, mean, std)
    assert m == mean and 0.0 <= low <= mean <= high


def test_summary_interval_matches_the_normal_one_for_large_n():
    _, low, high = report.summary_interval(10_000, 1.0, 0.5)
    se = 0.5 / math.sqrt(9_999)
    assert low == pytest.approx(1.0 - 1.96 * se, rel=1e-3) and high == pytest.approx(1.0 + 1.96 * se, rel=1e-3)
    assert report.summary_interval(1, 0.35, 0.0) == (0.35, 0.35, 0.35)


def test_log_axis_only_where_values_span_decades():
    assert report.wants_log_axis([0.056, 0.83, 180.0])  # model selection: congruent against incongruent
    assert not report.wants_log_axis([0.055, 0.06, 0.8])  # one biasing figure's bars
    assert not report.wants_log_axis([0.0, 0.0, 0.5, 5.0])  # zeros have no place on a log axis
    assert not report.wants_log_axis([float("nan"), 1.0])


def _prediction_run(obj_name: str = "cube", predictions: int = 6, samples: int = 3):
    """Records and extras as biasing.run_part makes them: compare and summarise on poses a push apart."""
    obj = load_object(obj_name)
    generator = torch.Generator().manual_seed(0)
    records, extras = [], {"hacc_samples": [], "training_scatter": {}, "training_actions": {}}
    start = obj.resting_pose(0.0, 0.0, 0.0)
    for m, model in enumerate(("friction:general", "friction:low")):
        for c, condition in enumerate(("friction:low", "friction:high")):
            truth_p = start.p + torch.tensor([0.4, 0.0, 0.0]) + 0.02 * torch.randn(predictions, samples, 3,
                                                                                  generator=generator)
            truth_p[..., 2] = start.p[2]
            truth = se3.Pose(truth_p, start.q.expand(predictions, samples, 4))
            offsets = {"pushtorch": 0.01 * (1 + m + c), "no_motion": 0.4, "mean_motion": 0.03,
                       "oracle_physics": 0.05}
            for method, offset in offsets.items():
                estimate = se3.Pose(truth_p[:, 0] + torch.tensor([offset, 0.0, 0.0]), start.q.expand(predictions, 4))
                acc = compare(estimate, truth, obj)
                records.append(summarise("prediction", obj_name, method, acc, model, condition))
                extras["hacc_samples"].append(report.sample_entry(records[-1], acc.hacc.reshape(-1, samples)))
    rng = np.random.default_rng(1)
    for label in ("friction:general", "friction:low"):
        actions = np.repeat([0, 1, 2], 10)
        points = np.stack([0.4 + 0.01 * rng.standard_normal(30), 0.2 * (actions - 1) + 0.01 * rng.standard_normal(30)],
                          axis=1)
        points[0] = [3.0, -2.0]  # one thrown push: outside the view, counted in the caption
        extras["training_scatter"].setdefault("friction_biasing", {}).setdefault(obj_name, {})[label] = \
            points.tolist()
        extras["training_actions"].setdefault("friction_biasing", {}).setdefault(obj_name, {})[label] = \
            actions.tolist()
    return records, extras


def test_figures_from_real_records_with_per_sample_values(tmp_path):
    records, extras = _prediction_run()
    outputs = report.write_outputs(tmp_path, "tiny", {}, 1.0, records, extras)
    names = {p.name for p in outputs["figures"]}
    assert names == {"friction_biasing.png", "friction_baselines.png", "objects.png",
                     "training_friction_biasing_cube.png"}
    text = outputs["report"].read_text()
    for path in outputs["figures"]:
        assert path.read_bytes()[:8] == PNG and f"figures/{path.name}" in text
    # the per-sample values are kept, and read back as the extras they were
    back = report.read_figure_data(outputs["figure_data"])
    assert len(back["hacc_samples"]) == len(extras["hacc_samples"])
    for saved, kept in zip(back["hacc_samples"], extras["hacc_samples"], strict=True):
        assert {k: saved[k] for k in statistics.SAMPLE_KEYS} == {k: kept[k] for k in statistics.SAMPLE_KEYS}
        np.testing.assert_allclose(saved["hacc"], kept["hacc"], rtol=1e-6)
    assert back["training_actions"] == extras["training_actions"]
    samples = statistics.samples_by_record(records, back)
    assert all(statistics.record_key(r) in samples for r in records)
    stat = statistics.group_stat(records, samples, method="pushtorch")
    pooled = report.pool(tables.select(records, method="pushtorch"))
    assert stat["interval"] == "bootstrap" and stat["n"] == pooled["n"]
    assert 0.0 <= stat["low"] <= stat["mean"] <= stat["high"]
    assert stat["mean"] == pytest.approx(pooled["hacc_mean"], rel=1e-5)


def test_figures_from_committed_paper_records_alone(tmp_path):
    """The committed paper runs keep results.json only: the bar figures are drawn with summary intervals."""
    records = []
    for name in ("model_selection", "pose_estimation"):
        records += json.loads((PAPER / name / "results.json").read_text())["records"]
    friction = json.loads((PAPER / "friction_biasing" / "results.json").read_text())["records"]
    records += [r for r in friction if r["object"] in ("cube", "cylinder")]
    paths = report.make_figures(tmp_path, records, {})
    assert {p.name for p in paths} == {"model_selection.png", "pose_estimation.png", "friction_biasing.png",
                                       "friction_baselines.png", "objects.png"}
    assert all(p.read_bytes()[:8] == PNG for p in paths)
    assert report.write_figure_data(tmp_path, {}) is None
    selection = [r for r in records if r["task"] == "selection"]
    stats = [statistics.group_stat(selection, {}, object=o, method=m)
             for o in ("cube", "cylinder") for m in ("congruent", "incongruent")]
    assert report.wants_log_axis(statistics.stat_values(stats, lows=False))
    assert min(statistics.stat_values(stats)) > 0  # summary intervals stay above zero
