"""An object as the library holds it: its mesh in the object frame, its symmetries, the convex parts the
physics engine pushes (paper, Test Set; Prediction Accuracy Measure needs its dimensions D_S).

Frames: every mesh is in metres with its origin at its centre of mass (:func:`centred` moves it there).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.objects.symmetry import Symmetry

__all__ = [
    "ObjectModel",
    "centred",
]

@dataclass
class ObjectModel:
    """A rigid object: its mesh (metres, origin at the centre of mass) and what the measure needs.

    Attributes:
        name: catalogue name or file stem.
        mesh: watertight triangle mesh in the object frame.
        symmetry: visually identical orientations (Q_gt).
        collision_parts: convex pieces whose union is the mesh, for the physics engine (which
            treats a dynamic mesh as its convex hull).
        collision_source: how the parts were made: ``"convex hull"`` (a convex mesh, or an open one),
            ``"primitives"`` (catalogue pieces), ``"v-hacd"`` (a concave user mesh decomposed),
            ``"convex parts"`` (a user mesh of several connected parts, each convex or open: their hulls) or
            ``"convex parts and v-hacd"`` (some of those parts concave and decomposed).
        source_origin: ``(3,)`` where the object frame's origin (the centre of mass) lies in the mesh file's
            own frame (metres, after scale and up axis), for a mesh loaded from a file; None for built-in
            shapes. Poses given in the file's frame (a push table's) become object-frame poses by it.
    """

    name: str
    mesh: trimesh.Trimesh
    symmetry: Symmetry
    collision_parts: list[trimesh.Trimesh] = field(default_factory=list)
    collision_source: str = "convex hull"
    source_origin: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not self.collision_parts:
            self.collision_parts = [self.mesh.convex_hull]

    @property
    def dimensions(self) -> torch.Tensor:
        """Extents ``(3,)`` of the axis-aligned box in the object frame, metres (the paper's D_S^-1)."""
        return torch.tensor(np.asarray(self.mesh.extents), dtype=torch.float32)

    @property
    def rest_height(self) -> float:
        """Height of the origin above the ground when the object rests upright (``-min z``)."""
        return float(-self.mesh.bounds[0, 2])

    def resting_pose(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> se3.Pose:
        """The pose of the object standing upright on the ground plane z = 0 at (x, y, yaw)."""
        return se3.from_xy_yaw(x, y, yaw, z=self.rest_height)


def centred(mesh: trimesh.Trimesh, parts: list[trimesh.Trimesh] | None = None):
    """``mesh`` (and its ``parts``) moved so the origin is the mesh's centre of mass."""
    offset = -np.asarray(mesh.center_mass)
    mesh = mesh.copy()
    mesh.apply_translation(offset)
    moved = []
    for part in parts or []:
        part = part.copy()
        part.apply_translation(offset)
        moved.append(part)
    return mesh, moved
