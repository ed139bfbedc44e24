"""Rerun logging of a trained model and a prediction (pushtorch.viz.contacts, .predictions, .densities,
.annealing), on a tiny real cube model.

The model is trained on real pybullet pushes and the prediction is made from a real single-shot
cloud; what is logged is read back from the saved ``.rrd`` with Rerun's own reader. The predicted
density's entities (draws, 90 % region, ghosts, mode, truth) are checked against draws made here with
the logger's seed, and logging is checked to leave the prediction and every caller's random stream as
they were.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.models.contact import closest_points_on_mesh
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.robot import bumper_mesh
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.runner import simulate_pushes
from pushtorch.viz import open_recording, read_entity_paths
from pushtorch.viz.annealing import ANNEAL_SERIES, ANNEAL_TIMELINE, log_anneal_history, log_anneal_series
from pushtorch.viz.contacts import TRAINING, log_contact_model
from pushtorch.viz.densities import (
    DENSITY_GHOSTS,
    DENSITY_REGION,
    DENSITY_SAMPLES,
    DENSITY_SEED,
    density_truth,
    draw_density,
)
from pushtorch.viz.helpers import range_colors, subsample
from pushtorch.viz.predictions import PREDICTION, log_prediction

SETTINGS = ModelSettings(
    query_kernels=300, anneal_candidates=50, anneal_steps=10, environment_kernels=500, manipulator_kernels=100
)
RECORDED_STEPS = SETTINGS.fast_anneal_steps + 2  # the initial candidates, every step, the polished ones

TRAINING_ENTITIES = (
    "object", "object/mesh", "object/axes", "contact/points", "contact/frames", "contact/implied_robot",
    "robot", "robot/chassis", "robot/axes", "bumper", "position/points", "position/frames",
)
DENSITY_ENTITIES = ("density/samples", "density/region_90", "density/ghosts", "density/mode", "density/mode/axes",
                    "density/truth", "density/truth/axes")
PREDICTION_ENTITIES = (
    "cloud", "robot", "robot/chassis", "robot/axes", "bumper",
    "manipulator_contact/frame", "manipulator_contact/relation",
    "environment_contacts/points", "environment_contacts/frames", "environment_contacts/relation",
    "initial_estimate", "initial_estimate/mesh", "initial_estimate/axes",
    "motion/experts", "motion/final_candidates",
    "final_predicted", "final_predicted/mesh", "final_predicted/axes",
    "initial_true", "initial_true/mesh", "final_true", "final_true/mesh", "initial_error", "final_error",
) + DENSITY_ENTITIES + tuple(ANNEAL_SERIES) + tuple(
    f"{query}/{part}" for query in ("robot_query", "pose_query")
    for part in ("features", "kernels", "candidates", "final_candidates")
)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A cube model from 3 actions x 10 real pushes, one prediction with history, and its ground truth."""
    cube = load_object("cube")
    actions = make_actions(3)
    plan = plan_training_pushes(cube, actions, 10, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    folder = tmp_path_factory.mktemp("pushes")
    run_plan(object_spec(cube), plan, folder, workers=1, progress=False)
    records = load_records(folder)
    model = train_push_model(cube, records, SETTINGS, generator=torch.Generator().manual_seed(0))
    truth_initial = cube.resting_pose(x=0.05, y=-0.02, yaw=0.3)
    cloud = capture_partial_cloud(cube, truth_initial)
    prediction = predict(model, cloud, actions[0], torch.Generator().manual_seed(1), record_history=True)
    outcome = simulate_pushes(cube, prediction.condition.robot_start, truth_initial, actions[0], 0.5, 0.3)
    truth_final = se3.Pose(outcome.object_final.p[0].float(), outcome.object_final.q[0].float())
    return dict(cube=cube, records=records, model=model, cloud=cloud, prediction=prediction,
                truth_initial=truth_initial, truth_final=truth_final, outcome=outcome)


def _rows(path, entity: str, component: str) -> list[tuple[int | None, list]]:
    """Every logged row of ``component`` (e.g. ``Points3D:positions``) at ``entity``: (anneal step, value)."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(str(path)).store().stream().to_chunks():
        if str(chunk.entity_path) != f"/{entity}":
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        values = batch.column(component).to_pylist()
        steps = (batch.column(ANNEAL_TIMELINE).to_pylist() if ANNEAL_TIMELINE in batch.schema.names
                 else [None] * len(values))
        rows.extend(zip(steps, values, strict=True))
    return rows


def _single(path, entity: str, component: str) -> np.ndarray:
    rows = _rows(path, entity, component)
    assert len(rows) == 1, (entity, component, len(rows))
    return np.asarray(rows[0][1], dtype=np.float64)


def test_contact_model_entities_and_training_placement(tmp_path, case):
    model, cube, records = case["model"], case["cube"], case["records"]
    path = tmp_path / "model.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_contact_model(rec, model, cube, max_points=1000, max_frames=50)
    rec.disconnect()  # writes the file's footer
    assert root == f"{TRAINING}/cube"
    paths = read_entity_paths(path)
    for child in TRAINING_ENTITIES:
        assert f"/{root}/{child}" in paths, child

    # The robot drawn is the training placement, recomputed here from the first valid record.
    valid = records.take(records.valid)
    placement = se3.relative(valid.object_initial.take(0), valid.robot_start.take(0))
    expected = se3.compose(cube.resting_pose(), placement)
    robot_p = _single(path, f"{root}/robot", "Transform3D:translation").reshape(3)
    np.testing.assert_allclose(robot_p[:2], expected.p[:2].numpy(), atol=1e-4)
    assert abs(robot_p[2]) < 1e-6

    # Every contact point shown is a model frame on the object within the cut-off of that bumper.
    points = _single(path, f"{root}/contact/points", "Points3D:positions").reshape(-1, 3)
    assert len(points) == min(len(model.contact.frames), 1000)
    bumper_at = se3.Pose(torch.tensor(robot_p, dtype=torch.float32), expected.q)
    _, distance = closest_points_on_mesh(bumper_mesh(bumper_at), torch.tensor(points, dtype=torch.float32))
    assert float(distance.max()) < model.settings.contact_cutoff + 1e-4
    frames = _single(path, f"{root}/contact/frames", "Arrows3D:vectors").reshape(-1, 3)
    assert len(frames) == 3 * min(len(model.contact.frames), 50)
    position = _single(path, f"{root}/position/points", "Points3D:positions").reshape(-1, 3)
    assert len(position) == min(len(model.position.frames), 1000)


def test_contact_model_follows_the_object_pose(tmp_path, case):
    """Drawn at another object pose, the frames and robot move with the object, rigidly."""
    model, cube = case["model"], case["cube"]
    moved = cube.resting_pose(x=1.0, y=0.5, yaw=1.2)
    path = tmp_path / "moved.rrd"
    rec = open_recording(path, "pushtorch_test")
    home = log_contact_model(rec, model, cube.mesh, label="home")
    away = log_contact_model(rec, model, cube.mesh, object_pose=moved, label="cube at (1, 0.5)")
    rec.disconnect()
    assert away == f"{TRAINING}/cube_at__1__0.5_"
    shift = se3.compose(moved, se3.inverse(cube.resting_pose()))
    transforms = [(e, "Transform3D:translation") for e in ("robot", "object")]
    points = [(e, "Points3D:positions") for e in ("contact/points", "position/points")]
    for entity, component in transforms + points:
        at_home = torch.tensor(_single(path, f"{home}/{entity}", component), dtype=torch.float32)
        at_home = at_home.reshape(-1, 3)
        at_away = _single(path, f"{away}/{entity}", component).reshape(-1, 3)
        np.testing.assert_allclose(at_away, se3.apply(shift, at_home).numpy(), atol=1e-4, err_msg=entity)


def test_prediction_entities_poses_and_annealing(tmp_path, case):
    prediction = case["prediction"]
    path = tmp_path / "prediction.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, prediction, case["truth_initial"], case["truth_final"], case["cube"],
                          label="cube push", cloud=case["cloud"], max_points=200)
    rec.disconnect()
    assert root == f"{PREDICTION}/cube_push"
    paths = read_entity_paths(path)
    for child in PREDICTION_ENTITIES:
        assert f"/{root}/{child}" in paths, child

    predicted = _single(path, f"{root}/final_predicted", "Transform3D:translation").reshape(3)
    np.testing.assert_allclose(predicted, prediction.final_pose.p.numpy(), atol=1e-6)
    error = _single(path, f"{root}/final_error", "LineStrips3D:strips").reshape(2, 3)
    np.testing.assert_allclose(error, np.stack([prediction.final_pose.p.numpy(),
                                                case["truth_final"].p.numpy()]), atol=1e-6)
    robot = _single(path, f"{root}/robot", "Transform3D:translation").reshape(3)
    np.testing.assert_allclose(robot, prediction.condition.robot_start.p.numpy(), atol=1e-6)

    # one row per annealing step (step 0: initial candidates) and the polished candidates, each with
    # every candidate
    steps = RECORDED_STEPS
    for query in ("robot_query", "pose_query"):
        rows = _rows(path, f"{root}/{query}/candidates", "Points3D:positions")
        assert sorted(step for step, _ in rows) == list(range(steps))
        assert all(len(points) == SETTINGS.anneal_candidates for _, points in rows)
        kernels = _single(path, f"{root}/{query}/kernels", "Points3D:positions").reshape(-1, 3)
        assert len(kernels) == min(SETTINGS.query_kernels, 200)
    # the last step of the robot query's history is where the chains ended
    last = dict(_rows(path, f"{root}/robot_query/candidates", "Points3D:positions"))[steps - 1]
    history = prediction.condition.robot_query.anneal.history
    np.testing.assert_allclose(np.asarray(last), history.p[-1].numpy(), atol=1e-6)
    # robot kernels are planar base poses: on the ground
    robot_kernels = _single(path, f"{root}/robot_query/kernels", "Points3D:positions").reshape(-1, 3)
    assert np.abs(robot_kernels[:, 2]).max() < 1e-6
    experts = _single(path, f"{root}/motion/experts", "Points3D:positions").reshape(-1, 3)
    assert 0 < len(experts) <= 200


def test_prediction_without_history_density_truth_or_mesh(tmp_path, case):
    """What is not there is not logged; the rest still is."""
    prediction = case["prediction"]
    condition = prediction.condition
    bare_anneal = dataclasses.replace(condition.robot_query.anneal, history=None, history_log_prob=None)
    bare_robot = dataclasses.replace(condition.robot_query, anneal=bare_anneal, density=None)
    bare = dataclasses.replace(prediction, condition=dataclasses.replace(condition, robot_query=bare_robot))
    path = tmp_path / "bare.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, bare)
    rec.disconnect()
    paths = read_entity_paths(path)
    for child in ("robot_query/candidates", "robot_query/kernels", "robot_query/features", "cloud",
                  "final_true", "initial_true", "final_error", "initial_error", "final_predicted/mesh"):
        assert f"/{root}/{child}" not in paths, child
    for child in ("robot_query/final_candidates", "pose_query/candidates", "pose_query/kernels", "robot",
                  "bumper", "final_predicted", "final_predicted/axes", "initial_estimate/axes",
                  "density/samples", "density/region_90", "density/ghosts", "density/mode"):
        assert f"/{root}/{child}" in paths, child
    assert f"/{root}/density/truth" not in paths  # no truth given
    assert not any(p.startswith(f"/{root}/collision_parts") for p in paths)  # no object given


def test_anneal_history_absent_returns_false(tmp_path, case):
    anneal = dataclasses.replace(case["prediction"].condition.pose_query.anneal, history=None)
    rec = open_recording(tmp_path / "h.rrd")
    assert log_anneal_history(rec, "world/h", anneal) is False
    assert log_anneal_history(rec, "world/h", case["prediction"].condition.pose_query.anneal) is True
    rec.disconnect()


def test_bad_arguments_raise(tmp_path, case):
    rec = open_recording(tmp_path / "bad.rrd")
    with pytest.raises(InvalidParameterError):
        log_prediction(rec, case["prediction"], max_points=0)
    with pytest.raises(InvalidParameterError):
        log_prediction(rec, case["prediction"], label="///")
    with pytest.raises(InvalidParameterError):  # every level needs a letter or digit
        log_prediction(rec, case["prediction"], label="part/../c0a1")
    with pytest.raises(InvalidParameterError):
        log_prediction(rec, case["prediction"], object_mesh="cube")
    with pytest.raises(InvalidParameterError):
        log_contact_model(rec, case["model"], case["cube"], max_frames=0)
    rec.disconnect()


@given(st.integers(0, 500), st.integers(1, 100))
def test_subsample_is_a_fixed_subset(n, limit):
    index = subsample(n, limit)
    assert len(index) == min(n, limit)
    assert torch.equal(index, torch.unique(index))  # sorted, no repeats
    assert len(index) == 0 or (0 <= int(index.min()) and int(index.max()) < n)
    assert torch.equal(index, subsample(n, limit))


@given(st.lists(st.one_of(st.floats(-1e6, 1e6), st.just(float("-inf"))), min_size=1, max_size=50))
def test_range_colors_span_viridis_and_mark_no_support_dark(values):
    colors = range_colors(torch.tensor(values, dtype=torch.float64))
    assert colors.shape == (len(values), 3) and colors.dtype == np.uint8
    darkest, brightest = range_colors(torch.tensor([0.0, 1.0]))
    finite = [v for v in values if np.isfinite(v)]
    for value, color in zip(values, colors, strict=True):
        if not np.isfinite(value) or (finite and value == min(finite)):
            assert np.array_equal(color, darkest)
        elif value == max(finite):
            assert np.array_equal(color, brightest)


def test_motion_annealing_is_logged_when_the_prediction_carries_it(tmp_path, case):
    """``motion/candidates`` appears exactly when the Prediction holds its motion AnnealResult."""
    prediction = case["prediction"]
    assert prediction.anneal is not None and prediction.anneal.history is not None
    path = tmp_path / "carrying.rrd"
    assert f"/{PREDICTION}/carrying/motion/candidates" in _logged(path, prediction, "carrying")
    rows = _rows(path, f"{PREDICTION}/carrying/motion/candidates", "Points3D:positions")
    assert sorted(step for step, _ in rows) == list(range(RECORDED_STEPS))
    plain = dataclasses.replace(prediction, anneal=None)
    assert f"/{PREDICTION}/plain/motion/candidates" not in _logged(tmp_path / "plain.rrd", plain, "plain")


def _logged(path, prediction, label: str) -> set[str]:
    rec = open_recording(path, "pushtorch_test")
    log_prediction(rec, prediction, label=label)
    rec.disconnect()
    return read_entity_paths(path)


def test_hierarchical_labels_nest_the_prediction(tmp_path, case):
    """``/`` in a label makes levels; each level is cleaned on its own; empty levels vanish."""
    path = tmp_path / "nested.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, case["prediction"], label="/friction_biasing/cube/friction:low//c0a1/")
    rec.disconnect()
    assert root == f"{PREDICTION}/friction_biasing/cube/friction_low/c0a1"
    assert f"/{root}/final_predicted" in read_entity_paths(path)


def test_annealing_series_are_the_best_log_likelihood_per_step(tmp_path, case):
    """``best_log_prob``: per step, the best of the chains' current log-likelihoods, and its running max."""
    prediction = case["prediction"]
    path = tmp_path / "series.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, prediction, label="series")
    bare = dataclasses.replace(prediction.anneal, history_log_prob=None)
    assert log_anneal_series(rec, "world/none", bare) is False
    rec.disconnect()
    for series, anneal in (("robot_query/best_log_prob", prediction.condition.robot_query.anneal),
                           ("pose_query/best_log_prob", prediction.condition.pose_query.anneal),
                           ("motion/best_log_prob", prediction.anneal)):
        rows = _rows(path, f"{root}/{series}", "Scalars:scalars")
        assert [step for step, _ in rows] == list(range(RECORDED_STEPS)), series
        logged = np.asarray([value for _, value in rows], dtype=np.float64)  # (steps, 2)
        history = anneal.history_log_prob.double().reshape(RECORDED_STEPS, -1)
        expected = history.max(dim=1).values
        expected = torch.where(torch.isfinite(expected), expected, torch.full_like(expected, float("nan")))
        np.testing.assert_allclose(logged[:, 0], expected.numpy(), rtol=1e-12, err_msg=series)
        so_far = np.fmax.accumulate(np.nan_to_num(logged[:, 0], nan=-np.inf))
        np.testing.assert_allclose(logged[:, 1], np.where(np.isfinite(so_far), so_far, np.nan), err_msg=series)
    assert f"/{PREDICTION}/none" not in read_entity_paths(path)


def test_prediction_plays_its_ground_truth_push(tmp_path, case):
    """With ``truth_push``, the push's object and robot move on ``sim_time`` under the prediction's root."""
    from pushtorch.viz.sim import SIM_TIMELINE

    outcome = case["outcome"]
    path = tmp_path / "truth_push.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, case["prediction"], case["truth_initial"], case["truth_final"], case["cube"],
                          label="pushed", truth_push=outcome)
    rec.disconnect()
    paths = read_entity_paths(path)
    for child in ("truth_push/object", "truth_push/object/mesh", "truth_push/robot", "truth_push/robot/chassis",
                  "truth_push/robot/bumper/mesh", "truth_push/object_path", "truth_push/robot_path"):
        assert f"/{root}/{child}" in paths, child
    assert f"/{root}/truth_push/object_final" not in paths  # final_true shows it already
    from rerun.chunk import RrdReader

    for entity, trajectory in (("object", outcome.object_trajectory), ("robot", outcome.robot_trajectory)):
        rows = []
        for chunk in RrdReader(str(path)).store().stream().to_chunks():
            if str(chunk.entity_path) == f"/{root}/truth_push/{entity}":
                batch = chunk.to_record_batch()
                if SIM_TIMELINE in batch.schema.names:
                    rows += batch.column("Transform3D:translation").to_pylist()
        np.testing.assert_allclose(np.asarray(rows).reshape(-1, 3), trajectory.p[0].numpy(), atol=1e-6)


