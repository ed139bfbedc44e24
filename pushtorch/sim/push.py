"""One push: the actions a = (ẋ, θ̇), the robot's twist controller, training placement, and execution.

Paper, Rigid Body Motions ("the robot will attempt to maintain a constant predefined velocity throughout
the push, although given the limitations of the robot's dynamics the resulting velocity may be less in
cases of high mass and/or friction") and the experiment tables (Number of Actions 3, Angle Range
[-10, 10], Action Duration 4 s, Action Speed 0.1 m/s).

Units: the Angle Range is read in degrees per second. A 4 s push at ±10 °/s turns the robot by ±40°, a
push that curves; at ±10 rad/s the robot would spin 6.4 turns in 4 s and push nothing. Inside the library
every angular velocity is in rad/s (SI); only the configuration speaks °/s.

:func:`execute_push` is numpy-only (workers of the parallel runner call it); :func:`make_actions` and
:func:`place_robot_against` speak torch and :class:`pushtorch.se3.Pose`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.sim.geometry import check_inside_world, quat_conjugate, quat_multiply, quat_rotate, yaw_quat

if TYPE_CHECKING:  # either engine's world runs a push (pushtorch.sim.engines.make_world)
    from pushtorch.sim.pybullet_world import PushWorld

__all__ = [
    "ACTION_DURATION",
    "ACTION_SPEED",
    "PushOutcome",
    "execute_push",
    "make_actions",
    "place_robot_against",
    "record_times",
]

#: The paper's action duration (s) and target speed (m/s).
ACTION_DURATION = 4.0
ACTION_SPEED = 0.1


def make_actions(
    count: int = 3,
    angle_range_deg: tuple[float, float] = (-10.0, 10.0),
    speed: float = ACTION_SPEED,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """The paper's actions: ``count`` angular velocities evenly spaced over the Angle Range.

    Args:
        count: number of actions N (1 gives the middle of the range; 3 gives -10, 0, +10 °/s).
        angle_range_deg: lowest and highest yaw rate in degrees per second (see module notes).
        speed: forward speed ẋ in m/s, the same for every action.

    Returns:
        ``(N, 2)`` tensor of actions ``(ẋ m/s, θ̇ rad/s)``.

    Raises:
        InvalidParameterError: count < 1, a non-finite or reversed range, or a non-positive speed.
    """
    low, high = (float(v) for v in angle_range_deg)
    if int(count) != count or count < 1:
        raise InvalidParameterError(f"the number of actions must be a positive integer, got {count!r}")
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise InvalidParameterError(
            f"the angle range must be finite with low <= high, got {angle_range_deg!r}"
        )
    if not (math.isfinite(speed) and speed > 0):
        raise InvalidParameterError(f"the action speed must be positive (m/s), got {speed!r}")
    if count == 1:
        rates_deg = torch.tensor([(low + high) / 2], dtype=torch.float64)
    else:
        rates_deg = torch.linspace(low, high, int(count), dtype=torch.float64)
    actions = torch.stack([torch.full_like(rates_deg, float(speed)), torch.deg2rad(rates_deg)], -1)
    return actions.to(dtype)


def _slab_min_x(
    triangles: np.ndarray, y_range: tuple[float, float], z_range: tuple[float, float]
) -> float | None:
    """Smallest x of the surface ``triangles (F, 3, 3)`` inside the slab ``y_range × z_range``.

    The minimum of the linear function x over a triangle clipped to the slab lies at a vertex of the
    clipped polygon, and every such vertex is one of: a triangle corner inside the slab, a crossing of a
    triangle edge with a slab face, or a point where one of the slab's four edge lines (parallel to x)
    pierces the triangle. All three candidate sets are computed at once; the result is exact.
    """
    tri = np.asarray(triangles, dtype=np.float64)
    (y0, y1), (z0, z1) = y_range, z_range
    eps = 1e-12

    def inside(points: np.ndarray) -> np.ndarray:
        y, z = points[..., 1], points[..., 2]
        return (y >= y0 - eps) & (y <= y1 + eps) & (z >= z0 - eps) & (z <= z1 + eps)

    candidates = [tri.reshape(-1, 3)[inside(tri.reshape(-1, 3))]]
    start, end = tri, np.roll(tri, -1, axis=1)  # (F, 3, 3) edges
    a, b = start.reshape(-1, 3), end.reshape(-1, 3)
    for axis, bound in ((1, y0), (1, y1), (2, z0), (2, z1)):
        denom = b[:, axis] - a[:, axis]
        ok = np.abs(denom) > eps
        t = np.where(ok, (bound - a[:, axis]) / np.where(ok, denom, 1.0), -1.0)
        ok &= (t >= 0.0) & (t <= 1.0)
        points = a + t[:, None] * (b - a)
        candidates.append(points[ok & inside(points)])
    p0, p1, p2 = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = p1 - p0, p2 - p0
    det = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]  # area of the yz projection (x 2)
    good = np.abs(det) > eps
    safe = np.where(good, det, 1.0)
    for y, z in ((y0, z0), (y0, z1), (y1, z0), (y1, z1)):
        dy, dz = y - p0[:, 1], z - p0[:, 2]
        u = (dy * e2[:, 2] - dz * e2[:, 1]) / safe
        v = (e1[:, 1] * dz - e1[:, 2] * dy) / safe
        hit = good & (u >= -eps) & (v >= -eps) & (u + v <= 1.0 + eps)
        x = p0[:, 0] + u * e1[:, 0] + v * e2[:, 0]
        candidates.append(np.stack([x, np.full_like(x, y), np.full_like(x, z)], -1)[hit])
    points = np.concatenate(candidates)
    return float(points[:, 0].min()) if len(points) else None


def place_robot_against(
    mesh,
    object_pose: se3.Pose,
    approach_yaw: float = 0.0,
    lateral_offset: float = 0.0,
    gap: float = 0.002,
) -> se3.Pose:
    """The training start pose: the bumper flat against the object, centred on the side facing the robot.

    The robot heads along ``approach_yaw`` (0: along +x towards the object); the bumper's centre line
    passes ``lateral_offset`` metres to the left of the object's centre; the robot is moved forward until
    the bumper's front face is ``gap`` metres from the first point of the object it would touch (exact,
    from the mesh clipped to the plate's width and height band).

    Args:
        mesh: the object's trimesh in its own frame (``ObjectModel.mesh``).
        object_pose: the object's pose in world (one pose).
        approach_yaw: robot heading in rad.
        lateral_offset: m, along the robot's left (+y of its heading).
        gap: m between bumper and object at the start (a few mm avoids a start in penetration).

    Returns:
        The robot base pose (one pose, on the ground, float32).

    Raises:
        InvalidPoseError: ``object_pose`` is not a single pose.
        InvalidParameterError: the bumper would miss the object (offset beyond the object's width).
    """
    from pushtorch.robot import bumper_geometry

    if object_pose.batch_shape != torch.Size([]):
        raise InvalidPoseError("place_robot_against takes one object pose")
    if not (math.isfinite(gap) and gap >= 0):
        raise InvalidParameterError(f"the placement gap must be >= 0, got {gap!r}")
    geometry = bumper_geometry()
    heading = yaw_quat(-float(approach_yaw))
    p = object_pose.p.detach().cpu().double().numpy()
    q = object_pose.q.detach().cpu().double().numpy()
    world = quat_rotate(q, np.asarray(mesh.triangles, dtype=np.float64)) + p  # (F, 3, 3)
    local = quat_rotate(heading, world)  # heading frame: x along the approach, same z
    centre = quat_rotate(heading, p)
    width = float(geometry.size[1])
    lateral = float(centre[1] + lateral_offset)
    x_first = _slab_min_x(local, (lateral - width / 2, lateral + width / 2), geometry.z_range)
    if x_first is None:
        raise InvalidParameterError(
            f"a bumper centred {lateral_offset:+.3f} m from the object's centre misses the object"
        )
    bumper_local = np.array([x_first - gap, lateral, float(geometry.mount.p[2])])
    bumper_world = quat_rotate(yaw_quat(float(approach_yaw)), bumper_local)
    bumper = se3.from_xy_yaw(float(bumper_world[0]), float(bumper_world[1]), float(approach_yaw),
                             z=float(bumper_world[2]))
    from pushtorch.robot import base_pose_from_bumper

    return base_pose_from_bumper(bumper.to(torch.float64)).to(torch.float32)


@dataclass
class PushOutcome:
    """The result of one push, numpy float64 (poses as position (3,) and wxyz quaternion (4,)).

    Attributes:
        object_final_p, object_final_q: object pose after the push and the settle time.
        object_trajectory_p, object_trajectory_q: ``(T, 3)``, ``(T, 4)`` at the record rate from t = 0.
        robot_trajectory_p, robot_trajectory_q: base poses ``(T, ...)`` at the same times.
        time: ``(T,)`` seconds since the push started.
        touched: the robot touched the object at some step.
        first_contact_time: s of the first contact (NaN if never).
        tipped: the object's up axis tilted more than the tip angle at a recorded time.
        left_ground: the object's centre rose or sank beyond the lift tolerance at a recorded time.
        object_initial_p, object_initial_q: object pose at t = 0 as simulated (equal to the input).
    """

    object_initial_p: np.ndarray
    object_initial_q: np.ndarray
    object_final_p: np.ndarray
    object_final_q: np.ndarray
    object_trajectory_p: np.ndarray
    object_trajectory_q: np.ndarray
    robot_trajectory_p: np.ndarray
    robot_trajectory_q: np.ndarray
    time: np.ndarray
    touched: bool
    first_contact_time: float
    tipped: bool
    left_ground: bool


def record_times(duration: float, time_step: float, record_rate: float) -> tuple[np.ndarray, int]:
    """Physics step indices of the recorded samples and the steps between them.

    Returns:
        (steps ``(T,)`` int, stride): samples at t = 0, stride·dt, ... up to ``duration``.
    """
    stride = max(1, int(round(1.0 / (record_rate * time_step))))
    n_steps = int(round(duration / time_step))
    return np.arange(0, n_steps + 1, stride), stride


def execute_push(
    world: PushWorld,
    robot_start_p: np.ndarray,
    robot_start_q: np.ndarray,
    object_p: np.ndarray,
    object_q: np.ndarray,
    speed: float,
    yaw_rate: float,
    duration: float,
    mass: float,
    ground_friction: float,
) -> PushOutcome:
    """Run one push in ``world`` and return what happened (no torch, no randomness).

    The object is (re-)spawned at ``(object_p, object_q)`` with ``mass`` and ``ground_friction``; the robot
    starts at rest at ``(robot_start_p, robot_start_q)`` (base frame, on the ground) and tracks the body
    twist ``(speed, yaw_rate)`` for ``duration`` s with bounded force and torque, then is commanded to stop
    while the world runs ``settle_time`` more seconds; the final pose is read at rest.

    Raises:
        InvalidParameterError: non-finite action or duration, bad mass/friction, or a start outside the
            simulated world (:func:`pushtorch.sim.geometry.check_inside_world`).
        SimulationError: pybullet failed, or the object's pose became non-finite.
    """
    from pushtorch.errors import SimulationError

    if not (math.isfinite(speed) and math.isfinite(yaw_rate)):
        raise InvalidParameterError(f"the action must be finite, got ({speed!r}, {yaw_rate!r})")
    if not (math.isfinite(duration) and duration > 0):
        raise InvalidParameterError(f"the push duration must be positive, got {duration!r}")
    s = world.settings
    object_p = np.asarray(object_p, dtype=np.float64)
    object_q = np.asarray(object_q, dtype=np.float64)
    object_q = object_q / np.linalg.norm(object_q)
    robot_start_p = np.asarray(robot_start_p, dtype=np.float64)
    robot_start_q = np.asarray(robot_start_q, dtype=np.float64)
    robot_start_q = robot_start_q / np.linalg.norm(robot_start_q)
    check_inside_world(world.spec, s, object_p, object_q, robot_start_p, speed, duration)

    # Every push is simulated in the robot's start frame (robot at the origin heading +x) and mapped back:
    # pybullet's friction directions follow the world axes, so the same push turned by 30° about the
    # world's z ended up to 7 cm elsewhere; in one frame, a push is a function of its relative set-up alone.
    to_start = quat_conjugate(robot_start_q)
    world.spawn_object(quat_rotate(to_start, object_p - robot_start_p), quat_multiply(to_start, object_q),
                       float(mass), float(ground_friction))
    world.place_robot(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))

    def object_pose() -> tuple[np.ndarray, np.ndarray]:
        p, q = world.object_pose()
        return robot_start_p + quat_rotate(robot_start_q, p), quat_multiply(robot_start_q, q)

    steps, _ = record_times(duration, s.time_step, s.record_rate)
    n_steps = int(round(duration / s.time_step))
    n_records = len(steps)
    obj_traj_p = np.empty((n_records, 3))
    obj_traj_q = np.empty((n_records, 4))
    joints = np.empty((n_records, 3))
    obj_traj_p[0], obj_traj_q[0] = object_pose()
    joints[0] = world.robot_joints()
    touched = False
    first_contact = math.nan
    control_every = world.control_every
    k = 1
    for step in range(1, n_steps + 1):
        if (step - 1) % control_every == 0:
            world.drive(speed, yaw_rate)
        world.step()
        if not touched and world.touching():
            touched, first_contact = True, step * s.time_step
        if k < n_records and step == steps[k]:
            obj_traj_p[k], obj_traj_q[k] = object_pose()
            joints[k] = world.robot_joints()
            k += 1
    world.drive(0.0, 0.0)
    for step in range(int(round(s.settle_time / s.time_step))):
        if step % control_every == 0:
            world.drive(0.0, 0.0)
        world.step()
        if not touched and world.touching():
            touched, first_contact = True, (n_steps + step + 1) * s.time_step
    final_p, final_q = object_pose()
    if not (np.isfinite(final_p).all() and np.isfinite(final_q).all()):
        raise SimulationError(f"the pose of {world.spec.name!r} became non-finite during the push")
    # An object thrown off the ground (a robot start inside it: issue 15) is recorded with left_ground set,
    # so training skips it and the experiments count it as thrown; starts outside the world were refused above.

    # Robot base poses in world: the joints move the base within the start frame.
    planar = np.stack([joints[:, 0], joints[:, 1], np.zeros(n_records)], -1)
    robot_p = robot_start_p + quat_rotate(robot_start_q, planar)
    robot_q = quat_multiply(robot_start_q, yaw_quat(joints[:, 2]))

    # Validity: tilt of the object's up axis relative to its start, and height change of its centre.
    all_p = np.concatenate([obj_traj_p, final_p[None]])
    all_q = np.concatenate([obj_traj_q, final_q[None]])
    relative = quat_multiply(all_q, quat_conjugate(object_q))
    up = quat_rotate(relative, np.array([0.0, 0.0, 1.0]))
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1.0, 1.0)))
    tipped = bool((tilt > s.tip_angle_deg).any())
    left_ground = bool((np.abs(all_p[:, 2] - object_p[2]) > s.lift_tolerance).any())
    return PushOutcome(
        object_initial_p=object_p,
        object_initial_q=object_q,
        object_final_p=final_p,
        object_final_q=final_q,
        object_trajectory_p=obj_traj_p,
        object_trajectory_q=obj_traj_q,
        robot_trajectory_p=robot_p,
        robot_trajectory_q=robot_q,
        time=steps * s.time_step,
        touched=touched,
        first_contact_time=first_contact,
        tipped=tipped,
        left_ground=left_ground,
    )
