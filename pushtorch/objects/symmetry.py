"""Visual symmetries Q_gt of an object: which rotations leave it looking the same (paper, Prediction Accuracy
Measure, Eq. pam).

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

Symmetries (:func:`detect_symmetry`, for every mesh but the cylinders, whose group is written down): a
rotation about the centre of mass is a symmetry when every surface sample (2000, seed 0) of the rotated mesh
lies within 1 % of the largest extent of the surface (open3d's exact point-to-triangle distance). The
rotations tried: continuous turns about a candidate axis (a surface of revolution: a cone, a vase, a
capsule, in any orientation), the 24 axis-permuting rotations (the boxes), turns by 360°/n (n = 2 … 12)
about candidate axes and half turns across them. Candidate axes are the object's x, y, z axes, the
principal axes of the surface's and the solid's second moments (every rotation axis of a symmetric body is
one), and, for the axes equal moments leave undetermined (a cube, an n-gon prism's cross-section), the
normals of the largest flat facets, the directions of the farthest vertices and a scan of the half turns
across a unique principal axis. The result is closed under composition (a group, q and -q one element, at
most 60 elements) and held as a :class:`Symmetry`: discrete rotations plus, for a surface of revolution, the
continuous axis (any direction in the object frame), both handled exactly by the accuracy measure.
Limits: an n-fold turn with n > 12 is found only as a continuous symmetry (when the n-gon is round within
the tolerance) or through two half turns; a sphere-like mesh is reported as continuous about z plus a half
turn, not as every rotation.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from pushtorch.errors import InvalidMeshError, InvalidParameterError

__all__ = [
    "Symmetry",
    "detect_symmetry",
]

_Z_AXIS = (0.0, 0.0, 1.0)
#: Two unit axes are the same line when ``|a·b| >= 1 - _ALIGNED`` (also: an axis "is" z).
_ALIGNED = 1e-6



@dataclass(frozen=True, init=False)
class Symmetry:
    """Orientations that look the same: ``q ⊗ s`` for each ``s`` in the group, exactly.

    Attributes:
        discrete: ``(K, 4)`` wxyz quaternions, identity included (first, as :func:`detect_symmetry` makes it).
        continuous_axis: ``None``, or a unit ``(3,)`` float32 vector ``a`` in the object frame: the object is
            also invariant to any rotation about ``a`` (a surface of revolution), so the group is
            ``{s ⊗ R_a(φ)}`` for all φ and every ``s`` in ``discrete`` (each ``s`` maps ``a`` to ``±a``: the
            identity and, if the object has one, a half turn that swaps the axis' ends). Handled in closed
            form (see :meth:`_aligned_parts`), not sampled.

    ``continuous_z`` (a property) is true when the continuous axis is the object's z axis. For backwards
    compatibility ``Symmetry(q, continuous_z=True)`` and ``Symmetry(q, True)`` mean ``continuous_axis = z``.
    """

    discrete: torch.Tensor
    continuous_axis: torch.Tensor | None

    def __init__(self, discrete: torch.Tensor, continuous_axis: torch.Tensor | None = None, *,
                 continuous_z: bool = False) -> None:
        """Check and store the group (``continuous_axis`` is normalised and stored as float32).

        Raises:
            InvalidParameterError: ``discrete`` is not a non-empty ``(K, 4)`` tensor of finite values, or the
                axis is not a finite non-zero 3-vector, or ``continuous_z`` contradicts ``continuous_axis``.
        """
        discrete = torch.as_tensor(discrete)
        if not discrete.is_floating_point():
            discrete = discrete.to(torch.float32)
        if discrete.ndim != 2 or discrete.shape[1] != 4 or discrete.shape[0] == 0 or not torch.isfinite(discrete).all():
            raise InvalidParameterError(
                f"symmetry quaternions must be a non-empty (K, 4) tensor of finite values, got {tuple(discrete.shape)}"
            )
        if isinstance(continuous_axis, (bool, np.bool_)):  # the old positional ``continuous_z`` flag
            continuous_axis = _Z_AXIS if continuous_axis else None
        axis = None
        if continuous_axis is not None:
            axis = torch.as_tensor(continuous_axis, dtype=torch.float64).detach().cpu()
            norm = float(axis.norm()) if axis.shape == (3,) else float("nan")
            if not (np.isfinite(norm) and norm > 1e-12):
                raise InvalidParameterError(
                    f"a continuous symmetry axis must be a finite non-zero 3-vector, got {axis.tolist()}"
                )
            axis = (axis / norm).to(torch.float32)
        if continuous_z:
            if axis is not None and abs(float(axis[2])) < 1.0 - _ALIGNED:
                raise InvalidParameterError(f"continuous_z=True contradicts continuous_axis={axis.tolist()}")
            axis = torch.tensor(_Z_AXIS, dtype=torch.float32)
        object.__setattr__(self, "discrete", discrete)
        object.__setattr__(self, "continuous_axis", axis)

    @property
    def continuous_z(self) -> bool:
        """True when the object is invariant to any rotation about its own z axis (a cylinder standing up)."""
        return self.continuous_axis is not None and abs(float(self.continuous_axis[2])) >= 1.0 - _ALIGNED

    @property
    def order(self) -> float:
        """Number of elements of the group: ``inf`` with a continuous axis, else ``K``."""
        return float("inf") if self.continuous_axis is not None else float(self.discrete.shape[0])

    def _aligned_parts(self, q_est: torch.Tensor, q_true: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Norms of the part of ``r = s^-1 ⊗ q_true^-1 ⊗ q_est`` inside / outside the group, ``(..., K)``.

        For a discrete element the group part is ``r_w``; with a continuous axis ``a`` the best rotation about
        ``a`` matches ``(r_w, r_v·a)`` exactly (maximise ``r_w cos(φ/2) + (r_v·a) sin(φ/2)``), and the rest is
        ``|r_v × a|`` (for ``a = z``: ``(r_w, r_z)`` inside, ``(r_x, r_y)`` outside).
        """
        from pytorch_kinematics import transforms as pkt

        r = pkt.quaternion_raw_multiply(pkt.quaternion_invert(q_true), q_est).unsqueeze(-2)
        t = pkt.quaternion_raw_multiply(pkt.quaternion_invert(self.discrete.to(r)), r)  # (..., K, 4)
        if self.continuous_axis is not None:
            axis = self.continuous_axis.to(t)
            vector = t[..., 1:]
            along = (vector * axis).sum(-1)
            inside = torch.stack([t[..., 0], along], -1).norm(dim=-1)
            outside = torch.linalg.cross(vector, axis.expand_as(vector)).norm(dim=-1)
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


#: Highest order of a discrete turn looked for about each candidate axis (360°/2 ... 360°/12).
_MAX_TURN_ORDER = 12
#: Largest finite group kept: the icosahedral group (60) is the largest with turns of order <= 12.
_MAX_GROUP_ORDER = 60
#: Turns (rad) a surface of revolution must survive about its axis: 14.4° (at least 14.4° from every multiple
#: of 360°/n, n <= 12, so no n-gon prism of such an order passes), the golden angle 137.5° and 108.9°.
_CONTINUOUS_TEST_ANGLES = (2 * np.pi / 25, np.pi * (3 - np.sqrt(5)), 1.9)
#: Two rotations less than this angle (rad) apart are one group element, or less than the angle that moves
#: no surface point by more than the tolerance when that is larger (a noisy mesh's symmetries compose into
#: near copies of each other), at most :data:`_SAME_ROTATION_MAX` (distinct elements of a group of at most
#: 60 are 6° apart at least).
_SAME_ROTATION = 1e-3
_SAME_ROTATION_MAX = 0.05
#: A rotation that passes with a largest sample distance above this fraction of the tolerance is polished.
_EXACT = 1e-3
#: A continuous axis (and the half turn across it) is the first candidate whose largest distance is within
#: this fraction of the tolerance of the best candidate's.
_CLOSE_ENOUGH = 0.1
#: Samples of the quick rejection stages before the full test (:class:`_SurfaceCheck`).
_SCREEN_STAGES = (64, 256)
#: Principal moments closer than this fraction of the largest are equal (their eigenvectors arbitrary).
_DEGENERATE_MOMENTS = 0.05
#: Facet normals and far-vertex directions tried as axes (each).
_EXTRA_AXES = 8
#: Planes scanned for half turns across an axis (:func:`_scan_half_turns`), at most.
_MAX_SCANS = 4


class _SurfaceCheck:
    """The symmetry test: every surface sample of the rotated mesh lies within ``tolerance`` of the surface.

    Distances are open3d's exact point-to-triangle distances; a rotation is first screened on the first 64,
    then 256 samples (the samples are in random order), so only plausible rotations pay the full test. The
    verdict is the full test's: a subset's largest distance never exceeds the whole set's.
    """

    def __init__(self, mesh: trimesh.Trimesh, samples: int, tolerance: float) -> None:
        """Sample ``samples`` surface points (seed 0: deterministic) and build the distance query."""
        from pushtorch.deps import import_open3d

        o3d = import_open3d()
        self._o3d = o3d
        points, _ = trimesh.sample.sample_surface(mesh, samples, seed=0)
        self.points = torch.as_tensor(np.asarray(points), dtype=torch.float64)
        self.tolerance = float(tolerance)
        self.radius = float(np.linalg.norm(np.asarray(mesh.vertices), axis=1).max())
        #: rotations closer than this are one group element (see _SAME_ROTATION)
        self.same_angle = float(np.clip(self.tolerance / max(self.radius, 1e-12), _SAME_ROTATION, _SAME_ROTATION_MAX))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
        )

    def max_distance(self, quats: torch.Tensor, count: int | None = None) -> torch.Tensor:
        """Largest distance ``(K,)`` of the first ``count`` samples rotated by each of ``quats (K, 4)``."""
        from pytorch_kinematics import transforms as pkt

        points = self.points[:count]
        mats = pkt.quaternion_to_matrix(quats.to(torch.float64))  # (K, 3, 3)
        moved = _dot(mats[:, None, :, :], points[None, :, None, :]).reshape(-1, 3).numpy().astype(np.float32)
        dist = self.scene.compute_distance(self._o3d.core.Tensor(moved)).numpy()
        return torch.from_numpy(dist.reshape(len(quats), -1).max(1).astype(np.float64))

    def distances(self, quats: torch.Tensor) -> torch.Tensor:
        """Largest sample distance ``(K,)`` of each of ``quats (K, 4)``, ``inf`` for those a screen rejected."""
        worst = torch.zeros(len(quats), dtype=torch.float64)
        for count in (*_SCREEN_STAGES, None):
            if count is not None and count >= len(self.points):
                continue
            index = (worst <= self.tolerance).nonzero().squeeze(1)
            if index.numel() == 0:
                break
            measured = self.max_distance(quats[index], count)
            worst[index] = torch.where(measured > self.tolerance, torch.inf, measured)
        return worst

    def passes(self, quats: torch.Tensor) -> torch.Tensor:
        """Which of ``quats (K, 4)`` map the mesh onto itself within the tolerance, ``(K,)`` bool."""
        return self.distances(quats) <= self.tolerance


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a * b).sum(-1)`` with broadcasting. Elementwise on purpose: these products are tiny, and a BLAS
    matrix product of a few rows can cost milliseconds when its threads wait for a busy CPU."""
    return (a * b).sum(-1)


def _turns(axes: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(A, B, 4)`` of the turns by each of ``angles (B,)`` about each unit axis of ``axes (A, 3)``."""
    from pytorch_kinematics import transforms as pkt

    return pkt.axis_angle_to_quaternion(axes[:, None, :] * angles[None, :, None])


