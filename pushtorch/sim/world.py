"""The pybullet world of a push: ground, robot with bumper, one object; created once, reset per push.

Paper, Experimental Setup: the authors simulated a Pioneer 3-DX with a bumper pushing objects in
Gazebo/ODE; pybullet replaces that engine here and is the ground truth of every push.

Design (decisions the paper leaves open, see docs/method.md):
    * The ground is a large static box whose top face is z = 0 (a box gives the objects a full contact
      manifold at once; a pybullet plane starts with one point and lets a resting object rock).
    * Objects are compounds of the :attr:`ObjectModel.collision_parts` convex pieces (pieces that are
      axis-aligned boxes become exact box primitives, the others convex hulls), free rigid bodies
      (maximal coordinates), with the collision margin set to 0 so an object rests exactly at its
      ``rest_height`` (the default 1 mm margin lifts it). Mass and friction are set per push; the inertia is
      the mesh's (uniform density) scaled to the sampled mass, in the principal frame of the mesh.
    * The bumper's friction acts in the robot's horizontal plane only (anisotropic friction): vertical
      static friction between plate and object is indeterminate for a rigid solver and pressed the object
      into the ground or lifted it, which made the effective ground friction erratic.
    * Friction: pybullet multiplies the coefficients of the two bodies in contact. The object's own
      coefficient is fixed to ``object_friction`` (1.0 by default); the ground gets
      ``ground_friction / object_friction`` and the bumper ``bumper_friction / object_friction``, so the
      effective object-ground and object-bumper coefficients are exactly the sampled / configured ones.
    * The world ends at the ground's edge (``ground_half_extent``, 50 m): an object beyond it would fall
      for ever. :func:`check_inside_world` refuses push inputs whose object or robot could leave the ground
      during the push (start position plus the distance the push can travel), or whose object starts
      below the ground; an object that still ends below the ground box is an error, never a record.
    * The robot is the package's URDF with a fixed world link placed at the push's start pose; its planar
      joints (x, y, yaw) start at 0, so joint x points along the start heading (see pushtorch.robot). Their
      velocity motors track the commanded body twist; each planar axis is bounded by ``max_force`` and yaw
      by ``max_torque`` (a box bound in the start frame: within the ±40° of a push the forward force
      available lies between ``max_force`` and 1.3 ``max_force``).

The simulation itself runs on numpy and pybullet (no torch on the workers' hot path).
Poses at this level are numpy ``(position (3,), quaternion (4,) wxyz)`` pairs; conversions to pybullet's
x,y,z,w happen here and nowhere else in the simulator.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pushtorch.errors import InvalidParameterError, SimulationError
from pushtorch.sim.drive import DRIVES, DriveSettings, DriveState, wheel_forces

__all__ = [
    "ENGINES",
    "ObjectSpec",
    "PushWorld",
    "SimSettings",
    "WORLD_VERSION",
    "check_inside_world",
    "make_world",
    "settings_from_config",
    "object_spec",
    "support_points",
    "quat_conjugate",
    "quat_multiply",
    "quat_rotate",
    "wxyz",
    "xyzw",
    "yaw_quat",
]

#: Version of the simulated world, written into every run manifest: records of another version are refused
#: (pushtorch.sim.runner), never mixed. 2: a fresh object collision shape per push (1 let a convex hull's
#: state carry over between the pushes of one worker). 3: mirror-symmetric pushes (a compliant floor, hulls
#: on support spheres, no early solver exit, every push simulated in the robot's start frame).
WORLD_VERSION = 3

#: Joint indices of pushtorch/assets/pioneer_bumper.urdf as pybullet numbers them.
JOINT_X, JOINT_Y, JOINT_YAW = 0, 1, 2
BASE_LINK_INDEX, BUMPER_LINK_INDEX = 2, 3
#: The engines a world runs in (``world.engine``; pushtorch.sim.mujoco_world for MuJoCo). Part of the world's
#: identity: pushes, models and caches of one engine are never mixed with another's.
ENGINES = ("pybullet", "mujoco")


@dataclass(frozen=True)
class SimSettings:
    """Physics and controller settings of the push simulator (the ``sim`` config group).

    Attributes:
        engine: ``pybullet`` (default) or ``mujoco``, the engine the world runs in (:func:`make_world`).
        time_step: physics step in s. 1/240 s keeps 0.1 m/s pushes quasi-static and stable.
        solver_iterations: constraint-solver iterations per step.
        control_every: physics steps between two updates of the robot's velocity targets.
        record_rate: Hz of the recorded object and robot trajectories (t = 0 included).
        settle_time: s the world keeps running after the push with the robot commanded to stop; the final
            object pose is read after it, at rest.
        bumper_friction: effective bumper-object friction coefficient.
        object_friction: the object's own pybullet friction coefficient (see module notes).
        max_force: N, bound of each planar drive axis of the robot (wheel traction of a 9 kg base, ~0.7 g).
        max_torque: N m, bound of the yaw drive.
        tip_angle_deg: an object whose up axis tilts more than this during the push has "tipped".
        lift_tolerance: m; an object whose centre rises or sinks more than this "left the ground".
        ground_half_extent: m, half side of the square ground box.
        robot: ``p3dx`` (default: the Pioneer's wheels, traction and motors, :mod:`pushtorch.sim.drive`) or
            ``ideal`` (the planar joints' velocity motors bounded by ``max_force`` and ``max_torque``, the
            robot before issue 16).
        drive: the ``p3dx`` drive's parameters (a :class:`~pushtorch.sim.drive.DriveSettings` or a mapping).
    """

    time_step: float = 1.0 / 240.0
    engine: str = "pybullet"
    solver_iterations: int = 50
    control_every: int = 4
    record_rate: float = 10.0
    settle_time: float = 0.25
    bumper_friction: float = 0.5
    object_friction: float = 1.0
    max_force: float = 60.0
    max_torque: float = 10.0
    tip_angle_deg: float = 10.0
    lift_tolerance: float = 0.01
    ground_half_extent: float = 50.0
    robot: str = "p3dx"
    drive: DriveSettings = field(default_factory=DriveSettings)

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise InvalidParameterError(f"world.engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")
        if self.robot not in DRIVES:
            raise InvalidParameterError(f"sim.robot must be one of {', '.join(DRIVES)}, got {self.robot!r}")
        if not isinstance(self.drive, DriveSettings):
            try:
                object.__setattr__(self, "drive", DriveSettings(**dict(self.drive)))
            except TypeError as exc:
                raise InvalidParameterError(f"sim.drive: {exc}") from exc
        positive = {
            "time_step": self.time_step,
            "record_rate": self.record_rate,
            "object_friction": self.object_friction,
            "max_force": self.max_force,
            "max_torque": self.max_torque,
            "tip_angle_deg": self.tip_angle_deg,
            "lift_tolerance": self.lift_tolerance,
            "ground_half_extent": self.ground_half_extent,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise InvalidParameterError(f"sim.{name} must be a positive finite number, got {value!r}")
        if not (np.isfinite(self.bumper_friction) and self.bumper_friction >= 0):
            raise InvalidParameterError(f"sim.bumper_friction must be >= 0, got {self.bumper_friction!r}")
        if not (np.isfinite(self.settle_time) and self.settle_time >= 0):
            raise InvalidParameterError(f"sim.settle_time must be >= 0, got {self.settle_time!r}")
        if int(self.solver_iterations) < 1 or int(self.control_every) < 1:
            raise InvalidParameterError("sim.solver_iterations and sim.control_every must be >= 1")
        if self.record_rate * self.time_step > 1.0:
            raise InvalidParameterError("sim.record_rate must not exceed the physics rate 1/time_step")


@dataclass(frozen=True)
class ObjectSpec:
    """What a worker needs to build an object in pybullet: plain arrays, cheap to send to a process.

    Attributes:
        name: object name (catalogue name or mesh file stem).
        parts: convex pieces as ``(V_i, 3)`` vertex arrays in the object frame (origin at the centre of
            mass, metres).
        part_faces: ``(F_i, 3)`` triangle vertex indices of each piece.
        rest_height: height of the origin above the ground when upright.
        inertia_per_kg: ``(3,)`` principal moments of inertia of a 1 kg object of this shape (kg m²/kg).
        principal_rotation: ``(4,)`` wxyz rotation of the principal inertia frame in the object frame.
    """

    name: str
    parts: tuple[np.ndarray, ...]
    part_faces: tuple[np.ndarray, ...]
    rest_height: float
    inertia_per_kg: np.ndarray
    principal_rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))


def object_spec(model) -> ObjectSpec:
    """The :class:`ObjectSpec` of an :class:`pushtorch.objects.ObjectModel` (uniform density).

    Raises:
        InvalidParameterError: the model has no collision part or a degenerate mass distribution.
    """
    mesh = model.mesh
    if not model.collision_parts:
        raise InvalidParameterError(f"object {model.name!r} has no collision parts")
    volume = float(mesh.volume)
    if not (np.isfinite(volume) and volume > 0):
        raise InvalidParameterError(f"object {model.name!r} encloses no volume")
    # trimesh's moment_inertia is about the centre of mass at density 1; divide by the volume for 1 kg.
    tensor = np.asarray(mesh.moment_inertia, dtype=np.float64) / volume
    off_diagonal = np.abs(tensor - np.diag(np.diag(tensor))).max()
    if off_diagonal <= 1e-9 * np.abs(tensor).max():
        moments, rotation = np.diag(tensor).copy(), np.array([1.0, 0.0, 0.0, 0.0])
    else:
        moments, axes = np.linalg.eigh(tensor)
        if np.linalg.det(axes) < 0:
            axes[:, 2] = -axes[:, 2]
        rotation = _matrix_to_wxyz(axes)
    if (moments <= 0).any():
        raise InvalidParameterError(f"object {model.name!r} has a non-positive principal moment of inertia")
    parts = tuple(np.array(p.vertices, dtype=np.float64) for p in model.collision_parts)
    faces = tuple(np.array(p.faces, dtype=np.int64) for p in model.collision_parts)
    return ObjectSpec(model.name, parts, faces, float(model.rest_height), moments, rotation)


#: Thickness of the ground box (m); its top face is z = 0.
GROUND_THICKNESS = 0.1
#: How far an object may start below the ground plane (m): resting poses sit exactly on it.
GROUND_PENETRATION_TOLERANCE = 0.005
#: How far the robot reaches from its base origin (m): the bumper plate's corners (see the URDF).
ROBOT_REACH = 0.5


def check_inside_world(
    spec: ObjectSpec,
    settings: SimSettings,
    object_p: np.ndarray,
    object_q: np.ndarray,
    robot_p: np.ndarray,
    speed: np.ndarray | float,
    duration: float,
) -> None:
    """Refuse pushes that could leave the simulated world (before any is simulated).

    The ground is the square ``|x|, |y| <= ground_half_extent``; a push moves at most ``|speed| * duration``
    m. Every object start (its centre plus its farthest point) and every robot start (plus
    :data:`ROBOT_REACH`) must lie that far inside the edge, and no object may start below the ground
    plane (beyond :data:`GROUND_PENETRATION_TOLERANCE`) or higher than the ground is wide.

    Args:
        object_p, object_q: ``(N, 3)``, ``(N, 4)`` object start poses (wxyz); robot_p: ``(N, 3)``;
        speed: ``(N,)`` or a scalar, m/s; duration: s per push.

    Raises:
        InvalidParameterError: a start outside the world, naming the first push and the limit.
    """
    object_p = np.asarray(object_p, dtype=np.float64).reshape(-1, 3)
    object_q = np.asarray(object_q, dtype=np.float64).reshape(-1, 4)
    robot_p = np.asarray(robot_p, dtype=np.float64).reshape(-1, 3)
    travel = np.abs(np.broadcast_to(np.asarray(speed, dtype=np.float64), (len(object_p),))) * float(duration)
    half = settings.ground_half_extent
    vertices = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in spec.parts])
    radius = float(np.linalg.norm(vertices, axis=-1).max())
    for what, p, margin in (("object", object_p, radius + travel), ("robot", robot_p, ROBOT_REACH + travel)):
        outside = np.abs(p[:, :2]).max(-1) + margin > half
        if outside.any():
            i = int(np.argmax(outside))
            raise InvalidParameterError(
                f"push {i} starts the {what} at ({p[i, 0]:.3g}, {p[i, 1]:.3g}) m, which with its reach and the"
                f" push's travel ({margin[i]:.3g} m) leaves the simulated ground |x|, |y| <= {half:g} m"
                " (sim.ground_half_extent): place it nearer the origin"
            )
    # lowest point of each distinct start pose (training plans repeat one pose thousands of times)
    poses, inverse = np.unique(np.concatenate([object_p, object_q], -1), axis=0, return_inverse=True)
    lowest = np.array([p[2] + quat_rotate(np.broadcast_to(q, (len(vertices), 4)), vertices)[:, 2].min()
                       for p, q in zip(poses[:, :3], poses[:, 3:], strict=True)])[inverse.reshape(-1)]
    sunk = lowest < -GROUND_PENETRATION_TOLERANCE
    if sunk.any():
        i = int(np.argmax(sunk))
        raise InvalidParameterError(
            f"push {i} starts the object {-lowest[i]:.3g} m below the ground (z = {object_p[i, 2]:.3g} m); "
            "place it on or above the ground (its resting pose has z = its rest height)"
        )
    high = object_p[:, 2] > half
    if high.any():
        i = int(np.argmax(high))
        raise InvalidParameterError(f"push {i} starts the object at z = {object_p[i, 2]:.3g} m, above the"
                                    f" simulated world (at most {half:g} m)")


# --- small quaternion helpers (numpy, wxyz) -------------------------------------------------------


def xyzw(q_wxyz: np.ndarray) -> list[float]:
    """wxyz → pybullet's x,y,z,w (as a list)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return [float(q[1]), float(q[2]), float(q[3]), float(q[0])]


def wxyz(q_xyzw) -> np.ndarray:
    """pybullet's x,y,z,w → wxyz array."""
    return np.array([q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]], dtype=np.float64)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions ``(..., 4)``."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) of wxyz quaternions ``(..., 4)``."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``(..., 3)`` by wxyz quaternions ``(..., 4)``."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def yaw_quat(yaw: np.ndarray | float) -> np.ndarray:
    """wxyz quaternions of rotations by ``yaw`` rad about z, shape ``(..., 4)``."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zeros = np.zeros_like(half)
    return np.stack([np.cos(half), zeros, zeros, np.sin(half)], -1)


def _as_axis_aligned_box(vertices: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray] | None:
    """``(centre, half_extents)`` if the convex piece is an axis-aligned box, else None."""
    v = np.asarray(vertices, dtype=np.float64)
    low, high = v.min(0), v.max(0)
    scale = max(float((high - low).max()), 1e-12)
    corners = np.array(
        [[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])]
    )
    if (high - low).min() <= rtol * scale:
        return None
    on_corner = np.abs(v[:, None, :] - corners[None]).max(-1) <= 1e-7 * scale  # (V, 8)
    if not on_corner.any(1).all() or not on_corner.any(0).all():
        return None
    return (low + high) / 2, (high - low) / 2


def _matrix_to_wxyz(m: np.ndarray) -> np.ndarray:
    """A proper rotation matrix (3, 3) → unit wxyz quaternion with w >= 0 (Shepperd's method)."""
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.empty(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


#: Support spheres of an object whose bottom is a convex hull (:meth:`PushWorld._create_object_shape`), their
#: radius (m), and how far the hull's own bottom is lifted above the spheres' lowest points (m).
SUPPORT_SPHERES, SUPPORT_RADIUS, SUPPORT_LIFT = 8, 0.005, 0.002
#: pybullet keeps only this many children of a compound collision shape.
MAX_COMPOUND_CHILDREN = 16
#: Ground contact stiffness and damping per kg of the object (N/m, N s/m): ERP 0.5 at 240 Hz, so the support
#: forces under an object are the unique ones of a compliant floor, not whichever of the statically
#: indeterminate solutions the solver's order settles on.
GROUND_STIFFNESS_PER_KG, GROUND_DAMPING_PER_KG = 19200.0, 80.0


def support_points(parts: list[np.ndarray], count: int = SUPPORT_SPHERES, radius: float = SUPPORT_RADIUS,
                   directions: int = 720) -> np.ndarray:
    """``(count, 2)`` points spread round an object's footprint, ``radius`` inside its edge.

    The footprint is the convex hull of the vertices at the object's bottom; the points lie on rays from
    the centre of mass (the object frame's origin) at angles ``2πk/count``, where a ray leaves the hull
    (``min_n h(n) / <d, n>`` over ``directions`` outward normals ``n``, ``h`` the hull's support function:
    exact to a micrometre for a 0.3 m footprint), pulled in by ``radius``.
    """
    if count <= 0:
        return np.zeros((0, 2))
    bottom = min(float(p[:, 2].min()) for p in parts)
    footprint = np.concatenate([p[p[:, 2] <= bottom + 1e-6, :2] for p in parts])
    angles = 2 * np.pi * np.arange(directions) / directions
    normals = np.stack([np.cos(angles), np.sin(angles)], -1)  # (D, 2)
    support = (footprint @ normals.T).max(0)  # (D,)
    rays = 2 * np.pi * np.arange(count) / count
    d = np.stack([np.cos(rays), np.sin(rays)], -1)  # (K, 2)
    along = d @ normals.T  # (K, D)
    reach = np.where(along > 1e-9, support / np.where(along > 1e-9, along, 1.0), np.inf).min(-1)
    return d * (reach - radius)[:, None]


@dataclass(frozen=True)
class Piece:
    """One collision piece of an object, the same in every engine (:func:`object_pieces`).

    Attributes:
        kind: ``box`` (an axis-aligned box part), ``hull`` (any other part: its convex hull) or ``sphere`` (a
            support sphere the hulls stand on).
        centre: ``(3,)`` the box's or sphere's centre in the object frame (a hull's vertices are in that frame).
        size: ``(3,)`` a box's half extents; ``(1,)`` a sphere's radius; empty for a hull.
        vertices, faces: a hull's ``(V, 3)`` vertices (its bottom lifted by :data:`SUPPORT_LIFT`) and ``(F, 3)``
            triangles; empty for the others.
    """

    kind: str
    centre: np.ndarray
    size: np.ndarray
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))


