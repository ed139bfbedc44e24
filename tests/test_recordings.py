"""Recordings that open ready to review: blueprint, ground-truth push on ``sim_time``, scalar series.

A tiny real model-selection part (real pybullet pushes, a real trained cube model, real predictions and
ground truth) runs through :func:`pushtorch.experiments.suite.run_suite`; its ``recording.rrd`` is read
back with Rerun's own reader. The blueprint is stored in the file as a separate *blueprint* store (same
application id as the recording), so it is read from ``RrdReader.blueprints()``, not from the recording's
chunks. Every logged prediction shows its density and its nll; a second run of two test conditions logs
the worst one (``recording.conditions=worst:1``), predicted again with the set's seeds.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from pushtorch.apps.config_check import ConfigError, check_config
from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.common import (
    LogConditions,
    PredictionSet,
    compare_displacement,
    entity_label,
    load_arrays,
)
from pushtorch.experiments.suite import run_suite
from pushtorch.sim.records import load_records
from pushtorch.viz import entity_name, open_recording
from pushtorch.viz.annealing import ANNEAL_SERIES, ANNEAL_TIMELINE
from pushtorch.viz.blueprint import pushes_blueprint, read_blueprint
from pushtorch.viz.predictions import PREDICTION
from pushtorch.viz.scores import GROUP_TIMELINE, hacc_root, part_summary_path
from pushtorch.viz.sim import SIM_TIMELINE

CONF = Path(__file__).resolve().parents[1] / "conf"
#: The suffix of the default world's caches (the truth in MuJoCo: pushtorch.experiments.training.engine_tag).
WORLD = "_mujoco"
TINY_SELECTION = [
    "experiment=model_selection",
    "experiment.progress=false",
    "experiment.workers=1",
    "experiment.actions.count=2",
    "experiment.training_objects=[cube]",
    "experiment.objects=[cube]",
    "experiment.methods=[adaptive]",
    "experiment.test_conditions=1",
    "experiment.truth_samples=2",
    "model=tiny",  # conf/model/tiny.yaml: the default model at the smallest sizes
]


def _chunks(path):
    from rerun.chunk import RrdReader

    return RrdReader(str(path)).store().stream().to_chunks()


def _columns(path, entity: str) -> dict[str, list]:
    """The rows logged at ``entity`` (no leading ``/``), by column; a column a chunk lacks is None there."""
    import pyarrow as pa

    rows: list[dict] = []
    for chunk in _chunks(path):
        if str(chunk.entity_path) == f"/{entity}":
            batch = chunk.to_record_batch()
            # timelines as integers (ns for durations): arrow's temporal → Python conversion can refuse ns
            batch = pa.RecordBatch.from_arrays(
                [c.cast(pa.int64()) if pa.types.is_temporal(c.type) else c for c in batch.columns],
                schema=pa.schema([pa.field(f.name, pa.int64()) if pa.types.is_temporal(f.type) else f
                                  for f in batch.schema]),
            )
            rows.extend(batch.to_pylist())
    names = {name for row in rows for name in row}
    return {name: [row.get(name) for row in rows] for name in names}


def _present(values: list) -> list:
    return [v for v in values if v is not None]


@pytest.fixture(scope="module")
def selection_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("selection")
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=TINY_SELECTION)
    summary = run_suite(cfg, out, [("model_selection", cfg.experiment, cfg.model)])
    return out, summary


def test_the_experiment_recording_ships_its_blueprint(selection_run):
    out, _ = selection_run
    blueprint = read_blueprint(out / "recording.rrd")
    assert blueprint["timeline"] == SIM_TIMELINE
    views = blueprint["views"]
    part = f"{PREDICTION}/model_selection"
    by_class = {kind: [v for v in views if v["class"] == kind] for kind in ("3D", "TimeSeries", "TextDocument")}
    assert {v["origin"] for v in by_class["3D"]} >= {part, "world/model/training"}
    assert [v["origin"] for v in by_class["TextDocument"]] == [part_summary_path("model_selection")]
    series_origins = [v["origin"] for v in by_class["TimeSeries"]]
    assert hacc_root("model_selection") in series_origins
    # one annealing view per annealing, each listing the series of every logged prediction
    annealing = [v for v in by_class["TimeSeries"] if v["origin"] == part]
    assert len(annealing) == len(ANNEAL_SERIES)
    roots = [f"{part}/cube/adaptive/c0a{j}" for j in range(2)]
    assert sorted(q for v in annealing for q in v["contents"]) == sorted(
        f"/{root}/{series}" for root in roots for series in ANNEAL_SERIES)


def test_predictions_are_hierarchical_and_play_their_ground_truth_push(selection_run):
    out, _ = selection_run
    root = f"{PREDICTION}/{entity_label('model_selection', 'cube', 'adaptive')}/c0a1"
    assert root == f"{PREDICTION}/model_selection/cube/adaptive/c0a1"
    paths = {str(chunk.entity_path) for chunk in _chunks(out / "recording.rrd")}
    assert not any("model_selection." in p for p in paths)  # no dotted flat names left
    for child in ("final_true", "final_predicted", "summary", "truth_push/object", "truth_push/object/mesh",
                  "truth_push/robot", "truth_push/robot/bumper/mesh", "truth_push/object_path"):
        assert f"/{root}/{child}" in paths, child

    # the object's transform per recorded time on sim_time, from its start to the push's end (4 s)
    obj = _columns(out / "recording.rrd", f"{root}/truth_push/object")
    seconds = np.asarray(_present(obj[SIM_TIMELINE])) / 1e9
    assert len(seconds) == 4 * 10 + 1 and seconds[0] == 0 and abs(seconds[-1] - 4.0) < 1e-9
    translations = np.asarray([v for v in obj["Transform3D:translation"] if v is not None]).reshape(-1, 3)
    # it starts where the true initial pose is (the recorded test pose) ...
    initial = np.asarray(_columns(out / "recording.rrd", f"{root}/initial_true")["Transform3D:translation"][0])
    np.testing.assert_allclose(translations[0], initial.reshape(3), atol=1e-6)
    # ... and the recorded trajectory is the one simulate_truth stored for condition 0, action 1, sample 0
    truth = load_records(out / "truth" / f"model_selection_cube_adaptive{WORLD}", dtype=torch.float64)
    samples = 2
    recorded = truth.object_trajectory.take(1 * samples).p.numpy()
    np.testing.assert_allclose(translations, recorded, atol=1e-6)  # float32 in the recording
    # the re-simulated final pose is the recorded one, bit for bit (the summary says so)
    summary = _columns(out / "recording.rrd", f"{root}/summary")["TextDocument:text"][0]
    summary = summary[0] if isinstance(summary, list) else summary
    assert "ends at the recorded final pose" in summary
    final_true = np.asarray(_columns(out / "recording.rrd", f"{root}/final_true")["Transform3D:translation"][0])
    np.testing.assert_array_equal(final_true.reshape(3),
                                  truth.object_final.take(1 * samples).p.float().numpy())


def test_annealing_and_hacc_series_are_logged(selection_run):
    out, _ = selection_run
    root = f"{PREDICTION}/model_selection/cube/adaptive/c0a0"
    for series in ANNEAL_SERIES:
        columns = _columns(out / "recording.rrd", f"{root}/{series}")
        steps = [s for s in columns[ANNEAL_TIMELINE] if s is not None]
        values = [v for v in columns["Scalars:scalars"] if v is not None]
        assert steps == list(range(len(steps))) and len(steps) > 2, series
        best = np.asarray(values, dtype=np.float64)  # (steps, 2): step best, best so far
        assert best.shape == (len(steps), 2)
        finite = np.isfinite(best[:, 1])
        assert finite.any() and np.all(np.diff(best[finite, 1]) >= 0), series  # best so far never drops
        assert "SeriesLines:names" in columns
    # one H_acc point per results.json record, at the record's index on the group timeline
    records = json.loads((out / "results.json").read_text())["records"]
    for index, record in enumerate(records):
        path = f"{hacc_root('model_selection')}/{entity_name(record['object'])}/{record['method']}/{record['metric']}"
        columns = _columns(out / "recording.rrd", path)
        assert [s for s in columns[GROUP_TIMELINE] if s is not None] == [index]
        value = [v for v in columns["Scalars:scalars"] if v is not None][0]
        assert value == pytest.approx([record["hacc_mean"]])
    assert "TextDocument:text" in _columns(out / "recording.rrd", part_summary_path("model_selection"))


DENSITY = ("density/samples", "density/region_90", "density/ghosts", "density/mode", "density/truth")


def _logged_roots(path) -> list[str]:
    """The root of every logged prediction: the parent of each ``.../c<i>a<j>/summary``."""
    paths = {str(chunk.entity_path) for chunk in _chunks(path)}
    return sorted(p[1:-len("/summary")] for p in paths
                  if p.startswith(f"/{PREDICTION}/") and re.search(r"/c\d+a\d+/summary$", p))


def _summary(path, root: str) -> str:
    text = _columns(path, f"{root}/summary")["TextDocument:text"][0]
    return text[0] if isinstance(text, list) else text


def test_every_logged_prediction_shows_its_density_and_nll(selection_run):
    out, _ = selection_run
    path = out / "recording.rrd"
    roots = _logged_roots(path)
    assert roots == [f"{PREDICTION}/model_selection/cube/adaptive/c0a{j}" for j in range(2)]
    paths = {str(chunk.entity_path) for chunk in _chunks(path)}
    scores, _ = load_arrays(out / "scores" / f"model_selection_cube_adaptive{WORLD}.npz")
    for j, root in enumerate(roots):
        shown = {p for p in paths if p.startswith(f"/{root}/") and "density" in p}
        assert {f"/{root}/{child}" for child in DENSITY} <= shown, root
        samples = _columns(path, f"{root}/density/samples")["Points3D:positions"]
        assert len(_present(samples)[0]) == 1000
        # the summary's nll is the record's score of the truth it shows (condition 0, action j, sample 0)
        summary = _summary(path, root)
        nll = re.search(r"nll (-?\d+\.\d+) nats", summary)
        assert nll, summary
        assert float(nll.group(1)) == pytest.approx(float(scores["pushtorch"][0, 0, j, 0]), abs=0.006)
        assert re.search(r"H_acc \d+\.\d+ \(displacement; frame \d+\.\d+\)", summary), summary


@pytest.fixture(scope="module")
def worst_run(selection_run, tmp_path_factory):
    """The tiny part with two test conditions, logging the worst one; training reused from the first run."""
    first, _ = selection_run
    out = tmp_path_factory.mktemp("worst")
    for folder in ("data", "models"):
        shutil.copytree(first / folder, out / folder)
    overrides = [o for o in TINY_SELECTION if not o.startswith("experiment.test_conditions=")]
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=overrides + ["experiment.test_conditions=2",
                                                       "recording.conditions=worst:1"])
    run_suite(cfg, out, [("model_selection", cfg.experiment, cfg.model)])
    return out


def test_worst_logs_the_condition_of_highest_hacc_as_the_set_predicted_it(worst_run):
    out = worst_run
    key = f"model_selection_cube_adaptive{WORLD}"
    predictions = PredictionSet.load(out / "predictions" / f"{key}.npz")
    n, a_count = predictions.final.batch_shape
    assert (n, a_count) == (2, 2)
    records = load_records(out / "truth" / key)
    truth = records.object_final.reshape(n, a_count, 2)  # one truth condition, 2 samples
    from pushtorch.objects import load_object

    acc = compare_displacement(predictions.estimate, predictions.final, predictions.truth_initial, truth,
                               load_object("cube"))
    hacc = acc.hacc.double().reshape(n, a_count, 2).mean((1, 2))
    worst = int(hacc.argmax())
    path = out / "recording.rrd"
    roots = _logged_roots(path)
    assert roots == [f"{PREDICTION}/model_selection/cube/adaptive/c{worst}a{j}" for j in range(a_count)]
    for j, root in enumerate(roots):
        # predicted again with the set's seeds: the very prediction the set holds
        final = np.asarray(_columns(path, f"{root}/final_predicted")["Transform3D:translation"][0]).reshape(3)
        np.testing.assert_allclose(final, predictions.final.take((worst, j)).p.numpy(), atol=1e-6)
        assert {f"/{root}/{child}" for child in DENSITY} <= {str(c.entity_path) for c in _chunks(path)}
        summary = _summary(path, root)
        assert f"worst:1: mean H_acc {float(hacc[worst]):.3f}" in summary, summary


def test_log_conditions_parse_and_choose():
    hacc = torch.tensor([0.3, 0.9, 0.1, 0.9, float("nan")])
    assert LogConditions.parse(None, 2).choose(hacc) == [0, 1]
    assert LogConditions.parse("first:9").choose(hacc) == [0, 1, 2, 3, 4]
    assert LogConditions.parse("worst:3").choose(hacc) == [4, 1, 3]  # NaN worst; ties to the lower index
    assert LogConditions.parse("best:2").choose(hacc) == [2, 0]
    assert LogConditions.parse([3, 0, 7]).choose(hacc) == [3, 0]  # in the order given; 7 is not there
    assert LogConditions.parse([]).choose(hacc) == []
    assert LogConditions.parse("worst:2").known_before_truth(5) == []
    assert LogConditions.parse([3, 0]).known_before_truth(2) == [0]
    for bad in (2, "2", "wurst:2", "worst:", "worst:-1", "first:101", [0, 0], [-1], [0.5], True, {"k": 1}):
        with pytest.raises(InvalidParameterError):
            LogConditions.parse(bad)


@pytest.mark.parametrize("value, fragment", [
    ("2", "write first:2"),
    ("wurst:2", "must be first:k, worst:k or best:k"),
    ("[0,0]", "twice"),
    ("[0,5]", "no part has more than 1"),
])
def test_config_check_refuses_a_malformed_recording_choice_in_one_line(value, fragment):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=TINY_SELECTION + [f"recording.conditions={value}"])
    with pytest.raises(ConfigError) as error:
        check_config(cfg, "config")
    message = str(error.value)
    assert "recording.conditions" in message and fragment in message and "\n" not in message
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        good = compose("config", overrides=TINY_SELECTION + ["recording.conditions=best:1"])
    check_config(good, "config")


def test_a_pushes_recording_ships_its_blueprint(tmp_path):
    """The smallest case: a blueprint sent before disconnect is in the file, in its own store."""
    from rerun.chunk import RrdReader

    path = tmp_path / "pushes.rrd"
    rec = open_recording(path, "pushtorch_test")
    rec.send_blueprint(pushes_blueprint())
    rec.disconnect()
    reader = RrdReader(str(path))
    assert [s.application_id for s in reader.blueprints()] == ["pushtorch_test"]
    blueprint = read_blueprint(path)
    assert blueprint["timeline"] == SIM_TIMELINE
    assert [(v["class"], v["origin"]) for v in blueprint["views"]] == [("3D", "world/sim")]


def test_a_recording_without_blueprint_reads_back_empty(tmp_path):
    path = tmp_path / "bare.rrd"
    rec = open_recording(path, "pushtorch_test")
    rec.disconnect()
    assert read_blueprint(path) == {"views": [], "timeline": None}