def _left_matrices(q: torch.Tensor) -> torch.Tensor:
    """``(K, 4, 4)`` matrices ``L(q)`` with ``q ⊗ p = L(q) p`` (wxyz), for ``q (K, 4)``."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([w, -x, -y, -z, x, w, -z, y, y, z, w, -x, z, -y, x, w], -1).reshape(-1, 4, 4)


def _products(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """All products ``a_i ⊗ b_j``, ``(P, K, 4)``, of ``a (P, 4)`` and ``b (K, 4)`` (one matrix product)."""
    return _dot(_left_matrices(a)[:, None, :, :], b[None, :, None, :])


def _same_rotation(a: torch.Tensor, b: torch.Tensor, angle: float = _SAME_ROTATION) -> torch.Tensor:
    """``(P, K)`` bool: is ``a_i (P, 4)`` the same rotation as ``b_j (K, 4)`` (``q`` and ``-q`` alike), that is
    less than ``angle`` apart: ``|<a, b>| = cos(angle / 2)``, exact enough in float64."""
    return _dot(a.to(torch.float64)[:, None, :], b.to(torch.float64)[None, :, :]).abs() >= np.cos(angle / 2)


def _canonical_sign(quats: torch.Tensor) -> torch.Tensor:
    """``quats (K, 4)`` with ``w > 0``, or for half turns (``w = 0``) the first non-zero component positive."""
    significant = quats.abs() > 1e-9
    first = torch.where(significant.any(-1), significant.to(torch.int64).argmax(-1), 0)
    sign = torch.sign(quats.gather(-1, first[:, None]))
    return quats * torch.where(sign == 0, 1.0, sign).to(quats)


def _new_elements(candidates: torch.Tensor, group: torch.Tensor, room: int, same: float) -> torch.Tensor | None:
    """The distinct rotations among ``candidates (P, 4)`` not in ``group (K, 4)``, sign-canonical, in order of
    first occurrence; ``None`` when there are more than ``room``. Rotations less than ``same`` apart are one."""
    candidates = candidates[~_same_rotation(candidates, group, same).any(-1)]
    kept = []
    while len(candidates):  # one pass per distinct new rotation, at most room + 1
        if len(kept) >= room:
            return None
        kept.append(candidates[0])
        candidates = candidates[~_same_rotation(candidates, candidates[:1], same)[:, 0]]
    return _canonical_sign(torch.stack(kept)) if kept else candidates


def _closure(group: torch.Tensor, limit: int = _MAX_GROUP_ORDER, same: float = _SAME_ROTATION) -> torch.Tensor | None:
    """``group (K, 4)`` with every product of its elements added until closed; ``None`` beyond ``limit``.

    Existing elements keep their places (and signs); new ones are appended. Each round multiplies only the
    last round's new elements with the whole group (both ways): older products are already in. A product that
    turns by less than 360°/``limit`` (but is not the identity) gives up at once: its powers alone would make
    more than ``limit`` elements (two near copies of one symmetry, the usual cause, make such a product).
    Rotations less than ``same`` apart are one element.
    """
    if len(group) > limit:
        return None
    smallest_turn = np.cos(np.pi / limit) + 1e-9  # |w| of a turn by 360°/limit
    fresh = group
    while True:
        products = torch.cat([_products(fresh, group).reshape(-1, 4), _products(group, fresh).reshape(-1, 4)])
        w = products[:, 0].abs()
        if bool(((w > smallest_turn) & (w < np.cos(same / 2))).any()):
            return None
        fresh = _new_elements(products, group, limit - len(group), same)
        if fresh is None:
            return None
        if len(fresh) == 0:
            return group
        group = torch.cat([group, fresh])


def _polish(check: _SurfaceCheck, quat: torch.Tensor, distance: float) -> torch.Tensor:
    """``quat (4,)``, a rotation that passes the test, with its axis moved (its angle kept) to where the
    largest sample distance is least: a candidate axis near, not on, a symmetry axis becomes the axis.

    Pattern search on 128 samples: try the 8 neighbouring axes ``width`` away, move to the best if it is
    better, else halve ``width``; from twice the tolerance's angle down to 1e-7 rad.
    """
    count = min(128, len(check.points))
    half = float(quat[0].clamp(-1.0, 1.0))
    sine = float(quat[1:].norm())
    if sine < 1e-9:
        return quat
    axis = quat[1:] / sine
    best = float(check.max_distance(quat[None], count)[0])
    steps = torch.tensor([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if i or j], dtype=torch.float64)
    width = 2.0 * check.tolerance / max(check.radius, 1e-12)
    while width > 1e-7 and best > 0.0:
        u, v = _perpendicular(axis)
        trial = axis + width * (steps[:, :1] * u + steps[:, 1:] * v)
        trial = trial / trial.norm(dim=-1, keepdim=True)
        quats = torch.cat([torch.full((len(trial), 1), half, dtype=torch.float64), sine * trial], -1)
        scores = check.max_distance(quats, count)
        k = int(scores.argmin())
        if float(scores[k]) < best:
            best, axis = float(scores[k]), trial[k]
        else:
            width /= 2.0
    polished = torch.cat([torch.tensor([half], dtype=torch.float64), sine * axis])
    # kept only when clearly better: at float32 noise the search wanders and would spoil an exact symmetry
    return polished if float(check.max_distance(polished[None])[0]) <= 0.5 * distance else quat


def _grow(check: _SurfaceCheck, group: torch.Tensor, generators: torch.Tensor) -> torch.Tensor:
    """Add each of ``generators (G, 4)`` (in order) whose closure with ``group`` still maps the mesh onto itself.

    A generator already in the group costs nothing; one that fails the test, or whose closure fails it or
    exceeds :data:`_MAX_GROUP_ORDER` elements (a near symmetry composing into ever new rotations), is left out.
    """
    if len(generators) == 0:
        return group
    same = check.same_angle
    generators = generators[~_same_rotation(generators, group, same).any(-1)]
    if len(generators) == 0:
        return group
    worst = check.distances(generators)
    order = torch.argsort(worst, stable=True)[: int((worst <= check.tolerance).sum())]
    # the most exact first: a near symmetry (a principal axis a few tenths of a degree off, say) would
    # otherwise shut out the exact one it approximates; one that is only near is polished first
    for generator, distance in zip(generators[order], worst[order].tolist(), strict=True):
        if distance > _EXACT * check.tolerance:
            generator = _polish(check, generator, distance)
        if bool(_same_rotation(generator[None], group, same).any()):
            continue
        bigger = _closure(torch.cat([group, _canonical_sign(generator[None])]), same=same)
        if bigger is not None and bool(check.passes(bigger[len(group):]).all()):
            group = bigger
    return group


def _unique_lines(directions: torch.Tensor, limit: int | None = None, aligned: float = _ALIGNED) -> torch.Tensor:
    """The first ``limit`` distinct lines (``a`` and ``-a`` alike, the same when ``|a·b| >= 1 - aligned``) among
    unit ``directions (N, 3)``, in order."""
    directions = directions[directions.norm(dim=-1) > 0.5]
    kept = []
    while len(directions) and (limit is None or len(kept) < limit):  # one pass per line kept
        kept.append(directions[0])
        directions = directions[_dot(directions, directions[0]).abs() < 1.0 - aligned]
    return torch.stack(kept) if kept else directions


def _second_moments(mesh: trimesh.Trimesh) -> list[torch.Tensor]:
    """``(3, 3)`` second moments about the origin: the surface's (exact, area-weighted) and, for a closed
    mesh, the solid's inertia tensor (about its centre of mass, the origin of an object frame)."""
    triangles = torch.tensor(np.asarray(mesh.triangles), dtype=torch.float64)  # (F, 3, 3)
    area = torch.tensor(np.asarray(mesh.area_faces), dtype=torch.float64)
    corner_sum = triangles.sum(1)
    # ∫ x xᵀ dA over a triangle = A/12 (Σ v vᵀ + (Σ v)(Σ v)ᵀ)
    outer = (triangles[:, :, :, None] * triangles[:, :, None, :]).sum(1)
    per_face = outer + corner_sum[:, :, None] * corner_sum[:, None, :]
    moments = [(area[:, None, None] * per_face).sum(0) / 12.0]
    if mesh.is_watertight and mesh.volume > 0:
        moments.append(torch.tensor(np.asarray(mesh.moment_inertia), dtype=torch.float64))
    return moments


