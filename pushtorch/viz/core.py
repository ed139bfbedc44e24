"""Rerun plumbing shared by every stage: recordings, entity paths, and logging of meshes, poses and clouds.

Not a paper section: this is how a user reviews every contact, kernel and prediction (README, "Rerun
recordings"). Entity paths are stable and documented in :mod:`pushtorch.viz`; quaternions cross to
Rerun's x,y,z,w order here and nowhere else.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import rerun as rr
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError

__all__ = [
    "WORLD",
    "curvature_colors",
    "entity_name",
    "log_arrows",
    "log_frames",
    "log_line_strip",
    "log_mesh",
    "log_points",
    "log_pose",
    "open_recording",
    "read_entity_paths",
    "transform_columns",
]

#: Root of every entity; world frame, z up, metres.
WORLD = "world"


def entity_name(label: str) -> str:
    """An entity path below a root, from a label: ``/`` separates its levels; within a level, characters
    Rerun would need escaped become ``_``. Empty levels (``a//b``, a leading or trailing ``/``) are dropped.

    Raises:
        InvalidParameterError: no level, or a level without a letter or digit.
    """
    levels = [re.sub(r"[^A-Za-z0-9_.\-]", "_", level) for level in str(label).split("/") if level]
    if not levels or not all(re.search(r"[A-Za-z0-9]", level) for level in levels):
        raise InvalidParameterError(
            f"an entity label needs at least one letter or digit in each level, got {label!r}"
        )
    return "/".join(levels)


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def open_recording(path: str | Path, application_id: str = "pushtorch") -> rr.RecordingStream:
    """A non-global recording that streams to ``path`` (a ``.rrd`` file, parent folders created).

    Call ``rec.flush()`` (or let it go out of scope) before reading the file back.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(application_id, send_properties=False)
    rec.save(str(path))
    rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    return rec


def log_mesh(
    rec: rr.RecordingStream,
    entity_path: str,
    mesh: trimesh.Trimesh,
    color: tuple[int, int, int, int] | None = None,
    static: bool = True,
) -> None:
    """A triangle mesh in its entity's local frame (pair it with :func:`log_pose` on the same path)."""
    rec.log(
        entity_path,
        rr.Mesh3D(
            vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
            triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
            vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
            albedo_factor=color if color is not None else (180, 180, 200, 255),
        ),
        static=static,
    )


def log_pose(rec: rr.RecordingStream, entity_path: str, pose: se3.Pose, static: bool = False) -> None:
    """The transform of ``entity_path`` relative to its parent: one pose, wxyz → Rerun's xyzw."""
    rec.log(
        entity_path,
        rr.Transform3D(
            translation=_np(pose.p).reshape(3).astype(np.float32),
            quaternion=rr.Quaternion(xyzw=_np(se3.wxyz_to_xyzw(pose.q)).reshape(4).astype(np.float32)),
        ),
        static=static,
    )


def transform_columns(poses: se3.Pose):
    """Poses ``(T,)`` as ``Transform3D`` columns for ``send_columns`` (one transform per row), wxyz → xyzw."""
    return rr.Transform3D.columns(
        translation=_np(poses.p).reshape(-1, 3).astype(np.float32),
        quaternion=_np(se3.wxyz_to_xyzw(poses.q)).reshape(-1, 4).astype(np.float32),
    )


def log_points(
    rec: rr.RecordingStream,
    entity_path: str,
    points,
    colors=None,
    radii: float | np.ndarray | None = 0.002,
    static: bool = False,
) -> None:
    """A point cloud ``(N, 3)``; colours ``(N, 3|4)`` uint8 or one colour for all."""
    rec.log(entity_path, rr.Points3D(_np(points).reshape(-1, 3), colors=colors, radii=radii), static=static)


def log_arrows(
    rec: rr.RecordingStream,
    entity_path: str,
    origins,
    vectors,
    colors=None,
    static: bool = False,
) -> None:
    """Arrows ``(N, 3)`` from ``origins`` along ``vectors`` (frames, normals, curvature directions)."""
    rec.log(
        entity_path,
        rr.Arrows3D(origins=_np(origins).reshape(-1, 3), vectors=_np(vectors).reshape(-1, 3), colors=colors),
        static=static,
    )


def log_line_strip(rec: rr.RecordingStream, entity_path: str, points, color=None, static: bool = False) -> None:
    """One polyline through ``points (N, 3)`` (trajectories)."""
    rec.log(entity_path, rr.LineStrips3D([_np(points).reshape(-1, 3)], colors=color), static=static)


def log_frames(
    rec: rr.RecordingStream, entity_path: str, poses: se3.Pose, length: float = 0.01, static: bool = False
) -> None:
    """Poses ``(N,)`` drawn as RGB axis triads (x red, y green, z blue) of ``length`` metres."""
    from pytorch_kinematics import transforms as pkt

    rot = pkt.quaternion_to_matrix(poses.q.reshape(-1, 4))  # (N, 3, 3), columns are the axes
    origins = poses.p.reshape(-1, 3)
    axes = rot.transpose(-1, -2) * length  # (N, 3 axes, 3)
    colours = np.array([[230, 40, 40], [40, 200, 40], [40, 90, 230]], dtype=np.uint8)
    log_arrows(
        rec,
        entity_path,
        origins.unsqueeze(1).expand(-1, 3, -1),
        axes,
        colors=np.tile(colours, (origins.shape[0], 1)),
        static=static,
    )


def curvature_colors(values, vmax: float | None = None) -> np.ndarray:
    """Map non-negative values (e.g. r1 in m⁻¹) to uint8 RGB with matplotlib's viridis."""
    from matplotlib import colormaps

    v = _np(values).astype(np.float64)
    top = vmax if vmax is not None else max(float(np.percentile(np.abs(v), 95)), 1e-9)
    rgba = colormaps["viridis"](np.clip(np.abs(v) / top, 0.0, 1.0))
    return (rgba[:, :3] * 255).astype(np.uint8)


def read_entity_paths(path: str | Path) -> set[str]:
    """Every entity path with data in a saved ``.rrd`` file, read back with Rerun's own reader."""
    from rerun.chunk import RrdReader

    store = RrdReader(str(path)).store()
    return {str(chunk.entity_path) for chunk in store.stream().to_chunks()}
