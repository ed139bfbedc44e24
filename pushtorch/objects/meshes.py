"""User meshes as the physics engine pushes them: loading, units, up axis, parts that form one body, convex
decomposition (paper, Test Set: objects beyond the catalogue).

User meshes are simulated as they are (:func:`load_mesh_file`): a closed convex mesh as itself, a closed
concave one as the union of the convex parts of a V-HACD decomposition (pybullet's ``vhacd``: offline,
deterministic, run once per mesh and cached in memory, and on disk when a ``cache_dir`` is named; otherwise
its files live in a temporary folder removed at once); an open mesh encloses no volume and is simulated as
its convex hull. A mesh of several connected parts (V-HACD outputs, CAD exports, pybullet_data's own
meshes) is one rigid body when its parts overlap, touch or lie :data:`BODY_GAP` (1 mm, after scaling) apart
or closer, transitively (the exact smallest distance between two parts: surfaces that cross, one part
inside the other, else vertex-to-triangle and edge-to-edge distances); parts farther apart are several
bodies and refused, the message giving the gap (one rigid body is pushed). Such a body is simulated as
each part's convex hull when the part is convex or open and its V-HACD parts when it is closed and concave,
and its mesh (clouds, features, symmetries, mass) is the watertight union of its closed parts and its open
parts' hulls (manifold3d). The parts are the file's own when each closes on its own, else those of the
mesh with coincident vertices merged. A mesh whose largest extent after scaling is outside
:data:`SIZE_RANGE` (0.01–2 m) is refused with the ``object.scale`` that would make it 0.2 m, so a file in
millimetres is never pushed as a 200 m object; ``up="y"`` turns a y-up file (+90° about x) before
anything else. The mass distribution is always the mesh's own (uniform density).

Frames: every mesh is in metres with its origin at its centre of mass; for the prisms the first
dimension lies along the object's x axis (the push direction when the object sits at yaw 0), and the
cylinders' and the hybrid's axes are the object's z axis (upright on the ground).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import trimesh

from pushtorch.errors import InvalidMeshError, InvalidParameterError
from pushtorch.objects.object_model import ObjectModel, centred
from pushtorch.objects.symmetry_detection import detect_symmetry

__all__ = [
    "BODY_GAP",
    "CONVEX_VOLUME_FRACTION",
    "MAX_PARTS",
    "SIZE_RANGE",
    "SUGGESTED_SIZE",
    "UP_AXES",
    "VHACD_SETTINGS",
    "check_up_axis",
    "convex_decomposition",
    "load_mesh_file",
    "save_mesh_file",
]

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
                from pushtorch.io import atomic_write_bytes

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


#: ``object.up``: the file axis that points up. ``"y"`` turns the mesh +90° about x, so its +y becomes +z.
UP_AXES = ("z", "y")
#: Parts of a mesh whose surfaces are this close or closer (m, after scaling) are one rigid body.
BODY_GAP = 1e-3
#: Largest extents (m, after scaling) a user mesh may have: objects this robot can push.
SIZE_RANGE = (0.01, 2.0)
#: The largest extent (m) a refused mesh's suggested ``object.scale`` gives it: the paper's objects' size.
SUGGESTED_SIZE = 0.2
#: Unit hints of a refused size: file unit → the ``object.scale`` of a file in it.
_UNITS = {"millimetres": 1e-3, "centimetres": 1e-2, "metres": 1.0}
#: Most connected parts a mesh may have to be joined into one body (each pair of nearby parts is measured).
MAX_PARTS = 256
#: Edges per side whose exact edge-to-edge distances :func:`_gap` computes, at most (the nearest ones).
_MAX_GAP_EDGES = 2000


def check_up_axis(up: str) -> str:
    """``up`` if it is one of :data:`UP_AXES`.

    Raises:
        InvalidParameterError: any other value.
    """
    if not isinstance(up, str) or up not in UP_AXES:
        raise InvalidParameterError(f"object.up must be one of {', '.join(UP_AXES)} (the file axis that points "
                                    f"up), got {up!r}")
    return up


def _shown(value: float) -> str:
    """``value`` to three significant digits, without an exponent for 1000 or 0.001."""
    return f"{float(f'{value:.3g}'):g}"


def _size_problem(path: Path, extent: float, scale: float) -> str | None:
    """Why a mesh whose largest extent is ``extent`` m (at ``scale``) is refused, with the scale that fits it;
    ``None`` when the extent is in :data:`SIZE_RANGE`."""
    low, high = SIZE_RANGE
    if low <= extent <= high:
        return None
    suggested = scale * SUGGESTED_SIZE / extent
    size = f"{_shown(extent * 1e3)} mm" if extent < low else f"{_shown(extent)} m"
    # a unit whose scale is within a factor of about 3 of the suggested one is likely the file's
    hint = next((f" ({unit_scale:g} if the file is in {unit})" for unit, unit_scale in _UNITS.items()
                 if abs(np.log10(suggested / unit_scale)) <= 0.5 and unit_scale != scale), "")
    if not hint and extent < low and abs(np.log10(suggested / scale / 1e3)) <= 0.5:
        hint = (f" ({_shown(suggested)} if its numbers are 1000 times too small, e.g. millimetres converted to "
                "metres twice)")
    return (f"{path} is {size} across (largest extent) at object.scale={scale:g}; objects for this robot are "
            f"{low:g}–{high:g} m. object.scale={_shown(suggested)} would make it {SUGGESTED_SIZE:g} m{hint}")


class _Surface:
    """One connected part of a mesh as an open3d scene: exact point-to-triangle distances, segment crossings
    and inside tests (float32, about ``origin``, so the coordinates stay small)."""

    def __init__(self, mesh: trimesh.Trimesh, origin: np.ndarray) -> None:
        from pushtorch.deps import import_open3d

        o3d = import_open3d()
        self._o3d = o3d
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64) - origin
        self.edges = self.vertices[np.asarray(mesh.edges_unique)]  # (E, 2, 3)
        self.closed = bool(mesh.is_watertight)
        self.bounds = np.stack([self.vertices.min(0), self.vertices.max(0)])
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))

    def _tensor(self, values: np.ndarray):
        return self._o3d.core.Tensor(np.ascontiguousarray(values, dtype=np.float32))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` exact distances (m) from ``points`` to this part's triangles."""
        return self.scene.compute_distance(self._tensor(points)).numpy().astype(np.float64)

    def crossed_by(self, segments: np.ndarray) -> bool:
        """Whether any of the ``(E, 2, 3)`` segments passes through one of this part's triangles."""
        rays = np.concatenate([segments[:, 0], segments[:, 1] - segments[:, 0]], -1)
        return bool(self.scene.test_occlusions(self._tensor(rays), tnear=0.0, tfar=1.0).numpy().any())

    def contains(self, point: np.ndarray) -> bool:
        """Whether ``point`` ``(3,)`` lies inside this part (a closed one; majority of three ray parities)."""
        return self.closed and bool(self.scene.compute_occupancy(self._tensor(point[None]), nsamples=3).numpy()[0])