def _candidate_axes(mesh: trimesh.Trimesh, tolerance: float) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Axes to try turns about, ``(A, 3)`` unit, most trusted first; and the principal axes whose two other
    principal moments are equal (the axis of an n-gon prism: the half turns across it need a scan).

    In order: the object's z, x, y axes (exact, and where a user usually models an axis of symmetry); the
    principal axes of the surface's and the solid's second moments (the axis of every rotational symmetry
    is one; most distinct moment first); the normals of the largest flat facets and the directions to the
    farthest vertices (the axes a cube's or a regular solid's equal moments leave undetermined).
    """
    found = [torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)]
    unique: list[torch.Tensor] = []
    for moment in _second_moments(mesh):
        values, vectors = torch.linalg.eigh(0.5 * (moment + moment.T))
        scale = float(values.abs().max()) or 1.0
        gaps = []
        for i in range(3):
            j, k = (n for n in range(3) if n != i)
            gap = min(abs(float(values[i] - values[j])), abs(float(values[i] - values[k]))) / scale
            if abs(float(values[j] - values[k])) <= _DEGENERATE_MOMENTS * scale < gap:
                unique.append(vectors[:, i])
            gaps.append(gap)
        found.append(vectors.T[np.argsort(gaps, kind="stable")[::-1].copy()])
    areas = np.concatenate([np.asarray(mesh.facets_area), np.asarray(mesh.area_faces)])
    normals = np.concatenate([np.asarray(mesh.facets_normal).reshape(-1, 3), np.asarray(mesh.face_normals)])
    in_facet = np.zeros(len(mesh.faces), dtype=bool)
    if len(mesh.facets):
        in_facet[np.concatenate(mesh.facets)] = True
    keep = np.concatenate([np.ones(len(mesh.facets), dtype=bool), ~in_facet])
    order = np.argsort(-areas[keep], kind="stable")
    flats = _unique_lines(torch.as_tensor(normals[keep][order], dtype=torch.float64), _EXTRA_AXES)
    # each the area-weighted mean of the face normals within 10° of it (either way): a flat side's true
    # normal even when it is noisy (a scan) or split into faces that are not quite coplanar
    face_normals = torch.tensor(np.asarray(mesh.face_normals), dtype=torch.float64)
    face_areas = torch.tensor(np.asarray(mesh.area_faces), dtype=torch.float64)
    if len(flats):
        cosines = _dot(face_normals[:, None, :], flats[None, :, :])  # (F, L)
        weights = torch.where(cosines.abs() >= np.cos(np.radians(10.0)), torch.sign(cosines), 0.0) * face_areas[:, None]
        means = (weights[:, :, None] * face_normals[:, None, :]).sum(0)
        lengths = means.norm(dim=-1, keepdim=True)
        flats = torch.where(lengths > 0, means / lengths.clamp_min(1e-300), flats)
    found.append(flats)
    vertices = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    radii = vertices.norm(dim=-1)
    far = torch.argsort(-radii, stable=True)
    far = far[radii[far] >= float(radii.max()) - tolerance]
    found.append(_unique_lines(vertices[far] / radii[far, None].clamp_min(1e-300), _EXTRA_AXES))
    unique_lines = _unique_lines(torch.stack(unique)) if unique else torch.zeros(0, 3, dtype=torch.float64)
    return _unique_lines(torch.cat(found)), list(unique_lines)


def _perpendicular(axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors ``u, v`` with ``(u, v, axis)`` right-handed and orthonormal (``u`` from the coordinate
    axis least aligned with ``axis``)."""
    basis = torch.eye(3, dtype=axis.dtype)[int(axis.abs().argmin())]
    u = basis - _dot(basis, axis) * axis
    u = u / u.norm()
    return u, torch.linalg.cross(axis, u)


