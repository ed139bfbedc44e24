"""The robot URDF: one file, two consumers (pybullet, pytorch_kinematics) that must agree; bumper mesh."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest
import torch

from pushtorch import robot, se3
from pushtorch.errors import InvalidPoseError


def _random_base_poses(shape, generator) -> se3.Pose:
    xy = (torch.rand((*shape, 2), generator=generator, dtype=torch.float64) - 0.5) * 4.0
    yaw = (torch.rand(tuple(shape), generator=generator, dtype=torch.float64) - 0.5) * 4 * math.pi
    return robot.joints_to_base_pose(torch.cat([xy, yaw.unsqueeze(-1)], -1))


@pytest.fixture(scope="module")
def client():
    cid = pb.connect(pb.DIRECT)
    body = pb.loadURDF(str(robot.URDF_PATH), useFixedBase=True, physicsClientId=cid)
    yield cid, body
    pb.disconnect(cid)


def test_pybullet_and_pytorch_kinematics_agree_on_the_bumper_pose(client):
    cid, body = client
    names = [pb.getJointInfo(body, j, physicsClientId=cid)[1].decode() for j in range(3)]
    assert tuple(names) == robot.JOINT_NAMES
    assert tuple(robot.kinematic_chain().get_joint_parameter_names()) == robot.JOINT_NAMES
    g = torch.Generator().manual_seed(0)
    bases = _random_base_poses((8,), g)
    ours = robot.bumper_pose(bases)
    for i in range(8):
        joints = robot.base_pose_to_joints(bases.take(i))
        for j, value in enumerate(joints.tolist()):
            pb.resetJointState(body, j, value, physicsClientId=cid)
        state = pb.getLinkState(body, 3, computeForwardKinematics=True, physicsClientId=cid)
        theirs = se3.from_pybullet(state[4], state[5], dtype=torch.float64)  # URDF link frame
        # pybullet computes in single precision
        assert torch.allclose(ours.p[i], theirs.p, atol=1e-5)
        assert se3.quat_distance(ours.q[i], theirs.q) < 1e-6


def test_pybullet_bumper_collision_box_matches_the_parsed_geometry(client):
    cid, body = client
    data = pb.getCollisionShapeData(body, 3, physicsClientId=cid)
    assert len(data) == 1 and data[0][2] == pb.GEOM_BOX
    geometry = robot.bumper_geometry()
    assert np.allclose(data[0][3], geometry.size)
    assert geometry.z_range == pytest.approx((0.02, 0.17))
    # the chassis is behind the bumper: the plate's back face is in front of the chassis' front face
    front_of_chassis = geometry.chassis_centre[0] + geometry.chassis_size[0] / 2
    assert float(geometry.mount.p[0]) - geometry.size[0] > front_of_chassis


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_bumper_pose_batches_and_inverts(shape):
    g = torch.Generator().manual_seed(1)
    bases = _random_base_poses(shape, g)
    bumper = robot.bumper_pose(bases)
    assert bumper.p.shape == (*shape, 3) and bumper.q.shape == (*shape, 4)
    back = robot.base_pose_from_bumper(bumper)
    assert torch.allclose(back.p, bases.p, atol=1e-9)
    assert (se3.quat_distance(back.q, bases.q) < 1e-12).all()
    # the bumper's front face is 0.26 m ahead of the base along its heading, at the plate's mid height
    heading = se3.yaw_of(bases.q)
    ahead = torch.stack([torch.cos(heading), torch.sin(heading)], -1)
    assert torch.allclose(((bumper.p[..., :2] - bases.p[..., :2]) * ahead).sum(-1),
                          torch.full(shape, 0.26, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(bumper.p[..., 2], torch.full(shape, 0.095, dtype=torch.float64))


def test_bumper_pose_float32_matches_float64():
    g = torch.Generator().manual_seed(2)
    bases = _random_base_poses((16,), g)
    p64 = robot.bumper_pose(bases).p
    p32 = robot.bumper_pose(bases.to(torch.float32)).p
    assert p32.dtype == torch.float32
    assert torch.allclose(p32.double(), p64, atol=1e-5)


def test_non_planar_base_pose_is_rejected():
    lifted = se3.from_xy_yaw(0.0, 0.0, 0.0, z=0.1)
    with pytest.raises(InvalidPoseError, match="ground"):
        robot.bumper_pose(lifted)
    tilted = se3.Pose(torch.zeros(3), se3.quat_normalize(torch.tensor([1.0, 0.2, 0.0, 0.0])))
    with pytest.raises(InvalidPoseError):
        robot.bumper_pose(tilted)


def test_bumper_mesh_in_link_frame_and_world():
    mesh = robot.bumper_mesh()
    geometry = robot.bumper_geometry()
    assert mesh.is_watertight
    assert np.allclose(mesh.extents, geometry.size)
    # link frame: front face at x = 0, plate behind it
    assert mesh.bounds[1, 0] == pytest.approx(0.0, abs=1e-12)
    assert mesh.bounds[0, 0] == pytest.approx(-geometry.size[0])
    base = robot.joints_to_base_pose(torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64))
    world = robot.bumper_mesh(base)
    triangles = robot.bumper_triangles(base)
    assert triangles.shape == (12, 3, 3)
    assert np.allclose(np.asarray(world.triangles), triangles.numpy(), atol=1e-9)
    low, high = robot.bumper_geometry().z_range
    assert world.bounds[0, 2] == pytest.approx(low) and world.bounds[1, 2] == pytest.approx(high)


def test_bumper_triangles_batch_shape():
    g = torch.Generator().manual_seed(3)
    triangles = robot.bumper_triangles(_random_base_poses((2, 3), g).to(torch.float32))
    assert triangles.shape == (2, 3, 12, 3, 3) and triangles.dtype == torch.float32


def test_robot_mesh_has_the_pioneer_footprint():
    mesh = robot.robot_mesh()
    length, width, _ = mesh.extents
    # the chassis 0.455 x 0.381 plus the bumper in front (0.26 m ahead of the centre, 0.40 wide)
    assert length == pytest.approx(0.455 / 2 + 0.26)
    assert width == pytest.approx(0.40)
    assert mesh.bounds[1, 2] == pytest.approx(0.237)
