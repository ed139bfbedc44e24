"""Collision-free robot starts (issue 15): clearance of the robot's boxes, exact back-off, and predictions
whose start never overlaps the observed cloud. Real meshes, clouds, pybullet pushes and models; no mocks."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import robot, se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError, ModelError
from pushtorch.features import compute_surface_features
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import (
    MAX_BACKOFF,
    START_CLEARANCE,
    clear_robot_start,
    clearance_points,
    generate_push_condition,
    predict,
)
from pushtorch.sim.push import place_robot_against
from pushtorch.sim.runner import simulate_pushes


def _box_points(generator: torch.Generator, count: int, dtype: torch.dtype) -> torch.Tensor:
    """``count`` points on the surface and inside a random box near the origin, turned about z."""
    half = 0.01 + 0.15 * torch.rand(3, generator=generator, dtype=dtype)
    centre = torch.cat([(torch.rand(2, generator=generator, dtype=dtype) - 0.5) * 1.2, half[2:]])
    local = (torch.rand(count, 3, generator=generator, dtype=dtype) * 2 - 1) * half
    face = torch.randint(0, 3, (count // 2,), generator=generator)  # half the points pushed onto a face
    sign = torch.where(torch.rand(count // 2, generator=generator) < 0.5, -1.0, 1.0).to(dtype)
    rows = torch.arange(count // 2)
    local[rows, face] = sign * half[face]
    yaw = float(torch.rand((), generator=generator)) * 2 * math.pi
    turn = se3.from_xy_yaw(0.0, 0.0, yaw).to(dtype)
    return se3.apply(turn, local) + centre


def _planar_starts(generator: torch.Generator, count: int, dtype: torch.dtype) -> se3.Pose:
    xy = (torch.rand(count, 2, generator=generator, dtype=dtype) - 0.5) * 1.0
    yaw = (torch.rand(count, generator=generator, dtype=dtype) - 0.5) * 2 * math.pi
    return robot.joints_to_base_pose(torch.cat([xy, yaw.unsqueeze(-1)], -1))


# -- the geometric check ---------------------------------------------------------------------------


@given(seed=st.integers(0, 2**31 - 1), clearance=st.floats(0.0, 0.01), count=st.integers(1, 300))
def test_backing_off_clears_every_point_and_a_clear_start_stays(seed, clearance, count):
    g = torch.Generator().manual_seed(seed)
    points = torch.stack([_box_points(g, count, torch.float32) for _ in range(4)])  # (4, N, 3)
    starts = _planar_starts(g, 4, torch.float32)
    distance = robot.backoff_distance(starts, points, clearance)
    assert distance.shape == (4,) and (distance >= 0).all()
    after = robot.start_clearance(robot.backed_off(starts, distance), points)
    assert (after >= clearance - 1e-6).all(), (after, clearance)
    before = robot.start_clearance(starts, points)
    assert (distance[before >= clearance] <= 1e-6).all()  # a start that already clears needs no back-off
    for i in range(4):  # the batch is the pushes one by one
        one = robot.backoff_distance(starts.take(i), points[i], clearance)
        torch.testing.assert_close(one, distance[i])


@given(seed=st.integers(0, 2**31 - 1), clearance=st.floats(0.0005, 0.01))
def test_backoff_is_the_smallest_that_clears(seed, clearance):
    g = torch.Generator().manual_seed(seed)
    points = _box_points(g, 200, torch.float64)
    start = _planar_starts(g, 1, torch.float64).take(0)
    distance = float(robot.backoff_distance(start, points, clearance))
    assert robot.start_clearance(robot.backed_off(start, distance), points) >= clearance - 1e-12
    if distance > 1e-4:  # any shorter back-off leaves a point too close
        assert robot.start_clearance(robot.backed_off(start, distance - 1e-4), points) < clearance


def test_bumper_is_ahead_of_the_chassis_and_clearance_is_a_signed_box_distance():
    centres, halves = robot.robot_boxes(torch.float64)
    chassis_front = centres[0, 0] + halves[0, 0]
    bumper_back, bumper_front = centres[1, 0] - halves[1, 0], centres[1, 0] + halves[1, 0]
    assert bumper_front == pytest.approx(0.26) and bumper_back > chassis_front  # the approach is the base's +x
    start = se3.from_xy_yaw(1.0, 2.0, math.pi / 2).to(torch.float64)  # heading along world +y
    ahead = se3.apply(start, torch.tensor([[0.30, 0.0, 0.10]], dtype=torch.float64))
    inside = se3.apply(start, torch.tensor([[0.25, 0.0, 0.10]], dtype=torch.float64))
    assert float(robot.start_clearance(start, ahead)) == pytest.approx(0.04)
    assert float(robot.start_clearance(start, inside)) == pytest.approx(-0.01)
    assert float(robot.backoff_distance(start, ahead)) == 0.0
    assert float(robot.backoff_distance(start, inside)) == pytest.approx(0.26 + 0.002 - 0.25)
    assert float(robot.start_clearance(start, inside[:0])) == math.inf


def test_backing_off_never_runs_the_chassis_into_a_point_behind_it():
    start = se3.identity((), torch.float64)
    in_bumper = torch.tensor([0.25, 0.0, 0.10], dtype=torch.float64)
    behind = torch.tensor([-0.26, 0.0, 0.10], dtype=torch.float64)  # 3.25 cm behind the chassis
    distance = float(robot.backoff_distance(start, torch.stack([in_bumper, behind])))
    assert distance == pytest.approx(0.012)  # the bumper's exit; the point behind is still 2 cm clear then
    close_behind = torch.tensor([-0.235, 0.0, 0.10], dtype=torch.float64)  # 7.5 mm behind the chassis
    distance = float(robot.backoff_distance(start, torch.stack([in_bumper, close_behind])))
    # reversing 1.2 cm would put that point inside the chassis: the robot must pass it entirely
    assert distance == pytest.approx(0.2275 + 0.002 - (-0.235))
    after = robot.start_clearance(robot.backed_off(start, distance), torch.stack([in_bumper, close_behind]))
    assert float(after) >= 0.002 - 1e-12


def test_bad_inputs_are_refused():
    start = se3.identity()
    with pytest.raises(InvalidParameterError, match="clearance"):
        robot.backoff_distance(start, torch.zeros(3, 3), clearance=-0.001)
    with pytest.raises(InvalidPointCloudError):
        robot.start_clearance(start, torch.zeros(3, 2))
    with pytest.raises(InvalidPointCloudError):
        robot.backoff_distance(start, torch.full((3, 3), math.nan))


# -- a start inside the cube ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def cube_scene():
    cube = load_object("cube")
    pose = cube.resting_pose()
    cloud = capture_partial_cloud(cube, pose)
    return cube, pose, cloud, compute_surface_features(cloud)


def test_a_start_inside_the_cube_is_backed_off_and_pushes_without_throwing(cube_scene):
    cube, pose, cloud, features = cube_scene
    touching = place_robot_against(cube.mesh, pose, gap=0.0)
    penetrating = robot.backed_off(touching, -0.03)  # the bumper 3 cm into the cube
    # the visible face then lies in the slot between chassis and bumper: the surface alone looks clear, the
    # occluded layer behind it (clearance_points) does not
    assert float(robot.start_clearance(penetrating, cloud.points)) > START_CLEARANCE
    assert float(robot.start_clearance(penetrating, clearance_points(features))) < 0
    start, backoff = clear_robot_start(penetrating, features)
    assert backoff == pytest.approx(0.03 + START_CLEARANCE, abs=2e-4)  # back to 2 mm in front of the face
    assert float(robot.start_clearance(start, cloud.points)) >= START_CLEARANCE - 1e-5
    assert float(robot.start_clearance(start, clearance_points(features))) >= START_CLEARANCE - 1e-5
    assert se3.yaw_of(start.q) == pytest.approx(float(se3.yaw_of(penetrating.q)), abs=1e-6)

    records = simulate_pushes(cube, se3.Pose.stack([penetrating, start]), pose, torch.tensor([0.1, 0.0]), 0.5, 0.3)
    assert bool(records.touched[1]) and not bool(records.left_ground[1]) and not bool(records.tipped[1])
    jump = (records.object_trajectory.p[:, 1, :2] - records.object_trajectory.p[:, 0, :2]).norm(dim=-1)
    print(f"\npenetrating start: left_ground={bool(records.left_ground[0])} tipped={bool(records.tipped[0])} "
          f"first-sample jump {1000 * float(jump[0]):.1f} mm (backed off: {1000 * float(jump[1]):.1f} mm)")


def test_a_start_deep_inside_the_cube_is_backed_off_beyond_the_bound(cube_scene):
    cube, pose, _, features = cube_scene
    deep = robot.backed_off(place_robot_against(cube.mesh, pose, gap=0.0), -0.15)
    start, backoff = clear_robot_start(deep, features)
    assert backoff == pytest.approx(0.15 + START_CLEARANCE, abs=2e-4) and backoff > MAX_BACKOFF
    assert robot.start_clearance(start, features.p) >= START_CLEARANCE - 1e-5


# -- real predictions ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_cylinder_model(small_model):
    return small_model("cylinder")


def _check_clear(condition, cloud_points):
    assert condition.backoff >= 0 and condition.valid == (condition.backoff <= MAX_BACKOFF)
    assert float(robot.start_clearance(condition.robot_start, cloud_points)) >= START_CLEARANCE - 1e-5
    annealed = condition.robot_query.pose  # the start the density chose, moved back by `backoff`
    torch.testing.assert_close(condition.robot_start.p, robot.backed_off(annealed, condition.backoff).p,
                               atol=1e-6, rtol=0)


def test_predicted_starts_clear_the_observed_cylinder(small_cylinder_model):
    cylinder = load_object("cylinder")
    cloud = capture_partial_cloud(cylinder, cylinder.resting_pose(x=0.05, yaw=0.4))
    features = compute_surface_features(cloud)
    model = small_cylinder_model
    prediction = predict(model, cloud, model.actions[1], torch.Generator().manual_seed(0))
    _check_clear(prediction.condition, cloud.points)
    dense = generate_push_condition(model, features, 2, torch.Generator().manual_seed(1), method="dense")
    _check_clear(dense, cloud.points)


def test_a_transferred_start_is_backed_off_and_marked_invalid_beyond_the_bound(small_cylinder_model, caplog):
    cube = load_object("cube")
    model = small_cylinder_model  # incongruent: a cylinder model on the cube
    outcomes = []
    for i, yaw in enumerate((-0.5, 0.0, 0.3, 0.7)):
        cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=yaw))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="pushtorch.apps.predict"):
            condition = predict(model, cloud, model.actions[i % 3], torch.Generator().manual_seed(i)).condition
        _check_clear(condition, cloud.points)  # backed off in every case: never an overlapping start
        logged = [r.getMessage() for r in caplog.records if "overlaps the observed object" in r.getMessage()]
        if condition.valid:
            assert condition.check_start() is condition and not logged
        else:
            assert len(logged) == 1 and "marked invalid" in logged[0]
            with pytest.raises(ModelError, match="overlaps the observed object"):
                condition.check_start()
        outcomes.append(f"{1000 * condition.backoff:.1f} mm{'' if condition.valid else ' (invalid)'}")
    print("\ncylinder model on the cube:", outcomes)
    invalid = replace(condition, backoff=MAX_BACKOFF + 0.01)  # the flag follows the bound
    assert not invalid.valid
    with pytest.raises(ModelError, match=f"{MAX_BACKOFF + 0.01:.3f} m"):
        invalid.check_start()
