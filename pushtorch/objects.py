"""The paper's object catalogue and user meshes, with dimensions (D_S) and visual symmetries (Q_gt).

Paper, Test Set and Pose Estimation Accuracy: a 0.2 m cube; rectangular prisms 0.1×0.2×0.2 and
0.3×0.2×0.2 m; cylinders of height 0.2 m and radius 0.1 / 0.15 m; the 0.2 m "hybrid" (half a cylinder
and an isosceles triangular prism joined by their largest flat faces); and the modified cube (1/16 of
its volume removed at one corner). Prediction Accuracy Measure (Eq. pam) needs each object's
dimensions (D_S) and its visually identical orientations Q_gt, held here as a :class:`Symmetry`.

Frames: every mesh is in metres with its origin at its centre of mass; for the prisms the first
dimension lies along the object's x axis (the push direction when the object sits at yaw 0), and the
cylinders' and the hybrid's axes are the object's z axis (upright on the ground).

User meshes are simulated as they are (:func:`load_mesh_file`): a closed convex mesh as itself, a closed
concave one as the union of the convex parts of a V-HACD decomposition (pybullet's ``vhacd``: offline,
deterministic, run once per mesh and cached in memory, and on disk when a ``cache_dir`` is named; otherwise
its files live in a temporary folder removed at once). A mesh of several disjoint bodies is refused (one
rigid body is pushed); an open mesh encloses no volume and is simulated as its convex hull. The mass
distribution is always the mesh's own (uniform density).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidMeshError, InvalidParameterError

__all__ = [
    "CATALOGUE",
    "ObjectModel",
    "Symmetry",
    "catalogue_names",
    "load_mesh_file",
    "load_object",
]

_CYLINDER_SECTIONS = 96


@dataclass(frozen=True)
class Symmetry:
    """Orientations that look the same: ``q ⊗ s`` for each ``s`` in the group, exactly.

    Attributes:
        discrete: ``(K, 4)`` wxyz quaternions, identity included.
        continuous_z: if true the object is also invariant to any rotation about its own z axis,
            so the group is ``{s ⊗ R_z(φ)}`` for all φ (a cylinder); handled in closed form.
    """

    discrete: torch.Tensor
    continuous_z: bool = False

    @property
    def order(self) -> float:
        return float("inf") if self.continuous_z else float(self.discrete.shape[0])

    def _aligned_parts(self, q_est: torch.Tensor, q_true: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Norms of the part of ``r = s^-1 ⊗ q_true^-1 ⊗ q_est`` inside / outside the group, ``(..., K)``.

        For a discrete element the group part is ``r_w``; with the continuous z symmetry the best
        rotation about z matches ``(r_w, r_z)`` exactly (maximise ``r_w cos(φ/2) + r_z sin(φ/2)``).
        """
        from pytorch_kinematics import transforms as pkt

        r = pkt.quaternion_raw_multiply(pkt.quaternion_invert(q_true), q_est).unsqueeze(-2)
        t = pkt.quaternion_raw_multiply(pkt.quaternion_invert(self.discrete.to(r)), r)  # (..., K, 4)
        if self.continuous_z:
            inside = torch.stack([t[..., 0], t[..., 3]], -1).norm(dim=-1)
            outside = torch.stack([t[..., 1], t[..., 2]], -1).norm(dim=-1)
        else:
            inside = t[..., 0].abs()
            outside = t[..., 1:].norm(dim=-1)
        return inside, outside

    def max_squared_alignment(self, q_est: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
        """``max_{q_gt ∈ Q_gt} <q_est, q_gt>^2`` with ``Q_gt = {q_true ⊗ s}``, batched over ``(...)``."""
        inside, outside = self._aligned_parts(q_est, q_true)
        return (inside**2 / (inside**2 + outside**2).clamp_min(1e-30)).amax(-1)

    def canonical_distance(self, q_est: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
        """``min_{q_gt ∈ Q_gt} (1 - <q_est, q_gt>^2)``: the angular term of Eq. pam, in [0, 1]."""
        return 1.0 - self.max_squared_alignment(q_est, q_true)

    def angle(self, q_est: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
        """Smallest rotation angle in rad between ``q_est`` and any orientation equivalent to ``q_true``."""
        # atan2 of the two parts stays accurate near 0, where acos of a float32 dot product does not
        inside, outside = self._aligned_parts(q_est, q_true)
        return (2.0 * torch.atan2(outside, inside)).amin(-1)


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
            ``"primitives"`` (catalogue pieces) or ``"v-hacd"`` (a concave user mesh decomposed).
    """

    name: str
    mesh: trimesh.Trimesh
    symmetry: Symmetry
    collision_parts: list[trimesh.Trimesh] = field(default_factory=list)
    collision_source: str = "convex hull"

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


def _rotations_of_cube_group() -> np.ndarray:
    """The 24 proper rotation matrices that permute the coordinate axes with signs."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            m = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs, strict=True)):
                m[row, col] = sign
            if np.linalg.det(m) > 0:
                mats.append(m)
    return np.stack(mats)


def detect_symmetry(mesh: trimesh.Trimesh, tolerance: float | None = None, samples: int = 2000) -> Symmetry:
    """The axis-permuting rotations (of the 24 of a cube) that map the mesh onto itself.

    A rotation R is kept when every surface sample of R·mesh lies within ``tolerance`` (default 1 % of
    the largest extent) of the original surface. Continuous symmetries are not detected here.
    """
    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    tolerance = tolerance if tolerance is not None else 0.01 * float(max(mesh.extents))
    points, _ = trimesh.sample.sample_surface(mesh, samples, seed=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    rotations = _rotations_of_cube_group()
    moved = np.einsum("kij,nj->kni", rotations, points).astype(np.float32)
    dist = scene.compute_distance(o3d.core.Tensor(moved.reshape(-1, 3))).numpy().reshape(len(rotations), -1)
    kept = [rot for rot, d in zip(rotations, dist, strict=True) if float(d.max()) <= tolerance]
    mats = torch.as_tensor(np.stack(kept), dtype=torch.float32)
    from pytorch_kinematics import transforms as pkt

    quats = pkt.matrix_to_quaternion(mats)
    # identity first, for readability of saved files and logs
    order = torch.argsort(-quats[:, 0].abs(), stable=True)
    return Symmetry(quats[order].contiguous())


def _z_flip_symmetry() -> Symmetry:
    """Identity and a half turn about x, combined with any rotation about z (a cylinder)."""
    return Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]), continuous_z=True)


def _centred(mesh: trimesh.Trimesh, parts: list[trimesh.Trimesh] | None = None):
    offset = -np.asarray(mesh.center_mass)
    mesh = mesh.copy()
    mesh.apply_translation(offset)
    moved = []
    for part in parts or []:
        part = part.copy()
        part.apply_translation(offset)
        moved.append(part)
    return mesh, moved


def _build(name: str) -> ObjectModel:
    if name == "modified_cube":
        mesh, parts = _modified_cube()
        mesh, parts = _centred(mesh, parts)
        return ObjectModel(name, mesh, detect_symmetry(mesh), parts, "primitives")
    if name in ("cylinder", "cylinder_wide"):
        mesh, _ = _centred(_cylinder(0.1 if name == "cylinder" else 0.15, 0.2))
        return ObjectModel(name, mesh, _z_flip_symmetry())
    builders = {
        "cube": lambda: _box((0.2, 0.2, 0.2)),
        "prism_thin": lambda: _box((0.1, 0.2, 0.2)),
        "prism_long": lambda: _box((0.3, 0.2, 0.2)),
        "hybrid": _hybrid,
    }
    mesh, _ = _centred(builders[name]())
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
    return list(CATALOGUE)


#: V-HACD settings (pybullet's defaults, stated so the cache key names them): voxels, concavity, vertices.
VHACD_SETTINGS = {"resolution": 100000, "concavity": 0.0025, "maxNumVerticesPerCH": 64}
#: A closed mesh whose volume is below this fraction of its convex hull's is concave (decomposed).
CONVEX_VOLUME_FRACTION = 0.99

_DECOMPOSITIONS: dict[str, list[trimesh.Trimesh]] = {}


def convex_decomposition(mesh: trimesh.Trimesh, cache_dir: str | Path | None = None) -> list[trimesh.Trimesh]:
    """Convex parts whose union approximates a closed concave ``mesh`` (V-HACD, pybullet's ``vhacd``).

    Deterministic for a given mesh; computed once per mesh and process (memoised by the SHA-256 of its
    vertices, faces and :data:`VHACD_SETTINGS`). With ``cache_dir`` the decomposition is also kept there as
    ``vhacd-<digest>.obj`` and reused by later processes; without, its files go to a temporary folder that
    is removed at once.

    Raises:
        InvalidMeshError: V-HACD produced no usable part.
    """
    import hashlib
    import json
    import tempfile

    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    digest = hashlib.sha256(vertices.tobytes() + faces.tobytes()
                            + json.dumps(VHACD_SETTINGS, sort_keys=True).encode()).hexdigest()[:32]
    if digest in _DECOMPOSITIONS:
        return [part.copy() for part in _DECOMPOSITIONS[digest]]
    cached = Path(cache_dir) / f"vhacd-{digest}.obj" if cache_dir is not None else None
    if cached is not None and cached.is_file():
        parts = _obj_parts(cached)
    else:
        with tempfile.TemporaryDirectory(prefix="pushtorch-vhacd-") as folder:
            source, result = Path(folder) / "mesh.obj", Path(folder) / "parts.obj"
            source.write_text("".join(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in vertices)
                              + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
            _run_vhacd(source, result, Path(folder) / "vhacd.log")
            parts = _obj_parts(result)
            if cached is not None:
                from pushtorch.sim.records import atomic_write_bytes

                atomic_write_bytes(cached, result.read_bytes())
    if not parts:
        raise InvalidMeshError("the convex decomposition (V-HACD) of the mesh produced no part")
    _DECOMPOSITIONS[digest] = parts
    return [part.copy() for part in parts]


def _run_vhacd(source: Path, result: Path, log_file: Path) -> None:
    """pybullet's V-HACD with its console output silenced (it prints to the C stdout)."""
    import os
    import sys

    import pybullet

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            pybullet.vhacd(str(source), str(result), str(log_file), **VHACD_SETTINGS)
    finally:
        os.dup2(saved, 1)
        os.close(saved)
    if not result.is_file():
        raise InvalidMeshError(f"the convex decomposition (V-HACD) wrote no result; see {log_file}")


def _obj_parts(path: Path) -> list[trimesh.Trimesh]:
    """The objects (``o`` groups) of a V-HACD result OBJ as convex meshes (vertex indices are global)."""
    vertices: list[list[float]] = []
    groups: list[list[list[int]]] = []
    for line in path.read_text().splitlines():
        head, _, rest = line.partition(" ")
        if head == "o":
            groups.append([])
        elif head == "v":
            vertices.append([float(v) for v in rest.split()[:3]])
        elif head == "f":
            if not groups:
                groups.append([])
            groups[-1].append([int(v.split("/")[0]) - 1 for v in rest.split()])
    points = np.asarray(vertices, dtype=np.float64)
    parts = []
    for faces in groups:
        used = np.unique(np.concatenate([np.asarray(f) for f in faces])) if faces else np.zeros(0, int)
        if len(used) >= 4:
            try:
                parts.append(trimesh.convex.convex_hull(points[used]))
            except Exception:  # a flat sliver (Qhull refuses it) holds no volume: leave it out
                continue
    return [part for part in parts if part.volume > 0]


def load_mesh_file(path: str | Path, scale: float = 1.0, name: str | None = None,
                   cache_dir: str | Path | None = None) -> ObjectModel:
    """Load any STL, OBJ or PLY mesh as an object, scaled by ``scale`` (file units × scale = metres).

    The mesh is re-centred at its centre of mass; its symmetries are detected among the 24 axis
    permutations (see :func:`detect_symmetry`). A closed concave mesh is simulated as its V-HACD convex
    parts (:func:`convex_decomposition`, ``cache_dir`` keeps them), a closed convex one as itself, an open
    one as its convex hull (module docstring); ``collision_source`` and ``len(collision_parts)`` say which.
    The object's name is ``name`` or the file's stem with characters unfit for a file name replaced by ``_``.

    Raises:
        InvalidMeshError: the file is missing or unreadable, holds no triangles, NaN/infinite vertices,
            several disjoint bodies, or encloses no volume.
        InvalidParameterError: ``scale`` is not a positive finite number; UnsafeNameError: a ``name``
            unfit for a file name.
    """
    from pushtorch.paths import safe_name, sanitised_name

    try:
        scale = float(scale)
    except (TypeError, ValueError) as exc:
        raise InvalidParameterError(f"mesh scale must be a positive finite number, got {scale!r}") from exc
    if not (np.isfinite(scale) and scale > 0):
        raise InvalidParameterError(f"mesh scale must be a positive finite number, got {scale!r}")
    name = safe_name(name, "object name") if name is not None else sanitised_name(Path(path).stem)
    path = Path(path)
    if path.is_dir():
        raise InvalidMeshError(f"{path} is a folder, not a mesh file (STL, OBJ or PLY)")
    if not path.is_file():
        raise InvalidMeshError(f"mesh file not found: {path}")
    try:
        # unprocessed, so NaN vertices are seen here (processing silently drops them and their faces)
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad files: the cause is the file, not the reader
        raise InvalidMeshError(
            f"could not read a mesh from {path}: the file is malformed or not a {path.suffix or 'mesh'} file "
            f"({type(exc).__name__})"
        ) from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InvalidMeshError(f"{path} holds no triangle mesh")
    bad = ~np.isfinite(np.asarray(loaded.vertices)).all(-1)
    if bad.any():
        raise InvalidMeshError(
            f"{path} has NaN or infinite coordinates in {int(bad.sum())} of {len(bad)} vertices"
        )
    mesh = trimesh.Trimesh(vertices=np.asarray(loaded.vertices) * scale, faces=loaded.faces)  # merged
    if len(mesh.faces) == 0:
        raise InvalidMeshError(f"{path} holds only degenerate triangles")
    bodies = mesh.split(only_watertight=False)
    if len(bodies) > 1:
        raise InvalidMeshError(
            f"{path} holds {len(bodies)} disjoint bodies; pushtorch pushes one rigid body: "
            "keep one body per file (or join them into one)"
        )
    source = "convex hull"
    if not mesh.is_watertight:
        # The centre of mass of an open mesh is undefined; its convex hull is the best physical proxy.
        try:
            mesh = mesh.convex_hull
        except Exception as exc:  # scipy's QhullError on flat or degenerate meshes
            raise InvalidMeshError(f"{path} is open and flat: it encloses no volume") from exc
    if not mesh.volume > 0:
        raise InvalidMeshError(f"{path} encloses no volume after scaling by {scale}")
    mesh, _ = _centred(mesh)
    parts: list[trimesh.Trimesh] = []
    if mesh.volume < CONVEX_VOLUME_FRACTION * mesh.convex_hull.volume:
        low, high = mesh.bounds
        # V-HACD's voxelised hulls overhang the mesh by about a voxel; kept inside its bounding box, the
        # object rests at its rest_height instead of on a millimetre of overhang
        parts = [trimesh.convex.convex_hull(np.clip(part.vertices, low, high))
                 for part in convex_decomposition(mesh, cache_dir)]
        source = "v-hacd"
    return ObjectModel(name, mesh, detect_symmetry(mesh), parts, source)


def load_object(name: str, path: str | Path | None = None, scale: float = 1.0,
                cache_dir: str | Path | None = None) -> ObjectModel:
    """A catalogue object by name, or a user mesh when ``name == "mesh"`` (``path``, ``scale`` and the
    folder ``cache_dir`` that keeps a concave mesh's decomposition, see :func:`load_mesh_file`).

    Raises:
        InvalidParameterError: unknown catalogue name, or object=mesh without a path.
    """
    if name == "mesh":
        if path is None or str(path) in ("", "???"):  # "???": Hydra's mandatory value, left unset
            raise InvalidParameterError(
                "object=mesh needs object.path=<an STL, OBJ or PLY file>; object.path is not set"
            )
        return load_mesh_file(path, scale, cache_dir=cache_dir)
    if name not in CATALOGUE:
        raise InvalidParameterError(f"unknown object {name!r}; the catalogue has {', '.join(CATALOGUE)}")
    if name not in _CACHE:
        _CACHE[name] = _build(name)
    return _CACHE[name]