def _points(path, entity: str) -> np.ndarray:
    return _single(path, entity, "Points3D:positions").reshape(-1, 3)


def test_density_draws_region_mode_and_truth(tmp_path, case):
    """The density's entities are draws made with the logger's own seed, the region their 90 % of highest
    log-density, the mode the predicted final pose and the truth the true motion from the estimate."""
    prediction, density = case["prediction"], case["prediction"].density
    path = tmp_path / "density.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, prediction, case["truth_initial"], case["truth_final"], case["cube"],
                          label="density", max_points=400, max_frames=10)
    rec.disconnect()
    n = min(DENSITY_SAMPLES, 400)
    draws = density.sample((n,), torch.Generator().manual_seed(DENSITY_SEED))
    samples = _points(path, f"{root}/density/samples")
    np.testing.assert_allclose(samples, draws[:, :3].numpy(), atol=1e-6)
    log_p = density.log_prob(draws).double()
    region = _points(path, f"{root}/density/region_90")
    assert len(region) == math.ceil(DENSITY_REGION * n)
    inside = {tuple(np.round(r, 6)) for r in region}
    outside = [k for k in range(n) if tuple(np.round(samples[k], 6)) not in inside]
    assert outside, "some draws lie outside the 90 % region"
    in_region = [k for k in range(n) if tuple(np.round(samples[k], 6)) in inside]
    assert float(log_p[in_region].min()) >= float(log_p[outside].max())
    ghosts = _single(path, f"{root}/density/ghosts", "Arrows3D:origins").reshape(-1, 3)
    assert len(ghosts) == 3 * min(DENSITY_GHOSTS, 10)
    np.testing.assert_allclose(ghosts[::3], draws[: len(ghosts) // 3, :3].numpy(), atol=1e-6)
    np.testing.assert_allclose(_points(path, f"{root}/density/mode"), prediction.final_pose.p.reshape(1, 3),
                               atol=1e-6)
    np.testing.assert_allclose(_points(path, f"{root}/density/mode"), density.mode[:3].reshape(1, 3), atol=1e-6)
    # the README's displaced truth: where the density scores the ground truth
    start, final = case["truth_initial"], case["truth_final"]
    moved = final.compose(start.inverse()).compose(prediction.condition.object_pose)
    truth = _points(path, f"{root}/density/truth")
    np.testing.assert_allclose(truth, moved.p.reshape(1, 3).numpy(), atol=1e-5)
    np.testing.assert_allclose(density_truth(prediction, final, start).vector(), moved.vector(), atol=1e-6)
    np.testing.assert_allclose(density_truth(prediction, final).vector(), final.vector(), atol=1e-6)


def test_draws_a_task_made_travel_with_its_examples_and_are_logged_as_drawn_here(tmp_path, case):
    """A cluster task saves its kept examples with their densities' draws (the submitting process only logs
    them): the draws loaded back are draw_density's, and a prediction logged with them shows the same samples,
    region and ghosts as one that draws while logging; draws of another count are drawn again."""
    from pushtorch.experiments.example_files import load_examples, save_examples
    from pushtorch.experiments.prediction_sets import Example

    prediction = case["prediction"]
    path = tmp_path / "examples.pt"
    save_examples(path, "set", {0}, [Example(0, 0, prediction, case["cloud"])])
    (example,) = load_examples(path, "set", {0})
    draws, log_p = draw_density(prediction.density)
    assert draws.shape == (DENSITY_SAMPLES, 7) and log_p.dtype == torch.float64
    assert torch.equal(example.drawn[0], draws) and torch.equal(example.drawn[1], log_p)
    assert example.residual is None and example.residual_drawn is None
    recording = tmp_path / "drawn.rrd"
    rec = open_recording(recording, "pushtorch_test")
    here = log_prediction(rec, prediction, label="here")
    there = log_prediction(rec, example.prediction, label="there", drawn=example.drawn)
    fewer = log_prediction(rec, prediction, label="fewer", max_points=50, drawn=example.drawn)
    rec.disconnect()
    for entity in ("density/samples", "density/region_90"):
        np.testing.assert_array_equal(_points(recording, f"{there}/{entity}"), _points(recording, f"{here}/{entity}"))
    np.testing.assert_array_equal(_single(recording, f"{there}/density/ghosts", "Arrows3D:origins"),
                                  _single(recording, f"{here}/density/ghosts", "Arrows3D:origins"))
    assert len(_points(recording, f"{fewer}/density/samples")) == 50


def test_logging_changes_neither_the_prediction_nor_any_random_stream(tmp_path, case):
    """A prediction logged and its twin not logged (same model, cloud, seed): same final pose and density,
    and the callers' generators, used on after the prediction, draw the same; torch's and numpy's global
    streams are untouched."""
    model, cloud = case["model"], case["cloud"]
    action = make_actions(3)[0]
    logged_stream, plain_stream = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    logged = predict(model, cloud, action, logged_stream, record_history=True)
    plain = predict(model, cloud, action, plain_stream, record_history=True)
    final_before = logged.final_pose.vector().clone()
    probe = logged.density.sample((32,), torch.Generator().manual_seed(5))
    log_p_before = logged.density.log_prob(probe)
    torch_state, numpy_state = torch.get_rng_state(), np.random.get_state()
    path = tmp_path / "unchanged.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, logged, case["truth_initial"], case["truth_final"], case["cube"], label="logged",
                          max_points=300)
    again = log_prediction(rec, logged, label="again", max_points=300)
    rec.disconnect()
    assert torch.equal(torch.get_rng_state(), torch_state)
    after = np.random.get_state()
    assert after[0] == numpy_state[0] and np.array_equal(after[1], numpy_state[1]) and after[2:] == numpy_state[2:]
    assert torch.equal(logged.final_pose.vector(), final_before)
    assert torch.equal(logged.final_pose.vector(), plain.final_pose.vector())
    assert torch.equal(logged.candidates.vector(), plain.candidates.vector())
    assert torch.equal(logged.density.sample((32,), torch.Generator().manual_seed(5)), probe)
    torch.testing.assert_close(logged.density.log_prob(probe), log_p_before, rtol=0, atol=0)
    torch.testing.assert_close(plain.density.log_prob(probe), log_p_before, rtol=0, atol=0)
    # the callers' streams go on alike: a draw from the density and a plain draw
    assert torch.equal(logged.density.sample((16,), logged_stream), plain.density.sample((16,), plain_stream))
    assert torch.equal(torch.rand(8, generator=logged_stream), torch.rand(8, generator=plain_stream))
    # and two recordings of one prediction show the same draws
    np.testing.assert_array_equal(_points(path, f"{root}/density/samples"),
                                  _points(path, f"{again}/density/samples"))


def test_collision_parts_are_shown_when_the_object_has_several(tmp_path, case):
    """modified_cube is simulated as its catalogue pieces: each is a mesh under ``collision_parts``, at the
    true initial pose; an object of one part (the cube) logs none."""
    modified = load_object("modified_cube")
    assert len(modified.collision_parts) > 1
    path = tmp_path / "parts.rrd"
    rec = open_recording(path, "pushtorch_test")
    several = log_prediction(rec, case["prediction"], case["truth_initial"], object_mesh=modified, label="several")
    one = log_prediction(rec, case["prediction"], case["truth_initial"], object_mesh=case["cube"], label="one")
    rec.disconnect()
    paths = read_entity_paths(path)
    for k, part in enumerate(modified.collision_parts):
        vertices = _single(path, f"{several}/collision_parts/part_{k}", "Mesh3D:vertex_positions").reshape(-1, 3)
        np.testing.assert_allclose(vertices, np.asarray(part.vertices), atol=1e-6)
    assert f"/{several}/collision_parts/part_{len(modified.collision_parts)}" not in paths
    at = _single(path, f"{several}/collision_parts", "Transform3D:translation").reshape(3)
    np.testing.assert_allclose(at, case["truth_initial"].p.numpy(), atol=1e-6)
    assert not any(p.startswith(f"/{one}/collision_parts") for p in paths)


class _Undrawable:
    """A density with a mode and no support anywhere (its sampler raises as FinalPoseDistribution's does)."""

    def __init__(self, mode: torch.Tensor) -> None:
        self.mode, self.batch_shape = mode, torch.Size()

    def sample(self, shape, generator=None):
        raise ModelError("no proposal has non-zero density under the product of experts")


def test_a_density_without_draws_logs_its_mode_only(tmp_path, case):
    prediction = case["prediction"]
    bare = dataclasses.replace(prediction, density=_Undrawable(prediction.final_pose.vector()))
    path = tmp_path / "undrawable.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_prediction(rec, bare, case["truth_initial"], case["truth_final"], label="undrawable")
    rec.disconnect()
    paths = read_entity_paths(path)
    assert {f"/{root}/density/mode", f"/{root}/density/truth"} <= paths
    assert f"/{root}/density/samples" not in paths and f"/{root}/density/region_90" not in paths
