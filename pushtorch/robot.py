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

Start clearance (issue 15): :func:`start_clearance` is the signed distance from points (an observed cloud)
to the robot's two collision boxes, the chassis and the bumper, both axis-aligned in the base frame (the
bumper box spans base x 0.24–0.26 m, ahead of the chassis' 0.2275 m: the robot approaches along its +x);
:func:`backoff_distance` is the exact distance the robot must reverse along its −x for every point to clear
both boxes by a margin, and :func:`backed_off` moves it there.
"""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError, InvalidPoseError

__all__ = [
    "BASE_LINK",
    "BUMPER_LINK",
    "URDF_PATH",
    "BumperGeometry",
    "backed_off",
    "backoff_distance",
    "base_pose_from_bumper",
    "base_pose_to_joints",
    "bumper_geometry",
    "bumper_mesh",
    "bumper_pose",
    "bumper_triangles",
    "joints_to_base_pose",
    "kinematic_chain",
    "link_inertial",
    "robot_mesh",
    "robot_boxes",
    "start_clearance",
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
    return se3.Pose.unchecked(torch.stack([x, y, z], -1), q)


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


def link_inertial(name: str) -> tuple[float, np.ndarray, np.ndarray]:
    """``(mass kg, centre of mass (3,), principal moments (3,))`` of a URDF link, as the URDF gives them (the
    MuJoCo world writes its robot from these; the URDF's inertia tensors are diagonal).

    Raises:
        InvalidPoseError: no such link, or a link without a diagonal inertia.
    """
    links = {link.get("name"): link for link in ET.fromstring(urdf_text()).findall("link")}
    inertial = links[name].find("inertial") if name in links else None
    if inertial is None:
        raise InvalidPoseError(f"URDF link {name!r} has no inertial")
    tensor = inertial.find("inertia").attrib
    if any(float(tensor.get(k, 0.0)) for k in ("ixy", "ixz", "iyz")):
        raise InvalidPoseError(f"URDF link {name!r} has an inertia with products of inertia")
    origin = inertial.find("origin")
    return (float(inertial.find("mass").get("value")), _floats(origin.get("xyz") if origin is not None else None),
            np.array([float(tensor[k]) for k in ("ixx", "iyy", "izz")]))


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
        return se3.Pose.unchecked(joints.new_zeros(*shape, 3), joints.new_zeros(*shape, 4))
    pose = se3.from_matrix(chain.forward_kinematics(flat).get_matrix())
    return se3.Pose.unchecked(pose.p.reshape(*shape, 3), pose.q.reshape(*shape, 4))


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
    return se3.apply(se3.Pose.unchecked(p, q), local)


def robot_mesh() -> trimesh.Trimesh:
    """Chassis and bumper collision boxes as one trimesh in the base frame (for drawing)."""
    geometry = bumper_geometry()
    chassis = trimesh.creation.box(extents=geometry.chassis_size)
    chassis.apply_translation(geometry.chassis_centre)
    bumper = bumper_mesh()
    bumper.apply_transform(se3.to_matrix(geometry.mount).numpy())
    return trimesh.util.concatenate([chassis, bumper])


def robot_boxes(dtype: torch.dtype = torch.float32, device: str | torch.device | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The chassis and bumper collision boxes in the base frame, axis-aligned: ``(centres, half_extents)``.

    Both are ``(2, 3)`` (row 0 the chassis, row 1 the bumper). The bumper box is its URDF box moved through
    the mount (``base_T_bumper``); a mount turned by a quarter turn swaps the plate's x and y extents.

    Raises:
        InvalidPoseError: the bumper mount is turned by other than a multiple of 90° (its box would not
            be axis-aligned with the base, which the clearance and back-off computations rely on), or the
            bumper is not ahead of the chassis (the robot approaches along its +x).
    """
    centres, halves = _robot_boxes64()
    return centres.to(dtype=dtype, device=device, copy=True), halves.to(dtype=dtype, device=device, copy=True)


@functools.lru_cache(maxsize=1)
def _robot_boxes64() -> tuple[torch.Tensor, torch.Tensor]:
    geometry = bumper_geometry()
    yaw = float(se3.yaw_of(geometry.mount.q))
    quarter = round(yaw / (math.pi / 2))
    if abs(yaw - quarter * math.pi / 2) > 1e-9:
        raise InvalidPoseError(f"the bumper mount must face along a base axis (yaw a multiple of 90°), got {yaw}")
    bumper_size = geometry.size[[1, 0, 2]] if quarter % 2 else geometry.size
    bumper_centre = se3.apply(geometry.mount, torch.as_tensor(geometry.box_centre, dtype=torch.float64))
    centres = torch.stack([torch.as_tensor(geometry.chassis_centre, dtype=torch.float64), bumper_centre])
    halves = torch.as_tensor(np.stack([geometry.chassis_size, bumper_size]) / 2, dtype=torch.float64)
    if not centres[1, 0] - halves[1, 0] > centres[0, 0]:  # the approach (and the back-off) assume it
        raise InvalidPoseError("the bumper box must sit ahead of the chassis centre, along the base's +x")
    return centres, halves


def _points_in_boxes(robot_start: se3.Pose, points: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Points ``(..., N, 3)`` relative to each box centre in the base frame, ``(..., 2, N, 3)``, and the
    boxes' half extents ``(2, 1, 3)``, in the points' dtype and device."""
    if not isinstance(points, torch.Tensor) or not points.is_floating_point() or points.dim() < 2 \
            or points.shape[-1] != 3:
        got = tuple(points.shape) if isinstance(points, torch.Tensor) else type(points).__name__
        raise InvalidPointCloudError(f"{name}: points must be a floating tensor (..., N, 3), got {got}")
    if not torch.isfinite(points).all():
        raise InvalidPointCloudError(f"{name}: points hold NaN or infinite values")
    se3.check_pose(robot_start, "robot_start")
    start = robot_start.to(dtype=points.dtype, device=points.device)
    rotation = se3.to_matrix(se3.Pose.unchecked(torch.zeros_like(start.p),
                                                start.q))[..., :3, :3]  # world_R_base (..., 3, 3)
    local = (points - start.p.unsqueeze(-2)) @ rotation  # (..., N, 3) in the base frame: R^T (x - p) per row
    centres, halves = robot_boxes(points.dtype, points.device)
    return local.unsqueeze(-3) - centres[:, None, :], halves[:, None, :]


def start_clearance(robot_start: se3.Pose, points: torch.Tensor) -> torch.Tensor:
    """Smallest signed distance (m) from ``points`` to the robot's chassis and bumper boxes, negative inside.

    Each box is an oriented box in the world: the base pose composed with the box's frame in the base
    (:func:`robot_boxes`). Exact box signed distances, batched.

    Args:
        robot_start: base poses ``(...)`` (any rigid pose; starts lie on the ground).
        points: ``(..., N, 3)`` world points (e.g. an observed cloud); batch dims broadcast with the poses.

    Returns:
        ``(...)`` the minimum over both boxes and all points; ``+inf`` for an empty point set.

    Raises:
        InvalidPointCloudError: misshaped or non-finite points. InvalidPoseError: a malformed pose.
    """
    rel, halves = _points_in_boxes(robot_start, points, "start_clearance")
    excess = rel.abs() - halves  # (..., 2, N, 3)
    distance = excess.clamp(min=0).norm(dim=-1) + excess.amax(-1).clamp(max=0)
    if distance.shape[-1] == 0:
        return distance.new_full(distance.shape[:-2], math.inf)
    return distance.flatten(-2).amin(-1)


def backoff_distance(robot_start: se3.Pose, points: torch.Tensor, clearance: float = 0.002) -> torch.Tensor:
    """How far (m) the robot must reverse along its own −x so every point clears both boxes by ``clearance``.

    The robot approaches along its +x (the bumper is ahead of the chassis), so reversing by ``s`` moves every
    point by ``+s`` along the base x. A point at distance ``e`` from a box's y–z cross-section is closer than
    ``clearance`` to the box exactly while its base-x offset from the box centre lies in the open interval
    ``±(h_x + sqrt(clearance² − e²))`` (never if ``e >= clearance``): each (point, box) pair gives an open
    interval of ``s``. The result is the smallest ``s >= 0`` in no interval
    (a sorted sweep, batched): 0 if the start already clears, otherwise at least the exit distance of
    every point inside the inflated boxes, and more if reversing would run the chassis into a point behind
    it. Exact for the given points.

    Args:
        robot_start: base poses ``(...)``.
        points: ``(..., N, 3)`` world points; batch dims broadcast with the poses.
        clearance: required distance (m), finite and >= 0.

    Returns:
        ``(...)`` back-off distances, ``>= 0``, in the points' dtype.

    Raises:
        InvalidParameterError: a negative or non-finite clearance. InvalidPointCloudError, InvalidPoseError:
            as :func:`start_clearance`.
    """
    if isinstance(clearance, bool) or not isinstance(clearance, int | float) or not math.isfinite(clearance) \
            or clearance < 0:
        raise InvalidParameterError(f"clearance must be a finite distance >= 0 (m), got {clearance!r}")
    rel, halves = _points_in_boxes(robot_start, points, "backoff_distance")
    cross = (rel[..., 1:].abs() - halves[..., 1:]).clamp(min=0).square().sum(-1)  # (..., 2, N)
    width = halves[..., 0] + (clearance**2 - cross).clamp(min=0).sqrt()
    hit = (cross < clearance**2) | (cross == 0)  # the footprint itself even when clearance² underflows
    x = rel[..., 0]
    s_out = (width - x).flatten(-2)
    live = hit.flatten(-2) & (s_out > 0)  # an interval wholly behind s = 0 never matters
    if not bool(live.any()):  # the usual case: nothing within reach ahead of or behind the robot
        return s_out.new_zeros(s_out.shape[:-1])
    s_in = (-width - x).flatten(-2)
    inf = torch.tensor(math.inf, dtype=s_in.dtype, device=s_in.device)
    s_in = torch.where(live, s_in, inf)
    s_out = torch.where(live, s_out, -inf)
    sentinel = s_in.new_full((*s_in.shape[:-1], 1), math.inf)  # an always-free gap after every interval
    s_in = torch.cat([s_in, sentinel], -1)
    s_out = torch.cat([s_out, -sentinel], -1)
    s_in, order = s_in.sort(-1)
    s_out = s_out.gather(-1, order)
    covered = s_out.cummax(-1).values.clamp(min=0)  # the union of the intervals so far reaches here
    before = torch.cat([torch.zeros_like(covered[..., :1]), covered[..., :-1]], -1)
    first_gap = (s_in >= before).int().argmax(-1, keepdim=True)  # argmax returns the first True
    return before.gather(-1, first_gap).squeeze(-1)


def backed_off(robot_start: se3.Pose, distance: torch.Tensor | float) -> se3.Pose:
    """The base poses ``(...)`` moved ``distance (...)`` metres straight back along their own −x axis."""
    distance = torch.as_tensor(distance, dtype=robot_start.p.dtype, device=robot_start.p.device)
    shape = torch.broadcast_shapes(robot_start.batch_shape, distance.shape)
    forward = se3.apply(se3.Pose.unchecked(torch.zeros_like(robot_start.p), robot_start.q),
                        torch.tensor([1.0, 0.0, 0.0], dtype=robot_start.p.dtype, device=robot_start.p.device))
    p = robot_start.p - distance.unsqueeze(-1) * forward
    return se3.Pose.unchecked(p.expand(*shape, 3), robot_start.q.expand(*shape, 4))
