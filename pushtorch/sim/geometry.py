"""Engine-independent geometry of a push world: where the world ends, quaternions, an object's collision pieces.

Paper, Experimental Setup: the authors pushed objects in Gazebo/ODE; the pybullet and MuJoCo worlds that
replace it (:mod:`pushtorch.sim.pybullet_world`, :mod:`pushtorch.sim.mujoco_world`) share what is here, so
the two engines push the same bodies in the same world:

    * :func:`check_inside_world` refuses push inputs whose object or robot could leave the ground during
      the push (start position plus the distance the push can travel), or whose object starts below the
      ground: the world ends at the ground's edge (``ground_half_extent``), beyond it an object would fall
      for ever.
    * Quaternion helpers on numpy wxyz arrays (:func:`quat_multiply`, :func:`quat_rotate`, ...) and the
      conversions to and from pybullet's x,y,z,w order (:func:`xyzw`, :func:`wxyz`), the only ones in the
      simulator.
    * :func:`object_pieces`: an object's collision pieces in every engine (exact boxes, convex hulls with
      lifted bottoms, the support spheres the hulls stand on, :func:`support_points`).

Numpy only (the workers' hot path has no torch).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pushtorch.errors import InvalidParameterError, SimulationError
from pushtorch.sim.settings import ObjectSpec, SimSettings

__all__ = [
    "GROUND_PENETRATION_TOLERANCE",
    "Piece",
    "ROBOT_REACH",
    "SUPPORT_LIFT",
    "SUPPORT_RADIUS",
    "SUPPORT_SPHERES",
    "check_inside_world",
    "object_pieces",
    "quat_conjugate",
    "quat_multiply",
    "quat_rotate",
    "support_points",
    "wxyz",
    "xyzw",
    "yaw_quat",
]

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


#: Support spheres of an object whose bottom is a convex hull (:func:`object_pieces`), their radius (m),
#: and how far the hull's own bottom is lifted above the spheres' lowest points (m).
SUPPORT_SPHERES, SUPPORT_RADIUS, SUPPORT_LIFT = 8, 0.005, 0.002


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