def _segment_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact distances between the segments ``a`` ``(..., 2, 3)`` and ``b`` ``(..., 2, 3)`` (broadcast);
    Ericson, Real-Time Collision Detection, 5.1.9."""
    p1, p2 = a[..., 0, :], b[..., 0, :]
    d1, d2, r = a[..., 1, :] - p1, b[..., 1, :] - p2, p1 - p2
    aa, ee = np.maximum((d1 * d1).sum(-1), 1e-300), np.maximum((d2 * d2).sum(-1), 1e-300)
    bb, cc, ff = (d1 * d2).sum(-1), (d1 * r).sum(-1), (d2 * r).sum(-1)
    denominator = aa * ee - bb * bb
    crossing = np.clip((bb * ff - cc * ee) / np.maximum(denominator, 1e-300), 0, 1)
    s = np.where(denominator > 1e-12 * aa * ee, crossing, 0.0)  # parallel segments: from a's start
    t = (bb * s + ff) / ee
    s = np.where(t < 0, np.clip(-cc / aa, 0, 1), np.where(t > 1, np.clip((bb - cc) / aa, 0, 1), s))
    t = np.clip(t, 0, 1)
    return np.linalg.norm(p1 + d1 * s[..., None] - p2 - d2 * t[..., None], axis=-1)


def _near_edges(edges: np.ndarray, other: _Surface, bound: float) -> np.ndarray:
    """The edges that may come closer than ``bound`` to ``other`` (their midpoint's distance less half their
    length), the :data:`_MAX_GAP_EDGES` nearest at most."""
    half = 0.5 * np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    lower = other.distance(edges.mean(1)) - half
    near = np.flatnonzero(lower < bound)
    return edges[near[np.argsort(lower[near], kind="stable")[:_MAX_GAP_EDGES]]]


def _gap(a: _Surface, b: _Surface) -> float:
    """Smallest distance (m) between two parts: 0 when their surfaces cross or touch or one holds the other,
    else the least of the vertex-to-triangle distances both ways and the edge-to-edge distances of the edges
    that can come closer (where the closest points of two polyhedra lie; exact unless more than
    :data:`_MAX_GAP_EDGES` edges of a part can, when the nearest of them are measured)."""
    if b.crossed_by(a.edges) or a.crossed_by(b.edges) or b.contains(a.vertices[0]) or a.contains(b.vertices[0]):
        return 0.0
    best = float(min(b.distance(a.vertices).min(), a.distance(b.vertices).min()))
    near_a, near_b = _near_edges(a.edges, b, best), _near_edges(b.edges, a, best)
    step = max(1, 2**20 // max(1, len(near_b)))  # about a million pairs at a time
    for start in range(0, len(near_a) if len(near_b) else 0, step):
        best = min(best, float(_segment_distances(near_a[start:start + step, None], near_b[None]).min()))
    return best


def _box_gap(a: _Surface, b: _Surface) -> float:
    """Distance (m) between two parts' bounding boxes: a lower bound of :func:`_gap`."""
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(a.bounds[0] - b.bounds[1], b.bounds[0] - a.bounds[1]))))


