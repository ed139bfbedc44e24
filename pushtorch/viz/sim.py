"""Rerun logging of recorded pushes: object, robot, bumper and trajectories over the ``sim_time`` timeline.

Paper, Experimental Setup (the simulated pushes that train and test every model). Logging replays a
:class:`pushtorch.sim.records.PushRecords` entry and re-simulates nothing: the recorded trajectories (at
the record rate) are the animation.

Entity paths, under ``world/sim/<label>`` (``<label>`` defaults to ``push_<index>``), or under any ``root``
the caller names (a prediction logs its ground-truth push at ``<prediction root>/truth_push``):
    .../object            object transform over ``sim_time``; its mesh at .../object/mesh
    .../object_final      the object's settled final pose (static), mesh in a lighter colour (optional)
    .../robot             robot base transform over ``sim_time``; chassis at .../robot/chassis
    .../robot/bumper      the bumper link (static mount transform) and its mesh at .../robot/bumper/mesh
    .../object_path       the object centre's path (line strip, static)
    .../robot_path        the robot base's path (line strip, static)
"""

from __future__ import annotations

import rerun as rr
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.viz.core import WORLD, log_line_strip, log_mesh, log_pose, transform_columns

__all__ = ["SIM", "SIM_TIMELINE", "log_push", "log_pushes"]

#: Root of every simulated push in a recording.
SIM = f"{WORLD}/sim"
#: The timeline of a push, seconds since its start.
SIM_TIMELINE = "sim_time"

_OBJECT_COLOUR = (70, 130, 220, 255)
_FINAL_COLOUR = (150, 200, 255, 120)
_CHASSIS_COLOUR = (190, 40, 40, 255)
_BUMPER_COLOUR = (150, 150, 150, 255)


def log_push(
    rec: rr.RecordingStream,
    records,
    i: int,
    object_mesh: trimesh.Trimesh | None,
    label: str | None = None,
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    root: str | None = None,
    with_final_pose: bool = True,
) -> str:
    """Log push ``i`` of ``records`` (a :class:`PushRecords`) as an animation on ``sim_time``.

    The transforms over time go out as one column per entity (``send_columns``): one row per recorded
    time, at the record rate.

    Args:
        rec: an open recording (see :func:`pushtorch.viz.open_recording`).
        records: the pushes.
        i: which push.
        object_mesh: the pushed object's mesh in its own frame (``ObjectModel.mesh``), or None to log
            the object's transforms without a mesh.
        label: entity name under ``world/sim`` (default ``push_<index>``); ignored when ``root`` is given.
        offset: static translation of this push's root entity (to lay several pushes side by side).
        root: the push's root entity path, instead of ``world/sim/<label>``.
        with_final_pose: also log ``object_final`` (a prediction already shows the true final pose).

    Returns:
        The push's root entity path.

    Raises:
        InvalidParameterError: ``i`` is out of range.
    """
    from pushtorch.robot import bumper_geometry, bumper_mesh

    n = len(records)
    if not -n <= i < n:
        raise InvalidParameterError(f"push {i} is out of range for {n} records")
    if root is None:
        root = f"{SIM}/{label or f'push_{int(records.index[i])}'}"
    rec.log(root, rr.Transform3D(translation=[float(v) for v in offset]), static=True)

    geometry = bumper_geometry()
    chassis = trimesh.creation.box(extents=geometry.chassis_size)
    chassis.apply_translation(geometry.chassis_centre)
    if object_mesh is not None:
        log_mesh(rec, f"{root}/object/mesh", object_mesh, color=_OBJECT_COLOUR)
    log_mesh(rec, f"{root}/robot/chassis", chassis, color=_CHASSIS_COLOUR)
    log_pose(rec, f"{root}/robot/bumper", geometry.mount.to(torch.float32), static=True)
    log_mesh(rec, f"{root}/robot/bumper/mesh", bumper_mesh(), color=_BUMPER_COLOUR)

    if with_final_pose:
        final = se3.Pose.unchecked(records.object_final.p[i], records.object_final.q[i])
        log_pose(rec, f"{root}/object_final", final, static=True)
        if object_mesh is not None:
            log_mesh(rec, f"{root}/object_final/mesh", object_mesh, color=_FINAL_COLOUR)
    object_path, robot_path = records.object_trajectory.take(i), records.robot_trajectory.take(i)  # (T,)
    log_line_strip(rec, f"{root}/object_path", object_path.p, color=_OBJECT_COLOUR, static=True)
    log_line_strip(rec, f"{root}/robot_path", robot_path.p, color=_CHASSIS_COLOUR, static=True)

    times = rr.TimeColumn(SIM_TIMELINE, duration=records.time.double().cpu().numpy())
    for entity, path in (("object", object_path), ("robot", robot_path)):
        rec.send_columns(f"{root}/{entity}", indexes=[times], columns=transform_columns(path))
    return root


def log_pushes(
    rec: rr.RecordingStream,
    records,
    indices,
    object_mesh: trimesh.Trimesh,
    spacing: float = 1.5,
) -> list[str]:
    """Log several pushes side by side (``spacing`` metres apart along world y); return their roots."""
    return [
        log_push(rec, records, int(i), object_mesh, offset=(0.0, k * spacing, 0.0))
        for k, i in enumerate(indices)
    ]
