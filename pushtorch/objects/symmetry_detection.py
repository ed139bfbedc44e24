"""Detection of an object's visual symmetries Q_gt from its mesh (paper, Prediction Accuracy Measure, Eq. pam).

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
most 60 elements) and held as a :class:`~pushtorch.objects.symmetry.Symmetry`: discrete rotations plus, for a
surface of revolution, the continuous axis (any direction in the object frame), both handled exactly by the
accuracy measure.
Limits: an n-fold turn with n > 12 is found only as a continuous symmetry (when the n-gon is round within
the tolerance) or through two half turns; a sphere-like mesh is reported as continuous about z plus a half
turn, not as every rotation.

The quaternion arithmetic the group is grown with (products, closure, axes, half turns) is
:mod:`~pushtorch.objects.rotation_groups`.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from pushtorch.errors import InvalidMeshError, InvalidParameterError
from pushtorch.objects.rotation_groups import (
    SAME_ROTATION,
    canonical_sign,
    closure,
    dot,
    half_turns,
    has_half_turn_across,
    perpendicular,
    rotation_axes,
    rotations_of_cube_group,
    same_rotation,
    turns,
    unique_lines,
)
from pushtorch.objects.symmetry import Symmetry

__all__ = ["detect_symmetry"]

#: Highest order of a discrete turn looked for about each candidate axis (360°/2 ... 360°/12).
_MAX_TURN_ORDER = 12
#: Turns (rad) a surface of revolution must survive about its axis: 14.4° (at least 14.4° from every multiple
#: of 360°/n, n <= 12, so no n-gon prism of such an order passes), the golden angle 137.5° and 108.9°.
_CONTINUOUS_TEST_ANGLES = (2 * np.pi / 25, np.pi * (3 - np.sqrt(5)), 1.9)
#: Rotations less apart than the angle that moves no surface point by more than the tolerance are one group
#: element too, when that angle is above :data:`~pushtorch.objects.rotation_groups.SAME_ROTATION` (a noisy
#: mesh's symmetries compose into near copies of each other), up to this angle (rad; distinct elements of a
#: group of at most 60 are 6° apart at least).
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
        #: rotations closer than this are one group element (see SAME_ROTATION)
        self.same_angle = float(np.clip(self.tolerance / max(self.radius, 1e-12), SAME_ROTATION, _SAME_ROTATION_MAX))
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
        moved = dot(mats[:, None, :, :], points[None, :, None, :]).reshape(-1, 3).numpy().astype(np.float32)
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
        u, v = perpendicular(axis)
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
    exceeds :data:`MAX_GROUP_ORDER` elements (a near symmetry composing into ever new rotations), is left out.
    """
    if len(generators) == 0:
        return group
    same = check.same_angle
    generators = generators[~same_rotation(generators, group, same).any(-1)]
    if len(generators) == 0:
        return group
    worst = check.distances(generators)
    order = torch.argsort(worst, stable=True)[: int((worst <= check.tolerance).sum())]
    # the most exact first: a near symmetry (a principal axis a few tenths of a degree off, say) would
    # otherwise shut out the exact one it approximates; one that is only near is polished first
    for generator, distance in zip(generators[order], worst[order].tolist(), strict=True):
        if distance > _EXACT * check.tolerance:
            generator = _polish(check, generator, distance)
        if bool(same_rotation(generator[None], group, same).any()):
            continue
        bigger = closure(torch.cat([group, canonical_sign(generator[None])]), same=same)
        if bigger is not None and bool(check.passes(bigger[len(group):]).all()):
            group = bigger
    return group


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
    flats = unique_lines(torch.as_tensor(normals[keep][order], dtype=torch.float64), _EXTRA_AXES)
    # each the area-weighted mean of the face normals within 10° of it (either way): a flat side's true
    # normal even when it is noisy (a scan) or split into faces that are not quite coplanar
    face_normals = torch.tensor(np.asarray(mesh.face_normals), dtype=torch.float64)
    face_areas = torch.tensor(np.asarray(mesh.area_faces), dtype=torch.float64)
    if len(flats):
        cosines = dot(face_normals[:, None, :], flats[None, :, :])  # (F, L)
        weights = torch.where(cosines.abs() >= np.cos(np.radians(10.0)), torch.sign(cosines), 0.0) * face_areas[:, None]
        means = (weights[:, :, None] * face_normals[:, None, :]).sum(0)
        lengths = means.norm(dim=-1, keepdim=True)
        flats = torch.where(lengths > 0, means / lengths.clamp_min(1e-300), flats)
    found.append(flats)
    vertices = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    radii = vertices.norm(dim=-1)
    far = torch.argsort(-radii, stable=True)
    far = far[radii[far] >= float(radii.max()) - tolerance]
    found.append(unique_lines(vertices[far] / radii[far, None].clamp_min(1e-300), _EXTRA_AXES))
    unique_principal = unique_lines(torch.stack(unique)) if unique else torch.zeros(0, 3, dtype=torch.float64)
    return unique_lines(torch.cat(found)), list(unique_principal)


