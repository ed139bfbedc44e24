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


def _z_flip_symmetry() -> Symmetry:
    """Identity and a half turn about x, combined with any rotation about z (a cylinder)."""
    return Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]), continuous_axis=torch.tensor(_Z_AXIS))


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
    """The catalogue's object names, in the paper's order."""
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


def _check_up(up: str) -> str:
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
            cache_dir: str | Path | None) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh], str]:
    """A mesh of several connected parts as one body: its watertight union (centred at its centre of mass),
    its convex collision parts and their ``collision_source`` (module docstring).

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
    mesh, solids = _centred(union, solids)
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
    return mesh, collision, "convex parts and v-hacd" if decomposed else "convex parts"


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

    up = _check_up(up)
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
        mesh, parts, source = _joined(path, vertices * scale, np.asarray(loaded.faces), mesh, cache_dir)
        return ObjectModel(name, mesh, detect_symmetry(mesh), parts, source)
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
                cache_dir: str | Path | None = None, up: str = "z") -> ObjectModel:
    """A catalogue object by name, or a user mesh when ``name == "mesh"`` (``path``, ``scale``, the folder
    ``cache_dir`` that keeps a concave mesh's decomposition and the file's ``up`` axis, see
    :func:`load_mesh_file`; a catalogue object ignores ``up``, which is checked all the same).

    Raises:
        InvalidParameterError: unknown catalogue name, object=mesh without a path, or ``up`` not one of
            :data:`UP_AXES`.
        InvalidMeshError: a mesh :func:`load_mesh_file` refuses.
    """
    _check_up(up)
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