def object_pieces(spec: ObjectSpec, max_children: int | None = None) -> tuple[Piece, ...]:
    """Exact boxes as box primitives, other pieces as convex hulls standing on a ring of small spheres: the
    spec's parts in their order, then the spheres.

    Box primitives are exact and collide several times faster than an 8-vertex hull. A hull keeps few
    ground contact points, chosen in an order the engine's collider settles (pybullet: at most four, added one
    per step; MuJoCo: the deepest vertices of a flat bottom, all equally deep): round objects' pushes then
    depend on their history or on the vertices' order, and mirrored pushes do not mirror. A hull piece's
    bottom is therefore lifted by :data:`SUPPORT_LIFT` and the object stands on :data:`SUPPORT_SPHERES`
    spheres spread round its footprint (:func:`support_points`), as many as ``max_children`` pieces leave
    room for (pybullet keeps 16 children of a compound shape).

    Raises:
        SimulationError: too many pieces to leave room for three support spheres.
    """
    parts = [np.asarray(p, dtype=np.float64) for p in spec.parts]
    bottom = min(float(p[:, 2].min()) for p in parts)
    pieces = []
    hull_on_ground = False
    for vertices, faces in zip(parts, spec.part_faces, strict=True):
        box = _as_axis_aligned_box(vertices)
        if box is not None:
            pieces.append(Piece("box", box[0], box[1]))
            continue
        low = vertices[:, 2] < bottom + SUPPORT_LIFT
        hull_on_ground |= bool((vertices[:, 2] <= bottom + 1e-6).any())
        lifted = vertices.copy()
        lifted[low, 2] = bottom + SUPPORT_LIFT  # exact for the vertical walls of the catalogue's pieces
        pieces.append(Piece("hull", np.zeros(3), np.zeros(0), lifted, np.asarray(faces, dtype=np.int64)))
    room = SUPPORT_SPHERES if max_children is None else max_children - len(pieces)
    count = min(SUPPORT_SPHERES, room) if hull_on_ground else 0
    if hull_on_ground and count < 3:
        raise SimulationError(
            f"{spec.name!r} has {len(pieces)} convex pieces: too many to stand on support spheres "
            f"within the engine's {max_children} collision pieces"
        )
    spheres = [Piece("sphere", np.array([x, y, bottom + SUPPORT_RADIUS]), np.array([SUPPORT_RADIUS]))
               for x, y in support_points(parts, count)]
    return tuple(pieces + spheres)