def _bodies(parts: list[trimesh.Trimesh]) -> tuple[list[list[int]], float]:
    """The parts grouped into rigid bodies (parts :data:`BODY_GAP` apart or closer, transitively, are one), and
    the smallest distance (m) between two bodies (``inf`` for one body)."""
    origin = np.concatenate([p.bounds for p in parts]).mean(0)
    surfaces = [_Surface(p, origin) for p in parts]
    body = list(range(len(parts)))

    def root(i: int) -> int:
        while body[i] != i:
            body[i] = body[body[i]]
            i = body[i]
        return i

    pairs = sorted((_box_gap(surfaces[i], surfaces[j]), i, j)
                   for i, j in itertools.combinations(range(len(parts)), 2))
    gaps: dict[tuple[int, int], float] = {}
    for lower, i, j in pairs:
        if lower > BODY_GAP:
            break
        if root(i) != root(j):
            gaps[i, j] = _gap(surfaces[i], surfaces[j])
            if gaps[i, j] <= BODY_GAP:
                body[root(i)] = root(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(parts)):
        groups.setdefault(root(i), []).append(i)
    apart = float("inf")
    if len(groups) > 1:
        for lower, i, j in pairs:
            if lower >= apart:
                break
            if root(i) != root(j):
                apart = min(apart, gaps[i, j] if (i, j) in gaps else _gap(surfaces[i], surfaces[j]))
    return list(groups.values()), apart


def _face_components(vertex_count: int, faces: np.ndarray) -> list[np.ndarray]:
    """The faces of each connected component (faces sharing a vertex, by index, are connected), as index arrays
    in the file's order."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(vertex_count, vertex_count))
    labels = connected_components(graph, directed=False)[1][faces[:, 0]]
    _, counts = np.unique(labels, return_counts=True)
    return np.split(np.argsort(labels, kind="stable"), np.cumsum(counts)[:-1])


def _closed_by_index(faces: np.ndarray) -> bool:
    """Whether every edge of ``faces`` (by vertex index) is shared by exactly two faces."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return bool((np.unique(edges, axis=0, return_counts=True)[1] == 2).all())


