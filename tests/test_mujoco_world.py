"""Real MuJoCo pushes: the second engine's world is the same world (robot, drive, objects, friction) as pybullet's.

Paper, Experimental Setup (the world) and Future Work (a world that is not the model's simulator).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.objects import load_object
from pushtorch.objects.meshes import load_mesh_file
from pushtorch.robot import start_clearance
from pushtorch.sim import (
    Normal,
    SimSettings,
    make_actions,
    object_spec,
    place_robot_against,
    plan_training_pushes,
    run_plan,
)
from pushtorch.sim.engines import make_world
from pushtorch.sim.runner import simulate_pushes

MUJOCO = SimSettings(engine="mujoco")


def _final(obj, start, pose, yaw_rate_deg: float, mass: float, friction: float, settings: SimSettings):
    records = simulate_pushes(obj, start, pose, torch.tensor([0.1, math.radians(yaw_rate_deg)]), mass, friction,
                              settings=settings)
    assert bool(records.touched[0]) and not bool(records.tipped[0] | records.left_ground[0])
    return se3.Pose(records.object_final.p[0], records.object_final.q[0])


def _slide(engine: str, mu: float, speed: float = 1.0) -> float:
    """How far (m) the cube slides from ``speed`` m/s along +x at ground friction ``mu``, far from the robot."""
    settings = SimSettings(engine=engine)
    with make_world(object_spec(load_object("cube")), settings) as world:
        world.spawn_object(np.array([2.0, 0.0, 0.1]), np.array([1.0, 0.0, 0.0, 0.0]), 0.5, mu)
        world.place_robot(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
        if engine == "mujoco":
            world.data.qvel[3:6] = (speed, 0.0, 0.0)  # the robot's dofs are 0-2, then the object's linear velocity
        else:
            world.pb.resetBaseVelocity(world.object, [speed, 0.0, 0.0], [0.0, 0.0, 0.0],
                                       physicsClientId=world.client)
        for _ in range(int(1.0 / settings.time_step)):  # 1 s: at mu >= 0.2 it stops within 0.51 s
            world.step()
        return float(world.object_pose()[0][0]) - 2.0


@pytest.mark.parametrize("engine", ["pybullet", "mujoco"])
@pytest.mark.parametrize("mu", [0.2, 0.5])
def test_the_sampled_friction_is_the_object_ground_coefficient_in_both_engines(engine, mu):
    """A block sliding at v stops after v²/(2 μ g): μ is the object-ground coefficient in both engines (MuJoCo
    would take the larger of the two geoms' coefficients, pybullet their product)."""
    expected = 1.0 / (2 * mu * 9.81)
    assert _slide(engine, mu) == pytest.approx(expected, rel=0.05)


def test_a_heavy_cube_moves_less_than_a_light_one_under_turning_pushes_in_mujoco():
    cube = load_object("cube")
    pose = cube.resting_pose()
    start = place_robot_against(cube.mesh, pose, gap=0.002)
    for rate in (-10.0, 10.0):
        light, heavy = (_final(cube, start, pose, rate, m, 0.4, MUJOCO) for m in (0.1, 5.0))
        moved = [float((p.p[:2] - pose.p.double()[:2]).norm()) for p in (light, heavy)]
        assert moved[0] - moved[1] > 0.02, moved


@pytest.mark.parametrize("name", ["cube", "cylinder", "hybrid"])
def test_mirrored_pushes_mirror_within_5_mm_in_mujoco(name):
    obj = load_object(name)
    pose = obj.resting_pose()
    start = place_robot_against(obj.mesh, pose, gap=0.002)
    right, left = (_final(obj, start, pose, rate, 0.5, 0.3, MUJOCO) for rate in (-10.0, 10.0))
    mirrored = torch.stack([left.p[0], -left.p[1]])
    assert float((right.p[:2] - mirrored).norm()) <= 0.005


def test_pushes_of_one_engine_are_refused_by_the_other(tmp_path):
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(1), 2, Normal(0.5, 0.01), Normal(0.3, 0.01), seed=0)
    run_plan(object_spec(cube), plan, tmp_path / "pushes", SimSettings(), progress=False)
    with pytest.raises(RecordFormatError, match="engine"):
        run_plan(object_spec(cube), plan, tmp_path / "pushes", MUJOCO, progress=False)
    # a folder written before the world named its engine is pybullet's
    manifest = tmp_path / "pushes" / "manifest.json"
    old = json.loads(manifest.read_text())
    del old["settings"]["engine"]
    manifest.write_text(json.dumps(old))
    run_plan(object_spec(cube), plan, tmp_path / "pushes", SimSettings(), progress=False)  # resumes
    with pytest.raises(RecordFormatError, match="engine"):
        run_plan(object_spec(cube), plan, tmp_path / "pushes", MUJOCO, progress=False)


def test_an_unknown_engine_is_refused():
    with pytest.raises(InvalidParameterError, match="world.engine"):
        SimSettings(engine="gazebo")


def _l_of_two_boxes(tmp_path):
    import trimesh

    bars = []
    for extents, centre in (((0.3, 0.05, 0.1), (0.0, 0.0, 0.05)), ((0.05, 0.15, 0.1), (-0.125, -0.09, 0.05))):
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(centre)
        bars.append(box)
    path = tmp_path / "l.obj"
    trimesh.util.concatenate(bars).export(path)
    return load_mesh_file(path)


def test_a_concave_mesh_pushes_as_its_parts_in_both_engines(tmp_path):
    """An L approached on its long bar's side by a bumper that misses the short bar: its convex hull would
    overlap the bumper by centimetres at the start; its parts leave the 2 mm gap, and both engines push it
    about the same."""
    obj = _l_of_two_boxes(tmp_path)
    assert len(obj.collision_parts) == 2
    pose = obj.resting_pose()
    centre_x = float(np.asarray(obj.mesh.bounds)[:, 0].mean())
    start = place_robot_against(obj.mesh, pose, approach_yaw=math.pi / 2, lateral_offset=-(centre_x + 0.12))
    surface = torch.as_tensor(obj.mesh.sample(4000, seed=0), dtype=torch.float32) + pose.p
    hull = torch.as_tensor(obj.mesh.convex_hull.sample(4000, seed=0), dtype=torch.float32) + pose.p
    assert float(start_clearance(start, surface)) > 0.001
    assert float(start_clearance(start, hull)) < -0.05
    finals = [_final(obj, start, pose, 0.0, 0.5, 0.3, SimSettings(engine=e)) for e in ("pybullet", "mujoco")]
    for final in finals:
        assert float(final.p[1] - pose.p[1]) > 0.2  # pushed along the approach (+y)
    assert float((finals[0].p[:2] - finals[1].p[:2]).norm()) < 0.05
    assert len(make_world(object_spec(obj), MUJOCO).model.geom_bodyid) == 3 + 2  # ground, chassis, bumper, parts