def settings_from_config(config: Mapping, which: str = "world") -> SimSettings:
    """The :class:`SimSettings` of a composed config: its ``sim`` group in the engine of ``world.engine``
    (``which="world"``: training pushes and ground truth) or ``physics.engine`` (``which="physics"``: the
    physics peers); pybullet where the config names none.

    Raises:
        InvalidParameterError: an unknown engine or simulator setting.
    """
    engine = (config.get(which) or {}).get("engine", "pybullet")
    try:
        return SimSettings(**{**(config.get("sim") or {}), "engine": engine})
    except TypeError as exc:
        raise InvalidParameterError(f"sim: {exc}") from exc


def make_world(spec: ObjectSpec, settings: SimSettings | None = None):
    """The world of ``settings.engine`` for ``spec``: a :class:`PushWorld` (pybullet) or a
    :class:`pushtorch.sim.mujoco_world.MujocoWorld`; both run :func:`pushtorch.sim.push.execute_push`.

    Raises:
        MissingDependencyError: the engine's package is not installed.
        SimulationError: the engine cannot build the world.
    """
    settings = settings or SimSettings()
    if settings.engine == "mujoco":
        try:
            import mujoco  # noqa: F401
        except ImportError as exc:
            from pushtorch.errors import MissingDependencyError

            raise MissingDependencyError(f"world.engine=mujoco needs MuJoCo: pip install mujoco ({exc})") from exc
        from pushtorch.sim.mujoco_world import MujocoWorld

        return MujocoWorld(spec, settings)
    return PushWorld(spec, settings)


