"""The paper's object catalogue and user meshes, with dimensions (D_S) and visual symmetries (Q_gt).

Paper, Test Set and Pose Estimation Accuracy: a 0.2 m cube; rectangular prisms 0.1×0.2×0.2 and
0.3×0.2×0.2 m; cylinders of height 0.2 m and radius 0.1 / 0.15 m; the 0.2 m "hybrid" (half a cylinder
and an isosceles triangular prism joined by their largest flat faces); and the modified cube (1/16 of
its volume removed at one corner). Prediction Accuracy Measure (Eq. pam) needs each object's
dimensions (D_S) and its visually identical orientations Q_gt, held here as a :class:`Symmetry`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from pushtorch.errors import InvalidParameterError
from pushtorch.objects.meshes import check_up_axis, load_mesh_file
from pushtorch.objects.object_model import ObjectModel, centred
from pushtorch.objects.symmetry import Symmetry
from pushtorch.objects.symmetry_detection import detect_symmetry

__all__ = [
    "CATALOGUE",
    "catalogue_names",
    "load_object",
]

_CYLINDER_SECTIONS = 96
_Z_AXIS = (0.0, 0.0, 1.0)


def _box(extents: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


def _cylinder(radius: float, height: float) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, height=height, sections=_CYLINDER_SECTIONS)


def _hybrid(size: float = 0.2) -> trimesh.Trimesh:
    """Half a cylinder (radius size/2, towards -x) and an isosceles triangular prism (apex at +x,
    height size/2) joined along their largest flat faces, extruded ``size`` along z. Convex."""
    radius = size / 2
    angles = np.linspace(np.pi / 2, 3 * np.pi / 2, _CYLINDER_SECTIONS // 2 + 1)
    outline = np.concatenate([np.stack([radius * np.cos(angles), radius * np.sin(angles)], 1), [[radius, 0.0]]])
    points = np.concatenate(
        [np.c_[outline, np.full(len(outline), -size / 2)], np.c_[outline, np.full(len(outline), size / 2)]]
    )
    return trimesh.convex.convex_hull(points)


def _modified_cube(size: float = 0.2) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh]]:
    """A cube with a cubic notch of 1/16 of its volume cut at its (+x, +y, +z) corner.

    The notch is itself a cube (side size / 16^(1/3) ≈ 0.079 m for 0.2 m) so the shape keeps the
    3-fold symmetry about the notched corner's diagonal and nothing else.
    """
    notch = size / 16 ** (1 / 3)
    h = size / 2
    cube = _box((size, size, size))
    cutter = _box((notch, notch, notch))
    cutter.apply_translation([h - notch / 2] * 3)
    mesh = cube.difference(cutter)
    lower = _box((size, size, size - notch))
    lower.apply_translation([0, 0, -notch / 2])
    back = _box((size - notch, size, notch))
    back.apply_translation([-notch / 2, 0, h - notch / 2])
    side = _box((notch, size - notch, notch))
    side.apply_translation([h - notch / 2, -notch / 2, h - notch / 2])
    return mesh, [lower, back, side]


def _z_flip_symmetry() -> Symmetry:
    """Identity and a half turn about x, combined with any rotation about z (a cylinder)."""
    return Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]), continuous_axis=torch.tensor(_Z_AXIS))


def _build(name: str) -> ObjectModel:
    if name == "modified_cube":
        mesh, parts = _modified_cube()
        mesh, parts = centred(mesh, parts)
        return ObjectModel(name, mesh, detect_symmetry(mesh), parts, "primitives")
    if name in ("cylinder", "cylinder_wide"):
        mesh, _ = centred(_cylinder(0.1 if name == "cylinder" else 0.15, 0.2))
        return ObjectModel(name, mesh, _z_flip_symmetry())
    builders = {
        "cube": lambda: _box((0.2, 0.2, 0.2)),
        "prism_thin": lambda: _box((0.1, 0.2, 0.2)),
        "prism_long": lambda: _box((0.3, 0.2, 0.2)),
        "hybrid": _hybrid,
    }
    mesh, _ = centred(builders[name]())
    return ObjectModel(name, mesh, detect_symmetry(mesh))


#: Catalogue name → one-line description (dimensions in metres).
CATALOGUE: dict[str, str] = {
    "cube": "cube, side 0.2",
    "prism_thin": "rectangular prism 0.1 (x) × 0.2 × 0.2",
    "prism_long": "rectangular prism 0.3 (x) × 0.2 × 0.2",
    "cylinder": "cylinder, radius 0.1, height 0.2",
    "cylinder_wide": "cylinder, radius 0.15, height 0.2",
    "hybrid": "half cylinder (r 0.1, towards -x) + isosceles triangular prism (apex +x), 0.2 × 0.2 × 0.2",
    "modified_cube": "cube 0.2 with a cubic notch of 1/16 of its volume at the (+x,+y,+z) corner",
}

_CACHE: dict[str, ObjectModel] = {}


def catalogue_names() -> list[str]:
    """The catalogue's object names, in the paper's order."""
    return list(CATALOGUE)


def load_object(name: str, path: str | Path | None = None, scale: float = 1.0,
                cache_dir: str | Path | None = None, up: str = "z") -> ObjectModel:
    """A catalogue object by name, or a user mesh when ``name == "mesh"`` (``path``, ``scale``, the folder
    ``cache_dir`` that keeps a concave mesh's decomposition and the file's ``up`` axis, see
    :func:`load_mesh_file`; a catalogue object ignores ``up``, which is checked all the same).

    Raises:
        InvalidParameterError: unknown catalogue name, object=mesh without a path, or ``up`` not one of
            :data:`UP_AXES`.
        InvalidMeshError: a mesh :func:`load_mesh_file` refuses.
    """
    check_up_axis(up)
    if name == "mesh":
        if path is None or str(path) in ("", "???"):  # "???": Hydra's mandatory value, left unset
            raise InvalidParameterError(
                "object=mesh needs object.path=<an STL, OBJ or PLY file>; object.path is not set"
            )
        return load_mesh_file(path, scale, cache_dir=cache_dir, up=up)
    if name not in CATALOGUE:
        raise InvalidParameterError(f"unknown object {name!r}; the catalogue has {', '.join(CATALOGUE)}")
    if name not in _CACHE:
        _CACHE[name] = _build(name)
    return _CACHE[name]
