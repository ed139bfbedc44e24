"""Predictions from a robot start the caller gives (issue 17's placement_spread test set): the manipulator
frame the cloud shows at that start, no robot query, the start used as given, and clear errors for a start
that touches nothing or sits inside the object. Real meshes, single-shot clouds and models trained on real
pybullet pushes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import trimesh

from pushtorch import robot, se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.features import compute_surface_features
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import manipulator_frame_at, manipulator_frames_at, predict, predict_many
from pushtorch.sim.push import place_robot_against


@pytest.fixture(scope="module")
def cube_scene():
    cube = load_object("cube")
    pose = cube.resting_pose()
    cloud = capture_partial_cloud(cube, pose, generator=torch.Generator().manual_seed(0))
    return cube, pose, cloud


@pytest.mark.parametrize("lateral", [-0.08, 0.0, 0.06])
def test_the_manipulator_frame_is_a_feature_touching_the_bumper_where_it_was_placed(cube_scene, lateral):
    cube, pose, cloud = cube_scene
    features = compute_surface_features(cloud)
    start = place_robot_against(cube.mesh, pose, 0.0, lateral, gap=0.002)
    frame = manipulator_frame_at(features, start)
    assert len(frame) == 1 and float(frame.weight[0]) > 0
    in_robot = se3.apply(se3.inverse(start), frame.v.p[0])
    bumper = robot.bumper_geometry()
    half_width = float(bumper.size[1]) / 2
    assert abs(float(in_robot[1])) <= half_width + 0.01  # on the plate's width
    # the relation reproduces the start: v ∘ u = R0
    entity = se3.compose(frame.v, frame.u)
    assert torch.allclose(entity.p[0], start.p, atol=1e-5)
    assert float(se3.angle_between(entity.q[0], start.q)) < 1e-3


def test_many_starts_get_each_its_own_frame_or_error_in_one_call(cube_scene):
    """The batched frames are each start's alone: the same as one start at a time, for touching starts, one
    5 m away (touches nothing) and one driven into the cube (overlaps it)."""
    cube, pose, cloud = cube_scene
    features = compute_surface_features(cloud)
    touching = [place_robot_against(cube.mesh, pose, yaw, lateral, gap=0.002)
                for yaw, lateral in ((0.0, -0.08), (0.3, 0.0), (-0.2, 0.05))]
    far = se3.Pose(touching[0].p + torch.tensor([5.0, 0.0, 0.0], dtype=touching[0].p.dtype), touching[0].q)
    heading = float(se3.yaw_of(touching[1].q))
    inside = se3.Pose(touching[1].p + 0.15 * torch.tensor([math.cos(heading), math.sin(heading), 0.0],
                                                          dtype=touching[1].p.dtype), touching[1].q)
    starts = [touching[0], far, touching[1], inside, touching[2]]
    frames, errors = manipulator_frames_at(features, starts)
    assert [type(e).__name__ if e else None for e in errors] == [None, "ModelError", None, "InvalidPoseError", None]
    assert frames[1] is None and frames[3] is None and "touches none" in str(errors[1])
    for start, frame in zip(starts, frames, strict=True):
        if frame is None:
            continue
        alone = manipulator_frame_at(features, start)
        for a, b in ((frame.v.p, alone.v.p), (frame.v.q, alone.v.q), (frame.u.p, alone.u.p), (frame.u.q, alone.u.q),
                     (frame.r, alone.r), (frame.weight, alone.weight)):
            assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6), (a, b)


def test_a_prediction_from_a_given_start_keeps_it_and_skips_the_robot_query(cube_scene, small_model):
    cube, pose, cloud = cube_scene
    model = small_model("cube")
    start = place_robot_against(cube.mesh, pose, 0.05, 0.07, gap=0.002)
    action = model.motions[0].action
    prediction = predict(model, cloud, action, torch.Generator().manual_seed(3), robot_start=start)
    condition = prediction.condition
    assert condition.robot_query is None and condition.backoff == 0.0 and condition.valid
    assert torch.allclose(condition.robot_start.p, start.p) and torch.allclose(condition.robot_start.q, start.q)
    # the contact patch is read at the given start: the bumper meets the cube off its centre line
    y_min, y_max, _ = condition.contact_patch.tolist()
    assert abs((y_min + y_max) / 2 + 0.07) < 0.03  # the bumper passes 7 cm left of the cube's centre
    assert torch.isfinite(prediction.final_pose.p).all() and torch.isfinite(prediction.log_prob)
    moved = float((prediction.final_pose.p[:2] - condition.object_pose.p[:2]).norm())
    assert 0.1 < moved < 0.8  # a 4 s push at 0.1 m/s moves the cube, and not farther than the robot drives


def test_dense_and_fast_take_the_given_start_alike(cube_scene, small_model):
    cube, pose, cloud = cube_scene
    model = small_model("cube")
    start = place_robot_against(cube.mesh, pose, 0.0, -0.05, gap=0.002)
    action = model.motions[1].action
    fast = predict(model, cloud, action, torch.Generator().manual_seed(1), robot_start=start)
    dense = predict(model, cloud, action, torch.Generator().manual_seed(1), robot_start=start, method="dense")
    for prediction in (fast, dense):
        assert torch.allclose(prediction.condition.robot_start.p, start.p)
    assert torch.equal(fast.condition.manipulator_frame.v.p, dense.condition.manipulator_frame.v.p)


def test_a_none_start_is_the_models_own_placement_with_the_same_stream(cube_scene, small_model):
    cube, pose, cloud = cube_scene
    model = small_model("cube")
    action = model.motions[2].action
    start = place_robot_against(cube.mesh, pose, 0.0, 0.04, gap=0.002)
    mixed = predict_many(model, [cloud, cloud], action, seed=5, robot_starts=[None, start])
    alone = predict(model, cloud, action, torch.Generator().manual_seed(5))
    assert mixed[0].condition.robot_query is not None
    assert torch.equal(mixed[0].final_pose.p, alone.final_pose.p)
    assert torch.allclose(mixed[1].condition.robot_start.p, start.p)


def test_a_start_that_touches_nothing_or_is_not_one_pose_is_refused(cube_scene, small_model):
    cube, pose, cloud = cube_scene
    model = small_model("cube")
    action = model.motions[0].action
    far = se3.from_xy_yaw(-2.0, 0.0, 0.0)
    with pytest.raises(ModelError, match="touches none of the"):
        predict(model, cloud, action, torch.Generator().manual_seed(0), robot_start=far)
    two = se3.Pose(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2))
    with pytest.raises(InvalidPoseError, match="one pose"):
        predict(model, cloud, action, torch.Generator().manual_seed(0), robot_start=two)
    nan = se3.Pose.unchecked(torch.tensor([float("nan"), 0.0, 0.0]), torch.tensor([1.0, 0, 0, 0]))
    with pytest.raises(InvalidPoseError):
        predict(model, cloud, action, torch.Generator().manual_seed(0), robot_start=nan)
    with pytest.raises(InvalidParameterError, match="one pose"):
        predict_many(model, [cloud, cloud], action, robot_starts=[None])


def test_a_start_inside_the_observed_object_is_refused_and_a_flush_one_is_not(cube_scene, small_model):
    cube, pose, cloud = cube_scene
    model = small_model("cube")
    action = model.motions[0].action
    features = compute_surface_features(cloud)
    touching = place_robot_against(cube.mesh, pose, 0.1, 0.03, gap=0.0)

    def forward(start: se3.Pose, metres: float) -> se3.Pose:
        heading = float(se3.yaw_of(start.q))
        step = torch.tensor([math.cos(heading), math.sin(heading), 0.0], dtype=start.p.dtype) * metres
        return se3.Pose(start.p + step, start.q)

    manipulator_frame_at(features, forward(touching, 0.004))  # within a sensor's few mm: accepted
    with pytest.raises(InvalidPoseError, match=r"overlaps the observed object: .* reverse 0\.02"):
        predict(model, cloud, action, torch.Generator().manual_seed(0), robot_start=forward(touching, 0.02))
    buried = forward(touching, 0.15)  # the bumper wholly behind the visible face
    with pytest.raises(InvalidPoseError, match="overlaps the observed object"):
        predict_many(model, [cloud, cloud], action, robot_starts=[None, buried])


# -- the placement_spread test set (experiments) ------------------------------------------------------------


def test_the_spread_test_set_is_a_config_group_off_by_default(tmp_path):
    from hydra import compose, initialize_config_dir

    from pushtorch.experiments.common import context_from_config
    from pushtorch.sim.plan import Placement

    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        default = context_from_config(compose("config", ["experiment=quickstart"]), tmp_path)
        spread = context_from_config(compose("config", ["experiment=quickstart", "test_placement=spread"]), tmp_path)
        spread_overrides = ["experiment=quickstart", "test_placement=spread"]
        wider = compose("config", [*spread_overrides, "test_placement.lateral_jitter=0.05"])
        unknown = compose("config", [*spread_overrides, "+test_placement.lateral=0.05"])
    assert default.test_placement is None
    assert spread.test_placement == Placement(gap=0.002, lateral_jitter=0.1, yaw_jitter_deg=5.0)
    assert context_from_config(wider, tmp_path).test_placement.lateral_jitter == 0.05
    with pytest.raises(InvalidParameterError, match="test_placement"):
        context_from_config(unknown, tmp_path)


@pytest.mark.parametrize("name", ["cube", "prism_thin", "cylinder_wide"])
def test_spread_test_starts_touch_the_object_off_centre_along_its_own_axis(name):
    from pushtorch.experiments.common import sample_test_poses, spread_test_start
    from pushtorch.sim.plan import Placement

    obj = load_object(name)
    placement = Placement(gap=0.002, lateral_jitter=0.1, yaw_jitter_deg=5.0)
    poses = sample_test_poses(obj, 12, (-45.0, 45.0), seed=7)
    points, _ = trimesh.sample.sample_surface(obj.mesh, 4000, seed=1)
    surface = torch.as_tensor(points, dtype=torch.float32)
    headings, laterals = [], []
    for i in range(len(poses.p)):
        pose = poses.take(i)
        start = spread_test_start(obj, pose, placement, torch.Generator().manual_seed(i))
        again = spread_test_start(obj, pose, placement, torch.Generator().manual_seed(i))
        assert torch.equal(start.p, again.p)  # seeded
        world = se3.apply(pose, surface.to(pose.p.dtype))
        clearance = float(robot.start_clearance(start, world))
        assert 0.0 <= clearance < 0.01  # against the object, not in it
        heading = float(se3.yaw_of(start.q)) - float(se3.yaw_of(pose.q))
        headings.append(abs(heading))
        laterals.append(float(se3.apply(se3.inverse(start), pose.p)[1]))  # object centre in the robot frame
    assert max(headings) <= 5.0 * torch.pi / 180 + 1e-5
    assert max(abs(y) for y in laterals) <= 0.1 + 1e-4 and max(abs(y) for y in laterals) > 0.03  # off-centre