class PushWorld:
    """One pybullet DIRECT client holding the ground, the robot and one object.

    The world is built once; every push resets it (poses, joint states, mass, friction) instead of
    rebuilding it. A push's outcome depends only on its own inputs: the object's collision shape and body
    are re-created before every push, so neither a contact cache nor a shape's internal state survives
    from the previous push (tests/test_sim_physics.py checks a push after another against a fresh world).

    Args:
        spec: the object to push.
        settings: physics and controller settings.
        urdf_path: robot URDF (default: the package's Pioneer with bumper).

    Raises:
        SimulationError: pybullet cannot connect or load a body.
    """

    def __init__(self, spec: ObjectSpec, settings: SimSettings | None = None, urdf_path: str | None = None):
        import pybullet as pb

        from pushtorch.robot import URDF_PATH

        self.pb = pb
        self.spec = spec
        self.settings = settings or SimSettings()
        if self.settings.engine != "pybullet":
            raise InvalidParameterError(f"PushWorld is the pybullet world; make_world builds a {self.settings.engine}"
                                        " one")
        self.client = pb.connect(pb.DIRECT)
        if self.client < 0:
            raise SimulationError("pybullet could not start a DIRECT physics client")
        self._closed = False
        s = self.settings
        cid = self.client
        pb.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=s.time_step,
            numSolverIterations=int(s.solver_iterations),
            numSubSteps=0,
            deterministicOverlappingPairs=1,
            # the solver's early exit (default 1e-7) stopped its iterations at an order-dependent point
            solverResidualThreshold=1e-9,
            physicsClientId=cid,
        )
        half = s.ground_half_extent
        ground_shape = pb.createCollisionShape(
            pb.GEOM_BOX, halfExtents=[half, half, GROUND_THICKNESS / 2], physicsClientId=cid
        )
        self.ground = pb.createMultiBody(
            0.0, ground_shape, basePosition=[0.0, 0.0, -GROUND_THICKNESS / 2], physicsClientId=cid
        )
        self.robot = pb.loadURDF(str(urdf_path or URDF_PATH), useFixedBase=True, physicsClientId=cid)
        if self.robot < 0:
            raise SimulationError(f"pybullet could not load the robot URDF {urdf_path or URDF_PATH}")
        # The chassis floats above the ground by design; skipping those pairs saves collision work.
        for link in range(-1, pb.getNumJoints(self.robot, physicsClientId=cid)):
            pb.setCollisionFilterPair(self.ground, self.robot, -1, link, 0, physicsClientId=cid)
            pb.changeDynamics(
                self.robot,
                link,
                lateralFriction=s.bumper_friction / s.object_friction,
                # Friction acts in the robot's horizontal plane only: vertical static friction between
                # the plate and the object is indeterminate for a rigid solver, which then pressed the
                # object into the ground or lifted it (ground normal force 0.8-1.5 m g, erratic pushes).
                anisotropicFriction=[1.0, 1.0, 0.0],
                physicsClientId=cid,
            )
        for joint in (JOINT_X, JOINT_Y, JOINT_YAW):
            pb.changeDynamics(self.robot, joint, jointDamping=0.0, linearDamping=0.0, angularDamping=0.0,
                              physicsClientId=cid)
        if s.robot == "p3dx":  # the base carries the robot's mass, which the wheels' traction depends on
            pb.changeDynamics(self.robot, BASE_LINK_INDEX, mass=s.drive.robot_mass, physicsClientId=cid)
        self._shape_folder = tempfile.mkdtemp(prefix="pushtorch-shape-")
        self._shape_args = self._shape_arguments(self._shape_folder)
        self._object_shape = -1
        self.object = -1
        # rotation of the principal (inertial) frame in the object frame, and its inverse
        self._q_principal = np.asarray(spec.principal_rotation, dtype=np.float64)

    # --- object ---------------------------------------------------------------------------------

    def _shape_arguments(self, folder: str) -> dict:
        """The arguments of ``createCollisionShapeArray`` for the object: one compound collision shape, exact
        boxes as box primitives, other pieces as convex hulls (written as OBJ files into ``folder``) standing
        on a ring of small spheres (:func:`object_pieces`). Made once per world; :meth:`_create_object_shape`
        builds a fresh shape from them for every push.
        """
        pb = self.pb
        types, half_extents, files, positions, radii = [], [], [], [], []
        geom = {"box": pb.GEOM_BOX, "hull": pb.GEOM_MESH, "sphere": pb.GEOM_SPHERE}
        for i, piece in enumerate(object_pieces(self.spec, MAX_COMPOUND_CHILDREN)):
            path = ""
            if piece.kind == "hull":
                path = os.path.join(folder, f"part{i}.obj")
                # pybullet builds a dynamic mesh's convex hull from the vertices its faces reference
                with open(path, "w") as f:
                    f.write("".join(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in piece.vertices))
                    f.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in piece.faces))
            types.append(geom[piece.kind])
            half_extents.append([float(v) for v in piece.size] if piece.kind == "box" else [0.0, 0.0, 0.0])
            files.append(path)
            positions.append([float(v) for v in piece.centre])
            radii.append(float(piece.size[0]) if piece.kind == "sphere" else 0.0)
        return {"shapeTypes": types, "halfExtents": half_extents, "fileNames": files, "radii": radii,
                "meshScales": [[1.0, 1.0, 1.0]] * len(types), "collisionFramePositions": positions,
                "collisionFrameOrientations": [[0.0, 0.0, 0.0, 1.0]] * len(types)}

    def _create_object_shape(self) -> int:
        """A fresh compound collision shape of the object (:meth:`_shape_arguments`)."""
        shape = self.pb.createCollisionShapeArray(**self._shape_args, physicsClientId=self.client)
        if shape < 0:
            raise SimulationError(f"pybullet could not create the collision shape of {self.spec.name!r}")
        return shape

    def _principal_pose(self, position: np.ndarray, q_object: np.ndarray) -> tuple[list[float], list[float]]:
        """Object-frame pose → pose of the principal inertial frame that pybullet stores as the base."""
        return [float(v) for v in position], xyzw(quat_multiply(q_object, self._q_principal))

    def spawn_object(
        self, position: np.ndarray, q_object: np.ndarray, mass: float, ground_friction: float
    ) -> None:
        """(Re-)create the object body at a pose (object frame, wxyz) with its mass and the ground friction.

        Raises:
            InvalidParameterError: mass or friction not positive and finite.
        """
        if not (np.isfinite(mass) and mass > 0):
            raise InvalidParameterError(f"object mass must be positive and finite, got {mass!r}")
        if not (np.isfinite(ground_friction) and ground_friction > 0):
            raise InvalidParameterError(
                f"ground friction must be positive and finite, got {ground_friction!r}"
            )
        pb, cid, s = self.pb, self.client, self.settings
        if self.object >= 0:
            pb.removeBody(self.object, physicsClientId=cid)
        # A fresh collision shape for every push: a convex-hull shape keeps state from the pushes it took
        # part in (a cylinder pushed after another push ended 27 mm from where it ends in a fresh world);
        # rebuilt, every push is a function of its own inputs alone (2-3 ms). pybullet refuses to remove a
        # shape a removed body used, so the old ones stay (a few kB each).
        self._object_shape = self._create_object_shape()
        pos, orn = self._principal_pose(position, q_object)
        self.object = pb.createMultiBody(
            baseMass=float(mass),
            baseCollisionShapeIndex=self._object_shape,
            basePosition=pos,
            baseOrientation=orn,
            baseInertialFramePosition=[0.0, 0.0, 0.0],
            baseInertialFrameOrientation=xyzw(self._q_principal),
            # a free rigid body (not a 0-link multibody) collides and solves markedly faster
            useMaximalCoordinates=True,
            physicsClientId=cid,
        )
        if self.object < 0:
            raise SimulationError(f"pybullet could not create the body of {self.spec.name!r}")
        pb.resetBasePositionAndOrientation(self.object, pos, orn, physicsClientId=cid)
        pb.changeDynamics(
            self.object,
            -1,
            mass=float(mass),
            localInertiaDiagonal=[float(v) for v in mass * np.asarray(self.spec.inertia_per_kg)],
            lateralFriction=s.object_friction,
            spinningFriction=0.0,
            rollingFriction=0.0,
            restitution=0.0,
            linearDamping=0.0,
            angularDamping=0.0,
            collisionMargin=0.0,
            activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=cid,
        )
        pb.changeDynamics(self.ground, -1, lateralFriction=float(ground_friction) / s.object_friction,
                          restitution=0.0, contactStiffness=GROUND_STIFFNESS_PER_KG * float(mass),
                          contactDamping=GROUND_DAMPING_PER_KG * float(mass), physicsClientId=cid)

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's current pose: position ``(3,)`` and wxyz quaternion ``(4,)`` of the object frame."""
        pos, orn = self.pb.getBasePositionAndOrientation(self.object, physicsClientId=self.client)
        q = quat_multiply(wxyz(orn), quat_conjugate(self._q_principal))
        return np.asarray(pos, dtype=np.float64), q / np.linalg.norm(q)

    # --- robot ----------------------------------------------------------------------------------

    def place_robot(self, position: np.ndarray, q_base: np.ndarray) -> None:
        """Put the robot's world link at the start pose (base frame, wxyz) with its joints at rest."""
        pb, cid = self.pb, self.client
        pb.resetBasePositionAndOrientation(
            self.robot, [float(v) for v in position], xyzw(q_base), physicsClientId=cid
        )
        for joint in (JOINT_X, JOINT_Y, JOINT_YAW):
            pb.resetJointState(self.robot, joint, 0.0, 0.0, physicsClientId=cid)
        self._drive_state = DriveState()
        if self.settings.robot == "p3dx":
            # the wheels' forces replace the joints' velocity motors (which would otherwise hold the joints)
            pb.setJointMotorControlArray(self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], pb.VELOCITY_CONTROL,
                                         targetVelocities=[0.0, 0.0, 0.0], forces=[0.0, 0.0, 0.0],
                                         physicsClientId=cid)
        self.drive(0.0, 0.0)

    @property
    def control_every(self) -> int:
        """Physics steps between two calls of :meth:`drive`: the wheels' forces act for one step only."""
        return 1 if self.settings.robot == "p3dx" else int(self.settings.control_every)

    def drive(self, speed: float, yaw_rate: float) -> None:
        """Command the body twist (forward speed m/s, yaw rate rad/s) through the robot's drive.

        ``p3dx``: the wheels' forces of :func:`pushtorch.sim.drive.wheel_forces` for the next physics step.
        ``ideal``: the planar joints live in the start frame, so the forward speed is split along the current
        heading; each drive axis is bounded by ``max_force`` (yaw by ``max_torque``).
        """
        if self.settings.robot == "p3dx":
            self._drive_wheels(speed, yaw_rate)
            return
        pb, cid, s = self.pb, self.client, self.settings
        heading = pb.getJointState(self.robot, JOINT_YAW, physicsClientId=cid)[0]
        pb.setJointMotorControlArray(
            self.robot,
            [JOINT_X, JOINT_Y, JOINT_YAW],
            pb.VELOCITY_CONTROL,
            targetVelocities=[speed * np.cos(heading), speed * np.sin(heading), yaw_rate],
            forces=[s.max_force, s.max_force, s.max_torque],
            physicsClientId=cid,
        )

    def _drive_wheels(self, speed: float, yaw_rate: float) -> None:
        pb, cid, s = self.pb, self.client, self.settings
        states = pb.getJointStates(self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], physicsClientId=cid)
        heading, (vx, vy, spin) = states[2][0], (st[1] for st in states)
        cos, sin = math.cos(heading), math.sin(heading)
        left, right, sideways = wheel_forces(s.drive, (speed, yaw_rate),
                                             (vx * cos + vy * sin, -vx * sin + vy * cos, spin), self._drive_state,
                                             s.time_step)
        forward = left + right
        torque = (right - left) * s.drive.wheel_separation / 2.0
        pb.setJointMotorControlArray(
            self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], pb.TORQUE_CONTROL,
            forces=[forward * cos - sideways * sin, forward * sin + sideways * cos, torque], physicsClientId=cid,
        )

    def robot_joints(self) -> np.ndarray:
        """Joint positions ``(3,)``: x, y (m) and yaw (rad) of the base in the start frame."""
        states = self.pb.getJointStates(
            self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], physicsClientId=self.client
        )
        return np.array([st[0] for st in states], dtype=np.float64)

    def touching(self) -> bool:
        """Whether the robot (bumper or chassis) is in contact with the object now."""
        return bool(self.pb.getContactPoints(self.robot, self.object, physicsClientId=self.client))

    def step(self) -> None:
        self.pb.stepSimulation(physicsClientId=self.client)

    def close(self) -> None:
        """Disconnect the pybullet client (idempotent)."""
        if not self._closed:
            try:
                self.pb.disconnect(physicsClientId=self.client)
            finally:
                self._closed = True
                shutil.rmtree(self._shape_folder, ignore_errors=True)

    def __enter__(self) -> PushWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort at interpreter shutdown
        try:
            self.close()
        except Exception:
            pass
