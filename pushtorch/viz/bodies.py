"""Rerun logging of the rigid bodies in a scene: an object's mesh at a pose, the robot at a base pose, and the
convex parts the simulator collides an object as.

Paper, Test Set (the objects, as :class:`~pushtorch.objects.ObjectModel` holds them) and Experimental Setup
(the robot with its bumper, :mod:`pushtorch.robot`). Everything is in the world frame (z up, metres) and
static. Entity paths, under a root the caller names (a trained model's or a prediction's):

=================================  ==============================================================
``<path>``                         a posed object (:func:`log_posed_mesh`): its transform; ``/axes``, ``/mesh``
``<root>/robot``                   the robot base pose (:func:`log_robot`): transform; ``/chassis``, ``/axes``
``<root>/bumper``                  the bumper at that base pose (world-frame mesh)
``<path>/part_<k>``                the object's convex collision parts (:func:`log_collision_parts`)
=================================  ==============================================================
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.viz.core import log_frames, log_mesh, log_pose
from pushtorch.viz.helpers import one_pose

__all__ = [
    "log_collision_parts",
    "log_posed_mesh",
    "log_robot",
    "mesh_of",
]

_CHASSIS_COLOUR = (190, 40, 40, 160)
_BUMPER_COLOUR = (240, 200, 40, 255)


def mesh_of(obj) -> trimesh.Trimesh | None:
    """The mesh of an :class:`~pushtorch.objects.ObjectModel`, a mesh itself, or None."""
    if obj is None or isinstance(obj, trimesh.Trimesh):
        return obj
    mesh = getattr(obj, "mesh", None)
    if not isinstance(mesh, trimesh.Trimesh):
        raise InvalidParameterError(f"expected an ObjectModel or a trimesh.Trimesh, got {type(obj).__name__}")
    return mesh


def log_posed_mesh(
    rec: rr.RecordingStream,
    entity_path: str,
    pose: se3.Pose,
    mesh: trimesh.Trimesh | None,
    color: tuple[int, int, int, int],
    axis_length: float = 0.05,
) -> None:
    """A pose as a transform with an axis triad, and the mesh under it if there is one (all static)."""
    pose = se3.Pose.unchecked(pose.p.reshape(3), pose.q.reshape(4))
    log_pose(rec, entity_path, pose, static=True)
    origin = se3.identity((1,), dtype=pose.p.dtype)
    log_frames(rec, f"{entity_path}/axes", origin, length=axis_length, static=True)
    if mesh is not None:
        log_mesh(rec, f"{entity_path}/mesh", mesh, color=color, static=True)


def log_robot(rec: rr.RecordingStream, root: str, base: se3.Pose) -> None:
    """The robot at one base pose: ``<root>/robot`` (transform, chassis, axes), ``<root>/bumper`` (world)."""
    from pushtorch.robot import bumper_geometry, bumper_mesh

    base = se3.Pose.unchecked(base.p.reshape(3), base.q.reshape(4))
    geometry = bumper_geometry()
    chassis = trimesh.creation.box(extents=geometry.chassis_size)
    chassis.apply_translation(geometry.chassis_centre)
    log_pose(rec, f"{root}/robot", base, static=True)
    log_mesh(rec, f"{root}/robot/chassis", chassis, color=_CHASSIS_COLOUR)
    log_frames(rec, f"{root}/robot/axes", se3.identity((1,), dtype=base.p.dtype), length=0.1, static=True)
    log_mesh(rec, f"{root}/bumper", bumper_mesh(base), color=_BUMPER_COLOUR)


def log_collision_parts(rec: rr.RecordingStream, entity_path: str, obj, pose: se3.Pose | None = None) -> bool:
    """The convex parts the simulator collides ``obj`` as, if there are several (static).

    ``entity_path`` gets ``pose``'s transform (if given) and ``entity_path/part_<k>`` a mesh per part of
    :attr:`~pushtorch.objects.ObjectModel.collision_parts` (object frame), one tab10 colour each.

    Returns:
        True if the parts were logged; False (nothing logged) for an object simulated as one part, or
        anything that is not an ObjectModel (a bare mesh).
    """
    parts = getattr(obj, "collision_parts", None)
    if isinstance(obj, trimesh.Trimesh) or not parts or len(parts) < 2:
        return False
    from matplotlib import colormaps

    palette = (np.asarray(colormaps["tab10"].colors)[:, :3] * 255).astype(np.uint8)
    if pose is not None:
        log_pose(rec, entity_path, one_pose(pose), static=True)
    for k, part in enumerate(parts):
        colour = tuple(int(c) for c in palette[k % len(palette)]) + (200,)
        log_mesh(rec, f"{entity_path}/part_{k}", part, color=colour, static=True)
    return True