def _connected_parts(path: Path, vertices: np.ndarray, faces: np.ndarray,
                     merged: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """The connected parts of a mesh: the file's own (faces sharing a vertex of the file, each merged) when
    every one of them is closed, as V-HACD results and exports of several objects are; else the parts of the
    merged mesh (faces sharing a vertex position: an STL's triangles, a file with seams).

    Raises:
        InvalidMeshError: more than :data:`MAX_PARTS` parts (a soup of loose triangles).
    """
    groups = _face_components(len(vertices), faces) if _closed_by_index(faces) else []
    parts = [trimesh.Trimesh(vertices, faces[g]) for g in groups] if len(groups) <= MAX_PARTS else []
    if parts and all(p.is_watertight for p in parts):
        return parts
    merged_faces = np.asarray(merged.faces)
    groups = _face_components(len(merged.vertices), merged_faces)
    if len(groups) > MAX_PARTS:
        raise InvalidMeshError(f"{path} holds {len(groups)} separate parts; at most {MAX_PARTS} are joined into "
                               "one body: join them (or merge their coincident vertices) in a mesh editor")
    return [trimesh.Trimesh(merged.vertices, merged_faces[g]) for g in groups]


def _joined(path: Path, vertices: np.ndarray, faces: np.ndarray, merged: trimesh.Trimesh,
            cache_dir: str | Path | None) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh], str, np.ndarray]:
    """A mesh of several connected parts as one body: its watertight union (centred at its centre of mass),
    its convex collision parts, their ``collision_source`` (module docstring) and the union's centre of mass in
    the file's frame.

    Raises:
        InvalidMeshError: parts more than :data:`BODY_GAP` apart (several bodies), no part that encloses a
            volume, or a union that is not one closed surface.
    """
    parts = _connected_parts(path, vertices, faces, merged)
    groups, apart = _bodies(parts)
    if len(groups) > 1:
        nearest = f"{apart * 1e3:.1f} mm apart"
        nearest = f" {nearest}" if len(groups) == 2 else f", the nearest two {nearest}"
        raise InvalidMeshError(
            f"{path} holds {len(groups)} disjoint bodies{nearest}; parts {BODY_GAP * 1e3:g} mm apart or closer "
            "count as one body, and pushtorch pushes one rigid body: keep one body per file (or join them into one)"
        )
    solids, closed = [], []
    for part in parts:
        if part.is_watertight and part.volume < 0:
            part.invert()
        if part.is_watertight and part.volume > 0:
            solids.append(part)
            closed.append(True)
            continue
        try:  # an open part encloses no volume: its convex hull stands in for it
            hull = part.convex_hull
        except Exception:  # scipy's QhullError: a flat part holds no volume and is left out
            continue
        if hull.volume > 0:
            solids.append(hull)
            closed.append(False)
    if not solids:
        raise InvalidMeshError(f"{path} encloses no volume: none of its {len(parts)} parts is a solid")
    try:
        union = solids[0] if len(solids) == 1 else trimesh.boolean.union(solids, engine="manifold")
    except Exception as exc:  # manifold3d refuses a part it cannot read as a solid
        raise InvalidMeshError(f"{path}: its {len(solids)} parts could not be joined into one solid "
                               f"({type(exc).__name__})") from exc
    volumes = [s.volume for s in solids]
    # the union holds the largest part and at most all of them (to rounding)
    if not (union.is_watertight and max(volumes) * (1 - 1e-4) <= union.volume <= sum(volumes) * (1 + 1e-4)):
        raise InvalidMeshError(f"{path}: the union of its {len(solids)} parts is not one closed surface")
    origin = np.array(union.center_mass, dtype=np.float64)
    mesh, solids = centred(union, solids)
    collision: list[trimesh.Trimesh] = []
    decomposed = False
    for solid, was_closed in zip(solids, closed, strict=True):
        hull = solid.convex_hull
        if not was_closed or solid.volume >= CONVEX_VOLUME_FRACTION * hull.volume:
            collision.append(hull)
            continue
        low, high = solid.bounds  # as for a single concave mesh (load_mesh_file)
        collision += [trimesh.convex.convex_hull(np.clip(piece.vertices, low, high))
                      for piece in convex_decomposition(solid, cache_dir)]
        decomposed = True
    return mesh, collision, "convex parts and v-hacd" if decomposed else "convex parts", origin


