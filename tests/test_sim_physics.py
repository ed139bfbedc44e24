"""Real pybullet pushes: the paper's quasi-static behaviour, stability, validity flags, determinism."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.objects import load_object
from pushtorch.sim import (
    Normal,
    PushWorld,
    SimSettings,
    execute_push,
    make_actions,
    object_spec,
    place_robot_against,
    plan_training_pushes,
    simulate_plan,
)
from pushtorch.sim.worker import simulate_arrays

GAP = 0.002
TRAVEL = 0.4  # 0.1 m/s for 4 s


def _np(pose: se3.Pose) -> tuple[np.ndarray, np.ndarray]:
    return pose.p.double().numpy(), pose.q.double().numpy()


class Pusher:
    """A world for one object plus the training placement, for short tests."""

    def __init__(self, name: str):
        self.model = load_object(name)
        self.world = PushWorld(object_spec(self.model), SimSettings())
        self.object_pose = self.model.resting_pose()
        self.start = place_robot_against(self.model.mesh, self.object_pose, gap=GAP)

    def push(self, yaw_rate_deg: float = 0.0, mass: float = 0.5, friction: float = 0.3, start=None, obj=None):
        robot_p, robot_q = _np(start if start is not None else self.start)
        obj_p, obj_q = _np(obj if obj is not None else self.object_pose)
        return execute_push(self.world, robot_p, robot_q, obj_p, obj_q, 0.1, math.radians(yaw_rate_deg), 4.0,
                            mass, friction)


@pytest.fixture(scope="module")
def cube():
    pusher = Pusher("cube")
    yield pusher
    pusher.world.close()


def _yaw_deg(q: np.ndarray) -> float:
    return math.degrees(float(se3.yaw_of(torch.as_tensor(q))))


def _tilt_deg(q: np.ndarray) -> np.ndarray:
    """Angle between each orientation's z axis and the world's (upright objects start at tilt 0)."""
    w, x, y, _ = np.moveaxis(np.atleast_2d(q), -1, 0)
    return np.degrees(np.arccos(np.clip(1 - 2 * (x * x + y * y), -1, 1)))


def test_straight_push_moves_the_cube_by_the_robot_travel(cube):
    out = cube.push(0.0, mass=0.5, friction=0.3)
    moved = out.object_final_p - out.object_initial_p
    robot_travel = out.robot_trajectory_p[-1] - out.robot_trajectory_p[0]
    assert out.touched and not out.tipped and not out.left_ground
    assert out.first_contact_time < 0.1  # the gap closes within a few steps
    assert robot_travel[0] == pytest.approx(TRAVEL, abs=0.005)
    assert moved[0] == pytest.approx(robot_travel[0] - GAP, abs=0.005)
    assert abs(moved[1]) < 0.02
    assert abs(_yaw_deg(out.object_final_q)) < 5.0


def test_turning_actions_turn_the_cube_in_opposite_directions(cube):
    left = cube.push(+10.0)
    right = cube.push(-10.0)
    yaw_left, yaw_right = _yaw_deg(left.object_final_q), _yaw_deg(right.object_final_q)
    assert yaw_left > 10.0 and yaw_right < -10.0
    assert left.object_final_p[1] > 0.1 and right.object_final_p[1] < -0.1
    # the robot turned by the commanded 40° (4 s at 10 °/s)
    assert _yaw_deg(left.robot_trajectory_q[-1]) == pytest.approx(40.0, abs=1.0)
    assert _yaw_deg(right.robot_trajectory_q[-1]) == pytest.approx(-40.0, abs=1.0)


def test_more_mass_or_friction_never_moves_the_cube_further(cube):
    noise = 0.002
    for yaw_rate in (0.0, 10.0):
        by_mass = [np.linalg.norm((o := cube.push(yaw_rate, m, 0.3)).object_final_p - o.object_initial_p)
                   for m in (0.1, 1.0, 5.0)]
        by_friction = [np.linalg.norm((o := cube.push(yaw_rate, 0.5, mu)).object_final_p - o.object_initial_p)
                       for mu in (0.1, 0.4, 0.8)]
        for series in (by_mass, by_friction):
            assert all(b <= a + noise for a, b in zip(series, series[1:], strict=False)), series


def test_friction_beyond_the_robot_force_bound_slows_the_robot(cube):
    light = cube.push(0.0, mass=0.5, friction=0.3)
    heavy = cube.push(0.0, mass=8.0, friction=0.8)  # 63 N of friction > 60 N per drive axis
    travel = lambda o: float(o.robot_trajectory_p[-1, 0] - o.robot_trajectory_p[0, 0])  # noqa: E731
    assert travel(heavy) < 0.5 * travel(light)
    assert heavy.touched and heavy.object_final_p[0] - heavy.object_initial_p[0] < 0.2


def test_ground_carries_the_weight_while_pushing(cube):
    """The bumper grips only horizontally: it neither presses the object down nor lifts it."""
    world, mass = cube.world, 5.0
    world.spawn_object(*_np(cube.object_pose), mass, 0.8)
    world.place_robot(*_np(cube.start))
    normals = []
    for step in range(240):
        if step % 4 == 0:
            world.drive(0.1, 0.0)
        world.step()
        if step >= 120:
            contacts = pb.getContactPoints(world.object, world.ground, physicsClientId=world.client)
            normals.append(sum(c[9] for c in contacts))
    assert np.mean(normals) == pytest.approx(mass * 9.81, rel=0.03)


def test_effective_ground_friction_is_the_sampled_value(cube):
    world = cube.world
    world.spawn_object(*_np(cube.object_pose), 0.5, 0.37)
    ground = pb.getDynamicsInfo(world.ground, -1, physicsClientId=world.client)[1]
    own = pb.getDynamicsInfo(world.object, -1, physicsClientId=world.client)[1]
    assert ground * own == pytest.approx(0.37)  # pybullet multiplies the two coefficients


def test_no_sinking_jumping_or_tipping_during_a_push(cube):
    for yaw_rate in (-10.0, 0.0, 10.0):
        out = cube.push(yaw_rate, mass=0.5, friction=0.8)
        heights = out.object_trajectory_p[:, 2] - cube.model.rest_height
        assert np.abs(heights).max() < 5e-4  # neither sinks nor jumps (0.5 mm)
        assert _tilt_deg(out.object_trajectory_q).max() < 1.0


def test_no_creeping_after_contact_ends(cube):
    cube.push(10.0, mass=0.5, friction=0.3)
    p0, q0 = cube.world.object_pose()
    for _ in range(240):  # one more second with the robot stopped
        cube.world.step()
    p1, q1 = cube.world.object_pose()
    assert np.abs(p1 - p0).max() < 5e-4
    assert math.degrees(float(se3.angle_between(torch.as_tensor(q0), torch.as_tensor(q1)))) < 0.1


def test_untouched_object_stays_put_and_is_flagged(cube):
    away = se3.from_xy_yaw(-1.0, 0.0, math.pi)  # behind the object, heading away from it
    out = cube.push(0.0, start=away)
    assert not out.touched and math.isnan(out.first_contact_time)
    assert np.abs(out.object_final_p - out.object_initial_p).max() < 2e-4  # no creep at rest


def test_tipped_and_left_ground_flags(cube):
    away = se3.from_xy_yaw(-1.0, 0.0, math.pi)
    pitch = se3.quat_normalize(torch.tensor([math.cos(0.3), math.sin(0.3), 0.0, 0.0]))
    tilted = se3.Pose(torch.tensor([0.0, 0.0, 0.16]), pitch)
    fell = cube.push(0.0, start=away, obj=tilted)
    assert fell.tipped and fell.left_ground
    dropped = cube.push(0.0, start=away, obj=se3.from_xy_yaw(0.0, 0.0, 0.0, z=0.15))
    assert dropped.left_ground and not dropped.tipped


@pytest.mark.parametrize("name", ["cylinder", "hybrid", "modified_cube"])
def test_other_shapes_push_without_tipping(name):
    pusher = Pusher(name)
    try:
        for yaw_rate in (-10.0, 0.0, 10.0):
            for mass, friction in ((0.5, 0.3), (5.0, 0.8)):
                out = pusher.push(yaw_rate, mass, friction)
                assert out.touched and not out.tipped and not out.left_ground
                assert _tilt_deg(out.object_trajectory_q).max() < 2.0
                # 5 kg at friction 0.8 takes the P3-DX's whole traction (39 N): it slows, but still pushes
                moved = np.linalg.norm(out.object_final_p[:2] - out.object_initial_p[:2])
                assert moved > (0.3 if mass < 1.0 else 0.2), (yaw_rate, mass, moved)
    finally:
        pusher.world.close()


def test_object_pose_round_trips_through_the_principal_inertia_frame():
    model = load_object("modified_cube")  # its principal axes are not the object axes
    spec = object_spec(model)
    assert abs(spec.principal_rotation[0]) < 0.999
    g = torch.Generator().manual_seed(4)
    with PushWorld(spec) as world:
        for yaw in (torch.rand(3, generator=g) * 2 * math.pi).tolist():
            pose = model.resting_pose(0.3, -0.2, yaw)
            world.spawn_object(*_np(pose), 1.0, 0.5)
            p, q = world.object_pose()
            assert np.allclose(p, pose.p.numpy(), atol=1e-6)
            assert float(se3.quat_distance(torch.as_tensor(q), pose.q.double())) < 1e-9
            # the geometry sits where the mesh says: rays cast down hit the mesh's top surface, notch included
            top = float(model.mesh.bounds[1, 2])
            notch = 0.2 / 16 ** (1 / 3)
            probes_local = torch.tensor([[0.1 - notch / 2, 0.1 - notch / 2, 0.0], [-0.05, -0.05, 0.0]],
                                        dtype=torch.float64)
            probes = se3.apply(pose.to(torch.float64), probes_local).numpy()
            hits = pb.rayTestBatch([[x, y, 1.0] for x, y, _ in probes], [[x, y, -1.0] for x, y, _ in probes],
                                   physicsClientId=world.client)
            heights = [h[3][2] - float(pose.p[2]) for h in hits]
            assert heights == pytest.approx([top - notch, top], abs=1e-4)


def test_object_inertia_is_the_mesh_inertia():
    spec = object_spec(load_object("cube"))
    assert np.allclose(spec.inertia_per_kg, (0.2**2 + 0.2**2) / 12)


@pytest.mark.parametrize("name", ["cube", "cylinder", "hybrid"])  # box primitives and convex hulls
def test_same_plan_gives_identical_records_in_any_order(name):
    model = load_object(name)
    plan = plan_training_pushes(model, make_actions(3), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=3)
    first = simulate_plan(object_spec(model), plan)
    again = simulate_plan(object_spec(model), plan)
    assert torch.equal(first.object_final.p, again.object_final.p)
    assert torch.equal(first.object_trajectory.q, again.object_trajectory.q)
    # a world keeps nothing from one push to the next: reversed order, same outcomes
    arrays = plan.arrays()
    reversed_arrays = {k: v[::-1].copy() for k, v in arrays.items()}
    with PushWorld(object_spec(model)) as world:
        backwards = simulate_arrays(world, reversed_arrays, name, plan.seed, plan.duration)
    assert np.array_equal(backwards["object_final_p"][::-1], first.object_final.p.numpy())


def test_worlds_share_their_hull_files_and_leave_no_folder_behind():
    """A world's convex hulls are OBJ files written once per content under <temp>/pushtorch-shapes, shared by
    every world; an unclosed world (a killed worker's) leaves no folder of its own in the temp folder."""
    import tempfile
    from pathlib import Path

    temp = Path(tempfile.gettempdir())
    before = set(temp.glob("pushtorch-shape-*"))
    spec = object_spec(load_object("hybrid"))  # convex hulls beside boxes
    first, second = PushWorld(spec), PushWorld(spec)
    shared = sorted((temp / "pushtorch-shapes").glob("*.obj"))
    second.close()
    del first  # never closed
    assert set(temp.glob("pushtorch-shape-*")) == before
    assert shared and all(path.is_file() and path.read_text().startswith("v ") for path in shared)


def test_make_actions_reads_the_angle_range_in_degrees_per_second():
    actions = make_actions(3)
    assert actions.shape == (3, 2)
    assert torch.allclose(actions[:, 0], torch.full((3,), 0.1))
    assert torch.allclose(torch.rad2deg(actions[:, 1]), torch.tensor([-10.0, 0.0, 10.0]))
    assert torch.allclose(make_actions(1)[:, 1], torch.zeros(1))
    five = torch.rad2deg(make_actions(5, (-10, 10))[:, 1])
    assert torch.allclose(five, torch.tensor([-10.0, -5, 0, 5, 10]))
    for bad in (dict(count=0), dict(count=2.5), dict(angle_range_deg=(10, -10)), dict(speed=0.0)):
        with pytest.raises(InvalidParameterError):
            make_actions(**bad)


def test_placement_puts_the_bumper_against_the_facing_side():
    from pushtorch.robot import bumper_pose

    for name in ("cube", "prism_long", "cylinder", "hybrid"):
        model = load_object(name)
        start = place_robot_against(model.mesh, model.resting_pose(), gap=GAP)
        bumper = bumper_pose(start)
        back = float(model.mesh.bounds[0, 0])  # the side facing a robot that heads along +x
        assert float(bumper.p[0]) == pytest.approx(back - GAP, abs=1e-5), name
        assert float(bumper.p[1]) == pytest.approx(0.0, abs=1e-6)
    # with a lateral offset and a heading the bumper's first point of contact is still exactly `gap` away,
    # as pybullet's own closest-point query sees it
    model = load_object("cube")
    with PushWorld(object_spec(model)) as world:
        for heading, offset in ((0.3, 0.05), (-0.5, -0.08)):
            start = place_robot_against(model.mesh, model.resting_pose(), heading, offset, gap=0.01)
            world.spawn_object(*_np(model.resting_pose()), 0.5, 0.3)
            world.place_robot(*_np(start))
            points = pb.getClosestPoints(
                world.robot, world.object, 0.1, linkIndexA=3, physicsClientId=world.client
            )
            assert min(p[8] for p in points) == pytest.approx(0.01, abs=2e-4)
    with pytest.raises(InvalidParameterError, match="misses"):
        place_robot_against(model.mesh, model.resting_pose(), lateral_offset=0.5)


def test_bad_push_parameters_raise(cube):
    with pytest.raises(InvalidParameterError):
        cube.push(0.0, mass=-1.0)
    with pytest.raises(InvalidParameterError):
        cube.push(0.0, friction=0.0)
    with pytest.raises(InvalidParameterError):
        SimSettings(time_step=0.0)


def test_simulate_pushes_accepts_any_start_pose_and_broadcasts():
    from pushtorch.sim import simulate_pushes

    model = load_object("cylinder")
    obj = model.resting_pose(0.5, 0.5, 0.0)
    # a robot 0.6 m south of the object heading north (+y), pushing it along +y
    start = se3.from_xy_yaw(0.5, 0.5 - 0.1 - 0.26 - 0.01, math.pi / 2)
    actions = make_actions(3)
    records = simulate_pushes(model, start, obj, actions, 0.5, torch.tensor([[0.3], [0.6]]))
    assert len(records) == 6 and records.valid.all()
    moved = records.object_final.p - records.object_initial.p
    assert (moved[:, 1] > 0.3).all()
    expected = torch.tensor([0.3, 0.3, 0.3, 0.6, 0.6, 0.6], dtype=torch.float64)
    assert torch.allclose(records.ground_friction, expected)
    with pytest.raises(InvalidParameterError):
        simulate_pushes(model, start, obj, actions, torch.ones(2), 0.3)


@pytest.mark.parametrize("robot", ["ideal", "p3dx"])
@pytest.mark.parametrize("name", ["cube", "prism_long", "cylinder", "hybrid"])
def test_mirrored_actions_give_mirrored_outcomes(name, robot):
    """A centred object pushed with -10 and +10 deg/s ends in mirror images (x, -y, -yaw) of each other; before
    world version 3 the cube's were 42 mm apart and the long prism's 59 mm and 19 deg."""
    from pushtorch.sim.runner import simulate_pushes

    model = load_object(name)
    pose = model.resting_pose()
    start = place_robot_against(model.mesh, pose, gap=GAP)
    actions = torch.tensor([[0.1, math.radians(-10.0)], [0.1, math.radians(10.0)]])
    records = simulate_pushes(model, start, pose, actions, 0.5, 0.3, settings=SimSettings(robot=robot))
    right, left = records.object_final.p[0], records.object_final.p[1]
    gap = float((right[:2] - torch.stack([left[0], -left[1]])).norm())
    yaw_right, yaw_left = (_yaw_deg(q.numpy()) for q in records.object_final.q)
    turn = abs(math.remainder(math.radians(yaw_right + yaw_left), 2 * math.pi))
    assert gap < 0.005 and (model.symmetry.continuous_z or math.degrees(turn) < 1.0), (gap, yaw_right, yaw_left)
    assert not bool(records.tipped.any()) and not bool(records.left_ground.any())


@pytest.mark.parametrize("name", ["cube", "cylinder"])
def test_a_push_does_not_depend_on_where_the_scene_stands_in_the_world(name):
    """The same relative push from a start turned by 30 deg about the world's z (and moved) ends at the same
    place relative to its start: every push is simulated in the robot's start frame."""
    from pushtorch.sim.runner import simulate_pushes

    model = load_object(name)
    pose = model.resting_pose()
    start = place_robot_against(model.mesh, pose, gap=GAP)
    moved = se3.from_xy_yaw(1.5, -0.7, math.radians(30.0)).to(torch.float64)
    action = torch.tensor([0.1, math.radians(10.0)])
    here = simulate_pushes(model, start, pose, action, 0.5, 0.3)
    start, pose = start.to(torch.float64), pose.to(torch.float64)
    there = simulate_pushes(model, se3.compose(moved, start), se3.compose(moved, pose), action, 0.5, 0.3)
    back = se3.compose(se3.inverse(moved), there.object_final)
    assert float((back.p - here.object_final.p).norm()) < 1e-4


def test_a_thin_prism_does_not_follow_the_cubes_motion_from_the_same_placement():
    """The physics behind issue 17's transfer floor (tools/transfer_floor.py): pushed from the same placement
    (bumper centred on the 0.2 m face, 2 mm short) with the same turning action, the cube and the 0.1 m prism
    both turn with the bumper, but the prism slides farther along it. The cube's motion in the robot's start
    frame, moved to the prism's start, misses the prism by centimetres; a straight push transfers exactly."""
    from pushtorch.evaluation.baselines import replay_motion
    from pushtorch.models.motion import local_motions
    from pushtorch.sim.runner import simulate_pushes

    def robot_frame_motion(name: str, yaw_rate_deg: float) -> tuple[se3.Pose, se3.Pose, se3.Pose, se3.Pose]:
        model = load_object(name)
        pose = model.resting_pose().to(torch.float64)
        start = place_robot_against(model.mesh, pose, gap=GAP).to(torch.float64)
        action = torch.tensor([0.1, math.radians(yaw_rate_deg)])
        final = simulate_pushes(model, start, pose, action, 0.5, 0.3).object_final
        final = se3.Pose(final.p[0], final.q[0])
        return start, pose, final, local_motions(start, se3.compose(final, se3.inverse(pose)))

    misses = {}
    for rate in (-10.0, 0.0, 10.0):
        _, _, _, cube_motion = robot_frame_motion("cube", rate)
        start, pose, truth, prism_motion = robot_frame_motion("prism_thin", rate)
        transferred = replay_motion(cube_motion, start, pose)
        misses[rate] = float((transferred.p[:2] - truth.p[:2]).norm())
        turn_gap = abs(math.degrees(float(se3.yaw_of(cube_motion.q) - se3.yaw_of(prism_motion.q))))
        assert turn_gap < 3.0, (rate, turn_gap)  # both turn with the bumper
    assert misses[0.0] < 0.005, misses
    assert misses[-10.0] > 0.03 and misses[10.0] > 0.03, misses  # measured 5.75 cm at 0.5 kg