def _scan_half_turns(check: _SurfaceCheck, axis: torch.Tensor, period: float) -> torch.Tensor | None:
    """A half turn about an axis perpendicular to ``axis`` that maps the mesh onto itself, or ``None``.

    Such half turns repeat every ``period`` (π/m with an m-fold turn about ``axis``). Their angle in the plane
    is scanned in steps that move no sample by more than the tolerance, scored on 256 samples; the best local
    minima are refined by zooming in, then tested in full.
    """
    u, v = perpendicular(axis)
    radius = max(check.radius, 1e-12)
    steps = int(min(1024, max(16, np.ceil(period * radius / check.tolerance))))
    step = period / steps

    def flips(angles: torch.Tensor) -> torch.Tensor:
        return half_turns(torch.cos(angles)[:, None] * u + torch.sin(angles)[:, None] * v)

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

    spins = turns(axes, torch.tensor(_CONTINUOUS_TEST_ANGLES, dtype=torch.float64))
    worst = check.distances(spins.reshape(-1, 4)).reshape(spins.shape[:2]).amax(-1)
    if bool((worst <= tolerance).any()):
        # the first candidate about as exact as the best: an axis a degree off may pass too (the object's z
        # near a tilted capsule's axis), and every axis passes for a sphere, where z is kept
        axis = axes[int((worst <= float(worst.min()) + _CLOSE_ENOUGH * tolerance).nonzero()[0, 0])]
        axis = axis * torch.sign(axis[int(axis.abs().argmax())])  # its largest component positive, for reading
        across = [torch.eye(3, dtype=torch.float64)[axis.abs() < 1e-9]]  # coordinate axes across it
        across.append(axes - dot(axes, axis)[:, None] * axis)  # the other candidates, projected across it
        across[-1] = across[-1][across[-1].norm(dim=-1) > 0.1]
        across.append(perpendicular(axis)[0][None])
        flips = half_turns(unique_lines(torch.cat([a / a.norm(dim=-1, keepdim=True) for a in across])))
        flip_worst = check.distances(flips)
        passed = flips[(flip_worst <= tolerance) & (flip_worst <= float(flip_worst.min()) + _CLOSE_ENOUGH * tolerance)]
        return Symmetry(torch.cat([identity, canonical_sign(passed[:1])]).float(), continuous_axis=axis)

    # the 24 axis-permuting turns (exact for the catalogue's boxes) and the turns by 360°/n about every
    # candidate axis, grown into a group most exact first
    cube_turns = pkt.matrix_to_quaternion(torch.as_tensor(rotations_of_cube_group(), dtype=torch.float32))
    # exact in float64 (their components are 0, ±1/2, ±1/√2, ±1), with the signs they always had
    levels = torch.tensor([0.0, 0.5, 0.5**0.5, 1.0], dtype=torch.float64)
    nearest = (cube_turns.abs().double()[..., None] - levels).abs().argmin(-1)
    cube_turns = torch.sign(cube_turns).double() * levels[nearest]
    orders = torch.arange(_MAX_TURN_ORDER, 1, -1, dtype=torch.float64)
    group = _grow(check, identity, torch.cat([cube_turns, turns(axes, 2 * torch.pi / orders).reshape(-1, 4)]))
    # half turns across an axis are not about principal axes when the moments in that plane are equal (an
    # n-gon prism, a cube's diagonal) and may be no facet normal either: scan for them
    scanned: list[torch.Tensor] = []
    same = check.same_angle
    for axis in [*unique_axes, *(a for a, _ in rotation_axes(group, same))]:
        if len(scanned) == _MAX_SCANS:
            break
        known = any(abs(float(dot(axis, other))) >= np.cos(same) for other in scanned)
        if known or has_half_turn_across(group, axis, same):
            continue
        scanned.append(axis)
        order = next((m for a, m in rotation_axes(group, same) if abs(float(dot(a, axis))) >= np.cos(same)), 1)
        flip = _scan_half_turns(check, axis, np.pi / order)
        if flip is not None:
            group = _grow(check, group, flip[None])

    # identity first, for readability of saved files and logs; axis-permuting elements in the order (and
    # with the signs) of rotations_of_cube_group, so an axis-aligned shape's group reads as it always has
    aligned = same_rotation(group, cube_turns, 1e-6)  # the very same rotation only
    group = torch.where(aligned.any(-1, keepdim=True), cube_turns[aligned.to(torch.int64).argmax(-1)], group)
    rank = torch.where(aligned.any(-1), aligned.to(torch.int64).argmax(-1), len(cube_turns) + torch.arange(len(group)))
    group = group[torch.argsort(rank, stable=True)].float()
    group = group[torch.argsort(-group[:, 0].abs(), stable=True)]
    return Symmetry(group.contiguous())