def load_mesh_file(path: str | Path, scale: float = 1.0, name: str | None = None,
                   cache_dir: str | Path | None = None, up: str = "z") -> ObjectModel:
    """Load any STL, OBJ or PLY mesh as an object, scaled by ``scale`` (file units × scale = metres).

    With ``up="y"`` the file's +y axis is turned to +z (+90° about x) before anything else; ``"z"`` keeps it.
    The mesh is re-centred at its centre of mass; its symmetries (discrete turns about any axis, and a
    continuous one for a surface of revolution) are detected by :func:`detect_symmetry`. A closed concave
    mesh is simulated as its V-HACD convex parts (:func:`convex_decomposition`, ``cache_dir`` keeps them), a
    closed convex one as itself, an open one as its convex hull; a mesh of several connected parts that
    overlap, touch or lie :data:`BODY_GAP` apart or closer is one body: their watertight union, simulated as
    each part's convex hull or decomposition (module docstring). ``collision_source`` and
    ``len(collision_parts)`` say which.
    The object's name is ``name`` or the file's stem with characters unfit for a file name replaced by ``_``.

    Args:
        path: the mesh file.
        scale: metres per file unit.
        name: the object's name (default: from the file's stem).
        cache_dir: folder that keeps V-HACD decompositions across processes (default: none).
        up: the file's up axis, one of :data:`UP_AXES`.

    Raises:
        InvalidMeshError: the file is missing or unreadable, holds no triangles, NaN/infinite vertices, parts
            more than :data:`BODY_GAP` apart (several bodies, the message gives the gap), a largest extent
            outside :data:`SIZE_RANGE` after scaling (the message gives the ``object.scale`` that makes it
            :data:`SUGGESTED_SIZE`), or encloses no volume.
        InvalidParameterError: ``scale`` is not a positive finite number, or ``up`` is not one of
            :data:`UP_AXES`; UnsafeNameError: a ``name`` unfit for a file name.
    """
    from pushtorch.paths import safe_name, sanitised_name

    up = check_up_axis(up)
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
    vertices = np.asarray(loaded.vertices)
    if up == "y":  # +90° about x: (x, y, z) -> (x, -z, y), exact
        vertices = np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], -1)
    mesh = trimesh.Trimesh(vertices=vertices * scale, faces=loaded.faces)  # merged
    if len(mesh.faces) == 0:
        raise InvalidMeshError(f"{path} holds only degenerate triangles")
    problem = _size_problem(path, float(np.max(mesh.extents)), scale)
    if problem:
        raise InvalidMeshError(problem)
    if len(mesh.split(only_watertight=False)) > 1:
        mesh, parts, source, origin = _joined(path, vertices * scale, np.asarray(loaded.faces), mesh, cache_dir)
        return ObjectModel(name, mesh, detect_symmetry(mesh), parts, source, origin)
    source = "convex hull"
    if not mesh.is_watertight:
        # The centre of mass of an open mesh is undefined; its convex hull is the best physical proxy.
        try:
            mesh = mesh.convex_hull
        except Exception as exc:  # scipy's QhullError on flat or degenerate meshes
            raise InvalidMeshError(f"{path} is open and flat: it encloses no volume") from exc
    if not mesh.volume > 0:
        raise InvalidMeshError(f"{path} encloses no volume after scaling by {scale}")
    origin = np.array(mesh.center_mass, dtype=np.float64)
    mesh, _ = centred(mesh)
    parts: list[trimesh.Trimesh] = []
    if mesh.volume < CONVEX_VOLUME_FRACTION * mesh.convex_hull.volume:
        low, high = mesh.bounds
        # V-HACD's voxelised hulls overhang the mesh by about a voxel; kept inside its bounding box, the
        # object rests at its rest_height instead of on a millimetre of overhang
        parts = [trimesh.convex.convex_hull(np.clip(part.vertices, low, high))
                 for part in convex_decomposition(mesh, cache_dir)]
        source = "v-hacd"
    return ObjectModel(name, mesh, detect_symmetry(mesh), parts, source, origin)


def save_mesh_file(mesh: trimesh.Trimesh, path: str | Path) -> None:
    """Write ``mesh`` as a binary PLY with float64 vertices, atomically: lossless, so :func:`load_mesh_file`
    reads back the same vertices and faces bit for bit (trimesh's own PLY export rounds to float32).

    Raises:
        InvalidParameterError: ``path`` does not end in ``.ply``.
    """
    from pushtorch.io import atomic_write_bytes

    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise InvalidParameterError(f"{path}: a lossless mesh is written as .ply")
    vertices = np.ascontiguousarray(mesh.vertices, dtype="<f8")
    faces = np.zeros(len(mesh.faces), dtype=[("count", "<u1"), ("index", "<i4", (3,))])
    faces["count"], faces["index"] = 3, np.asarray(mesh.faces)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    atomic_write_bytes(path, header.encode("ascii") + vertices.tobytes() + faces.tobytes())
