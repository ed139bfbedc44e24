"""Finite groups of rotations as unit quaternions: products, closure, sign-canonical elements, axes and half turns.

Paper, Prediction Accuracy Measure (Eq. pam): the visually identical orientations Q_gt of an object form a group
(:class:`~pushtorch.objects.symmetry.Symmetry`); this is the arithmetic that
:func:`~pushtorch.objects.symmetry_detection.detect_symmetry` grows one from. Quaternions are wxyz and ``q`` and
``-q`` are one rotation (one group element); a group has at most :data:`MAX_GROUP_ORDER` elements. Everything
is in float64 where exactness matters (sameness of rotations).
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

__all__ = [
    "ALIGNED",
    "MAX_GROUP_ORDER",
    "SAME_ROTATION",
    "canonical_sign",
    "closure",
    "dot",
    "half_turns",
    "has_half_turn_across",
    "perpendicular",
    "rotation_axes",
    "rotations_of_cube_group",
    "same_rotation",
    "turns",
    "unique_lines",
]

#: Two unit axes are the same line when ``|a·b| >= 1 - ALIGNED`` (also: an axis "is" z).
ALIGNED = 1e-6
#: Largest finite group kept: the icosahedral group (60) is the largest with turns of order <= 12.
MAX_GROUP_ORDER = 60
#: Two rotations less than this angle (rad) apart are one group element (the default of :func:`same_rotation`
#: and :func:`closure`; symmetry detection widens it for a noisy mesh, see
#: :mod:`~pushtorch.objects.symmetry_detection`).
SAME_ROTATION = 1e-3


def rotations_of_cube_group() -> np.ndarray:
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


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a * b).sum(-1)`` with broadcasting. Elementwise on purpose: these products are tiny, and a BLAS
    matrix product of a few rows can cost milliseconds when its threads wait for a busy CPU."""
    return (a * b).sum(-1)


def turns(axes: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(A, B, 4)`` of the turns by each of ``angles (B,)`` about each unit axis of ``axes (A, 3)``."""
    from pytorch_kinematics import transforms as pkt

    return pkt.axis_angle_to_quaternion(axes[:, None, :] * angles[None, :, None])


def _left_matrices(q: torch.Tensor) -> torch.Tensor:
    """``(K, 4, 4)`` matrices ``L(q)`` with ``q ⊗ p = L(q) p`` (wxyz), for ``q (K, 4)``."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([w, -x, -y, -z, x, w, -z, y, y, z, w, -x, z, -y, x, w], -1).reshape(-1, 4, 4)


def _products(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """All products ``a_i ⊗ b_j``, ``(P, K, 4)``, of ``a (P, 4)`` and ``b (K, 4)`` (one matrix product)."""
    return dot(_left_matrices(a)[:, None, :, :], b[None, :, None, :])


def same_rotation(a: torch.Tensor, b: torch.Tensor, angle: float = SAME_ROTATION) -> torch.Tensor:
    """``(P, K)`` bool: is ``a_i (P, 4)`` the same rotation as ``b_j (K, 4)`` (``q`` and ``-q`` alike), that is
    less than ``angle`` apart: ``|<a, b>| = cos(angle / 2)``, exact enough in float64."""
    return dot(a.to(torch.float64)[:, None, :], b.to(torch.float64)[None, :, :]).abs() >= np.cos(angle / 2)


def canonical_sign(quats: torch.Tensor) -> torch.Tensor:
    """``quats (K, 4)`` with ``w > 0``, or for half turns (``w = 0``) the first non-zero component positive."""
    significant = quats.abs() > 1e-9
    first = torch.where(significant.any(-1), significant.to(torch.int64).argmax(-1), 0)
    sign = torch.sign(quats.gather(-1, first[:, None]))
    return quats * torch.where(sign == 0, 1.0, sign).to(quats)


def _new_elements(candidates: torch.Tensor, group: torch.Tensor, room: int, same: float) -> torch.Tensor | None:
    """The distinct rotations among ``candidates (P, 4)`` not in ``group (K, 4)``, sign-canonical, in order of
    first occurrence; ``None`` when there are more than ``room``. Rotations less than ``same`` apart are one."""
    candidates = candidates[~same_rotation(candidates, group, same).any(-1)]
    kept = []
    while len(candidates):  # one pass per distinct new rotation, at most room + 1
        if len(kept) >= room:
            return None
        kept.append(candidates[0])
        candidates = candidates[~same_rotation(candidates, candidates[:1], same)[:, 0]]
    return canonical_sign(torch.stack(kept)) if kept else candidates


def closure(group: torch.Tensor, limit: int = MAX_GROUP_ORDER, same: float = SAME_ROTATION) -> torch.Tensor | None:
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


def unique_lines(directions: torch.Tensor, limit: int | None = None, aligned: float = ALIGNED) -> torch.Tensor:
    """The first ``limit`` distinct lines (``a`` and ``-a`` alike, the same when ``|a·b| >= 1 - aligned``) among
    unit ``directions (N, 3)``, in order."""
    directions = directions[directions.norm(dim=-1) > 0.5]
    kept = []
    while len(directions) and (limit is None or len(kept) < limit):  # one pass per line kept
        kept.append(directions[0])
        directions = directions[dot(directions, directions[0]).abs() < 1.0 - aligned]
    return torch.stack(kept) if kept else directions


def perpendicular(axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors ``u, v`` with ``(u, v, axis)`` right-handed and orthonormal (``u`` from the coordinate
    axis least aligned with ``axis``)."""
    basis = torch.eye(3, dtype=axis.dtype)[int(axis.abs().argmin())]
    u = basis - dot(basis, axis) * axis
    u = u / u.norm()
    return u, torch.linalg.cross(axis, u)


def half_turns(axes: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(A, 4)`` of the half turns about unit ``axes (A, 3)``: ``(0, a)``."""
    return torch.cat([torch.zeros(len(axes), 1, dtype=axes.dtype), axes], -1)


def rotation_axes(group: torch.Tensor, same: float) -> list[tuple[torch.Tensor, int]]:
    """The distinct rotation axes of ``group (K, 4)`` (axes less than ``same`` rad apart are one) with the
    order of the turns about each, highest first."""
    vectors = group[:, 1:]
    lengths = vectors.norm(dim=-1)
    axes = vectors[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    aligned = 1.0 - np.cos(same)
    result = []
    for axis in unique_lines(axes, aligned=aligned):
        result.append((axis, 1 + int((dot(axes, axis).abs() >= 1.0 - aligned).sum())))
    return sorted(result, key=lambda item: -item[1])


def has_half_turn_across(group: torch.Tensor, axis: torch.Tensor, same: float) -> bool:
    """Whether ``group`` holds a half turn about an axis perpendicular to ``axis`` (within ``same`` rad)."""
    half = group[group[:, 0].abs() < np.sin(same / 2), 1:]
    return bool((dot(half, axis).abs() < np.sin(same) * half.norm(dim=-1)).any())