def _half_turns(axes: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(A, 4)`` of the half turns about unit ``axes (A, 3)``: ``(0, a)``."""
    return torch.cat([torch.zeros(len(axes), 1, dtype=axes.dtype), axes], -1)


def _scan_half_turns(check: _SurfaceCheck, axis: torch.Tensor, period: float) -> torch.Tensor | None:
    """A half turn about an axis perpendicular to ``axis`` that maps the mesh onto itself, or ``None``.

    Such half turns repeat every ``period`` (π/m with an m-fold turn about ``axis``). Their angle in the plane
    is scanned in steps that move no sample by more than the tolerance, scored on 256 samples; the best local
    minima are refined by zooming in, then tested in full.
    """
    u, v = _perpendicular(axis)
    radius = max(check.radius, 1e-12)
    steps = int(min(1024, max(16, np.ceil(period * radius / check.tolerance))))
    step = period / steps

    def flips(angles: torch.Tensor) -> torch.Tensor:
        return _half_turns(torch.cos(angles)[:, None] * u + torch.sin(angles)[:, None] * v)

    count = _SCREEN_STAGES[-1]
    angles = torch.arange(steps, dtype=torch.float64) * step
    scores = check.max_distance(flips(angles), count)
    # at the grid point nearest a true symmetry the flip axis is off by <= step/2: samples move <= radius·step
    minima = (scores <= scores.roll(1)) & (scores <= scores.roll(-1)) & (scores <= check.tolerance + radius * step)
    for index in minima.nonzero().squeeze(1)[torch.argsort(scores[minima], stable=True)][:3]:
        low, high = float(angles[index]) - step, float(angles[index]) + step
        best = float(angles[index])
        for _ in range(6):
            trial = torch.linspace(low, high, 17, dtype=torch.float64)
            best = float(trial[int(check.max_distance(flips(trial), count).argmin())])
            width = (high - low) / 16
            low, high = best - width, best + width
        flip = flips(torch.tensor([best], dtype=torch.float64))
        if bool(check.passes(flip)[0]):
            return flip[0]
    return None


def _rotation_axes(group: torch.Tensor, same: float) -> list[tuple[torch.Tensor, int]]:
    """The distinct rotation axes of ``group (K, 4)`` (axes less than ``same`` rad apart are one) with the
    order of the turns about each, highest first."""
    vectors = group[:, 1:]
    lengths = vectors.norm(dim=-1)
    axes = vectors[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    aligned = 1.0 - np.cos(same)
    result = []
    for axis in _unique_lines(axes, aligned=aligned):
        result.append((axis, 1 + int((_dot(axes, axis).abs() >= 1.0 - aligned).sum())))
    return sorted(result, key=lambda item: -item[1])


def _has_half_turn_across(group: torch.Tensor, axis: torch.Tensor, same: float) -> bool:
    """Whether ``group`` holds a half turn about an axis perpendicular to ``axis`` (within ``same`` rad)."""
    half = group[group[:, 0].abs() < np.sin(same / 2), 1:]
    return bool((_dot(half, axis).abs() < np.sin(same) * half.norm(dim=-1)).any())


def detect_symmetry(mesh: trimesh.Trimesh, tolerance: float | None = None, samples: int = 2000) -> Symmetry:
    """The rotations about the origin (the centre of mass of an object frame) that map the mesh onto itself.

    A rotation R is kept when every one of ``samples`` surface samples of R·mesh (seed 0, deterministic)
    lies within ``tolerance`` (default 1 % of the largest extent) of the original surface. Tried, in order:

    1. a continuous symmetry (surface of revolution): turns by 14.4°, 137.5° and 108.9° about each
       candidate axis (:func:`_candidate_axes`: the object's z, x, y axes, the principal axes of the
       surface's and the solid's second moments, normals of the largest facets, directions to the farthest
       vertices). The first axis that passes is the continuous axis, so a sphere-like mesh (every axis
       passes) is reported as continuous about z (not as the whole SO(3)): its discrete part is the
       identity and, when one passes, a half turn about an axis perpendicular to the continuous axis;
    2. otherwise a finite group grown from the identity: the 24 axis-permuting rotations (exact for
       axis-aligned boxes), then the turns by 360°/n, n = 12 … 2, about every candidate axis, then for a
       principal axis whose two other moments are equal (an n-gon prism) or a turn axis without a half
       turn across it, the half turns about the axes perpendicular to it (scanned: those axes are not
       principal directions). Each accepted rotation is closed under composition (q and -q are one
       element) and every new element must pass the test, with at most 60 elements.

    Returns:
        The group, identity first (then by decreasing ``|w|``), float32.

    Raises:
        InvalidMeshError: the mesh has no triangles or no extent; InvalidParameterError: ``tolerance`` is not
            a positive finite number or ``samples`` is below 16.
    """
    from pytorch_kinematics import transforms as pkt

    if len(mesh.faces) == 0 or not float(max(mesh.extents)) > 0:
        raise InvalidMeshError("cannot detect the symmetries of a mesh without triangles or extent")
    tolerance = tolerance if tolerance is not None else 0.01 * float(max(mesh.extents))
    try:
        tolerance = float(tolerance)
        samples = int(samples)
    except (TypeError, ValueError) as exc:
        raise InvalidParameterError(f"bad symmetry tolerance {tolerance!r} or sample count {samples!r}") from exc
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise InvalidParameterError(f"symmetry tolerance must be a positive finite length, got {tolerance!r}")
    if samples < 16:
        raise InvalidParameterError(f"symmetry detection needs at least 16 surface samples, got {samples}")

    check = _SurfaceCheck(mesh, samples, tolerance)
    axes, unique_axes = _candidate_axes(mesh, tolerance)
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)

    spins = _turns(axes, torch.tensor(_CONTINUOUS_TEST_ANGLES, dtype=torch.float64))
    worst = check.distances(spins.reshape(-1, 4)).reshape(spins.shape[:2]).amax(-1)
    if bool((worst <= tolerance).any()):
        # the first candidate about as exact as the best: an axis a degree off may pass too (the object's z
        # near a tilted capsule's axis), and every axis passes for a sphere, where z is kept
        axis = axes[int((worst <= float(worst.min()) + _CLOSE_ENOUGH * tolerance).nonzero()[0, 0])]
        axis = axis * torch.sign(axis[int(axis.abs().argmax())])  # its largest component positive, for reading
        across = [torch.eye(3, dtype=torch.float64)[axis.abs() < 1e-9]]  # coordinate axes across it
        across.append(axes - _dot(axes, axis)[:, None] * axis)  # the other candidates, projected across it
        across[-1] = across[-1][across[-1].norm(dim=-1) > 0.1]
        across.append(_perpendicular(axis)[0][None])
        flips = _half_turns(_unique_lines(torch.cat([a / a.norm(dim=-1, keepdim=True) for a in across])))
        flip_worst = check.distances(flips)
        passed = flips[(flip_worst <= tolerance) & (flip_worst <= float(flip_worst.min()) + _CLOSE_ENOUGH * tolerance)]
        return Symmetry(torch.cat([identity, _canonical_sign(passed[:1])]).float(), continuous_axis=axis)

    # the 24 axis-permuting turns (exact for the catalogue's boxes) and the turns by 360°/n about every
    # candidate axis, grown into a group most exact first
    cube_turns = pkt.matrix_to_quaternion(torch.as_tensor(_rotations_of_cube_group(), dtype=torch.float32))
    # exact in float64 (their components are 0, ±1/2, ±1/√2, ±1), with the signs they always had
    levels = torch.tensor([0.0, 0.5, 0.5**0.5, 1.0], dtype=torch.float64)
    nearest = (cube_turns.abs().double()[..., None] - levels).abs().argmin(-1)
    cube_turns = torch.sign(cube_turns).double() * levels[nearest]
    orders = torch.arange(_MAX_TURN_ORDER, 1, -1, dtype=torch.float64)
    group = _grow(check, identity, torch.cat([cube_turns, _turns(axes, 2 * torch.pi / orders).reshape(-1, 4)]))
    # half turns across an axis are not about principal axes when the moments in that plane are equal (an
    # n-gon prism, a cube's diagonal) and may be no facet normal either: scan for them
    scanned: list[torch.Tensor] = []
    same = check.same_angle
    for axis in [*unique_axes, *(a for a, _ in _rotation_axes(group, same))]:
        if len(scanned) == _MAX_SCANS:
            break
        known = any(abs(float(_dot(axis, other))) >= np.cos(same) for other in scanned)
        if known or _has_half_turn_across(group, axis, same):
            continue
        scanned.append(axis)
        order = next((m for a, m in _rotation_axes(group, same) if abs(float(_dot(a, axis))) >= np.cos(same)), 1)
        flip = _scan_half_turns(check, axis, np.pi / order)
        if flip is not None:
            group = _grow(check, group, flip[None])

    # identity first, for readability of saved files and logs; axis-permuting elements in the order (and
    # with the signs) of _rotations_of_cube_group, so an axis-aligned shape's group reads as it always has
    aligned = _same_rotation(group, cube_turns, 1e-6)  # the very same rotation only
    group = torch.where(aligned.any(-1, keepdim=True), cube_turns[aligned.to(torch.int64).argmax(-1)], group)
    rank = torch.where(aligned.any(-1), aligned.to(torch.int64).argmax(-1), len(cube_turns) + torch.arange(len(group)))
    group = group[torch.argsort(rank, stable=True)].float()
    group = group[torch.argsort(-group[:, 0].abs(), stable=True)]
    return Symmetry(group.contiguous())
