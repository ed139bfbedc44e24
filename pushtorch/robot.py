"""The pushing robot: a Pioneer 3-DX-like base with a flat bumper, its URDF, kinematics and bumper mesh.

Paper, Experimental Setup ("a Pioneer 3-DX mobile robot equipped with a bumper affixed in front of it to
provide a flat surface for the pushes") and Rigid Body Motions (the manipulative link L of the robot,
here the bumper). One URDF, ``pushtorch/assets/pioneer_bumper.urdf``, serves two consumers:

    * pybullet loads it with a fixed "world" link placed at the push's start pose (pushtorch.sim);
    * pytorch_kinematics loads it with the world link at the origin, so the planar joint vector
      ``(x, y, yaw)`` IS the base pose, and batched forward kinematics gives the bumper's pose for any
      batch of base poses (the manipulator contact model needs it).

Frames: world z up, ground z = 0. The base frame lies on the ground at the centre of rotation, x forward.
The bumper link frame is the centre of the plate's front face, x along its outward normal, z up; the
plate's collision box lies behind it (x in [-thickness, 0]).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidPoseError

__all__ = [
    "BASE_LINK",
    "BUMPER_LINK",
    "URDF_PATH",
    "BumperGeometry",
    "base_pose_from_bumper",
    "base_pose_to_joints",
    "bumper_geometry",
    "bumper_mesh",
    "bumper_pose",
    "bumper_triangles",
    "joints_to_base_pose",
    "kinematic_chain",
    "robot_mesh",
    "urdf_text",
]

URDF_PATH = Path(__file__).resolve().parent / "assets" / "pioneer_bumper.urdf"
BASE_LINK = "base_link"
BUMPER_LINK = "bumper"
#: Joint order of the planar base in the URDF and in every joint vector here.
JOINT_NAMES = ("base_x", "base_y", "base_yaw")


@dataclass(frozen=True)
class BumperGeometry:
    """The bumper plate, read from the URDF.

    Attributes:
        size: ``(3,)`` thickness (x), width (y) and height (z) of the plate in metres.
        box_centre: ``(3,)`` centre of the collision box in the bumper link frame.
        mount: pose of the bumper link in the base frame (``base_T_bumper``), float64.
        chassis_size: ``(3,)`` extents of the chassis collision box.
        chassis_centre: ``(3,)`` centre of the chassis box in the base frame.
    """

    size: np.ndarray
    box_centre: np.ndarray
    mount: se3.Pose
    chassis_size: np.ndarray
    chassis_centre: np.ndarray

    @property
    def z_range(self) -> tuple[float, float]:
        """Heights above the ground (base frame z) spanned by the plate."""
        z = float(self.mount.p[2] + self.box_centre[2])
        return z - self.size[2] / 2, z + self.size[2] / 2


def _planar_pose(
    x: torch.Tensor, y: torch.Tensor, yaw: torch.Tensor, z: torch.Tensor | float = 0.0
) -> se3.Pose:
    """Poses at (x, y, z) turned by ``yaw`` about z, in the dtype of ``x`` (se3.from_xy_yaw is float32)."""
    x, y, yaw = torch.broadcast_tensors(x, y, yaw)
    z = torch.as_tensor(z, dtype=x.dtype, device=x.device).expand_as(x)
    zeros = torch.zeros_like(yaw)
    q = torch.stack([torch.cos(yaw / 2), zeros, zeros, torch.sin(yaw / 2)], -1)
    return se3.Pose(torch.stack([x, y, z], -1), q)


def urdf_text() -> str:
    """The robot URDF as a string (for pybullet, pytorch_kinematics or a viewer)."""
    return URDF_PATH.read_text()


def _floats(text: str | None, default: str = "0 0 0") -> np.ndarray:
    return np.array([float(v) for v in (text or default).split()], dtype=np.float64)


def _box_of(link: ET.Element, what: str = "collision") -> tuple[np.ndarray, np.ndarray]:
    element = link.find(what)
    box = element.find("geometry/box") if element is not None else None
    if box is None:
        raise InvalidPoseError(f"URDF link {link.get('name')!r} has no {what} box")
    origin = element.find("origin")
    return _floats(box.get("size")), _floats(origin.get("xyz") if origin is not None else None)


@functools.lru_cache(maxsize=1)
def bumper_geometry() -> BumperGeometry:
    """The bumper and chassis boxes and the bumper mount, parsed from the shipped URDF."""
    root = ET.fromstring(urdf_text())
    links = {link.get("name"): link for link in root.findall("link")}
    size, centre = _box_of(links[BUMPER_LINK])
    chassis_size, chassis_centre = _box_of(links[BASE_LINK])
    joint = next(j for j in root.findall("joint") if j.find("child").get("link") == BUMPER_LINK)
    origin = joint.find("origin")
    xyz = _floats(origin.get("xyz"))
    rpy = _floats(origin.get("rpy"))
    if np.abs(rpy[:2]).max() > 1e-12:
        raise InvalidPoseError("the bumper mount must be level (roll = pitch = 0)")
    x, y, yaw = (torch.tensor(v, dtype=torch.float64) for v in (xyz[0], xyz[1], rpy[2]))
    mount = _planar_pose(x, y, yaw, z=float(xyz[2]))
    return BumperGeometry(size, centre, mount, chassis_size, chassis_centre)


@functools.lru_cache(maxsize=8)
def _chain(dtype: torch.dtype, device: str):
    import pytorch_kinematics as pk

    chain = pk.build_serial_chain_from_urdf(urdf_text(), end_link_name=BUMPER_LINK, root_link_name="world")
    return chain.to(dtype=dtype, device=device)


def kinematic_chain(dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"):
    """The serial ``pytorch_kinematics`` chain world → bumper with joints ``(base_x, base_y, base_yaw)``.

    Cached per dtype and device; ``forward_kinematics`` takes ``(B, 3)`` joint values.
    """
    return _chain(dtype, str(torch.device(device)))


def base_pose_to_joints(base: se3.Pose, atol: float = 1e-4) -> torch.Tensor:
    """Planar joint values ``(..., 3)`` = (x, y, yaw) of base poses ``(...)`` on the ground.

    Raises:
        InvalidPoseError: a pose is not planar (base above/below the ground or tilted beyond ``atol``).
    """
    p, q = base.p, se3.check_unit_quaternion(base.q, name="base.q")
    if p.shape[-1:] != (3,):
        raise InvalidPoseError(f"base.p must have shape (..., 3), got {tuple(p.shape)}")
    tilt = (q[..., 1] ** 2 + q[..., 2] ** 2).sqrt()
    if p.numel() and (p[..., 2].abs().max() > atol or tilt.max() > atol):
        raise InvalidPoseError("a robot base pose must lie on the ground (z = 0) and rotate about z only")
    shape = torch.broadcast_shapes(p.shape[:-1], q.shape[:-1])
    yaw = se3.yaw_of(q).expand(shape)
    return torch.stack([p[..., 0].expand(shape), p[..., 1].expand(shape), yaw], -1)


def joints_to_base_pose(joints: torch.Tensor) -> se3.Pose:
    """Base poses ``(...)`` from planar joint values ``(..., 3)`` = (x, y, yaw)."""
    return _planar_pose(joints[..., 0], joints[..., 1], joints[..., 2])


def bumper_pose(base: se3.Pose) -> se3.Pose:
    """Pose of the bumper link (centre of the plate's front face) for base poses ``(...)``.

    Batched forward kinematics of the URDF through ``pytorch_kinematics`` (flattened to one batch dim and
    reshaped back); dtype and device follow ``base.p``.

    Raises:
        InvalidPoseError: a base pose is not planar (see :func:`base_pose_to_joints`).
    """
    joints = base_pose_to_joints(base)
    shape = joints.shape[:-1]
    chain = kinematic_chain(joints.dtype, joints.device)
    flat = joints.reshape(-1, 3)
    if flat.shape[0] == 0:
        return se3.Pose(joints.new_zeros(*shape, 3), joints.new_zeros(*shape, 4))
    pose = se3.from_matrix(chain.forward_kinematics(flat).get_matrix())
    return se3.Pose(pose.p.reshape(*shape, 3), pose.q.reshape(*shape, 4))


def base_pose_from_bumper(bumper: se3.Pose) -> se3.Pose:
    """The base pose ``(...)`` that puts the bumper link at ``bumper (...)`` (inverse of the mount).

    Only the bumper's position in the xy plane and its heading matter; the result lies on the ground.
    """
    mount = bumper_geometry().mount.to(bumper.p.dtype)
    base = se3.compose(bumper, se3.inverse(mount).to(bumper.p.device))
    return _planar_pose(base.p[..., 0], base.p[..., 1], se3.yaw_of(base.q))


def bumper_mesh(base: se3.Pose | None = None) -> trimesh.Trimesh:
    """The bumper's collision box as a trimesh: in the bumper link frame, or in world for one base pose."""
    geometry = bumper_geometry()
    mesh = trimesh.creation.box(extents=geometry.size)
    mesh.apply_translation(geometry.box_centre)
    if base is not None:
        if base.batch_shape != torch.Size([]):
            raise InvalidPoseError("bumper_mesh takes one base pose; use bumper_triangles for a batch")
        pose = bumper_pose(base.to(torch.float64))
        mesh.apply_transform(se3.to_matrix(pose).numpy())
    return mesh


def bumper_triangles(base: se3.Pose) -> torch.Tensor:
    """The bumper's collision triangles in world, ``(..., F, 3, 3)`` (F = 12), for base poses ``(...)``.

    For closest-point queries from object points to the bumper (manipulator contact model).
    """
    mesh = bumper_mesh()
    local = torch.as_tensor(np.array(mesh.triangles), dtype=base.p.dtype, device=base.p.device)  # (F, 3, 3)
    pose = bumper_pose(base)
    shape = pose.batch_shape
    p = pose.p.reshape(*shape, 1, 1, 3)
    q = pose.q.reshape(*shape, 1, 1, 4)
    return se3.apply(se3.Pose(p, q), local)


def robot_mesh() -> trimesh.Trimesh:
    """Chassis and bumper collision boxes as one trimesh in the base frame (for drawing)."""
    geometry = bumper_geometry()
    chassis = trimesh.creation.box(extents=geometry.chassis_size)
    chassis.apply_translation(geometry.chassis_centre)
    bumper = bumper_mesh()
    bumper.apply_transform(se3.to_matrix(geometry.mount).numpy())
    return trimesh.util.concatenate([chassis, bumper])
