"""Visual symmetries Q_gt of an object, held as a group: which rotations leave it looking the same (paper,
Prediction Accuracy Measure, Eq. pam).

A :class:`Symmetry` holds discrete rotations plus, for a surface of revolution, a continuous axis (any direction
in the object frame), and gives Eq. pam's angular term over the whole group in closed form: the nearest
visually identical orientation, exactly, with no sampling of the continuous part. The group of a mesh is found
by :func:`~pushtorch.objects.symmetry_detection.detect_symmetry` (the catalogue's cylinders have theirs written
down); the quaternion group arithmetic is :mod:`~pushtorch.objects.rotation_groups`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pushtorch.errors import InvalidParameterError
from pushtorch.objects.rotation_groups import ALIGNED

__all__ = ["Symmetry"]

_Z_AXIS = (0.0, 0.0, 1.0)


@dataclass(frozen=True, init=False)
class Symmetry:
    """Orientations that look the same: ``q ⊗ s`` for each ``s`` in the group, exactly.

    Attributes:
        discrete: ``(K, 4)`` wxyz quaternions, identity included (first, as
            :func:`~pushtorch.objects.symmetry_detection.detect_symmetry` makes it).
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
            if axis is not None and abs(float(axis[2])) < 1.0 - ALIGNED:
                raise InvalidParameterError(f"continuous_z=True contradicts continuous_axis={axis.tolist()}")
            axis = torch.tensor(_Z_AXIS, dtype=torch.float32)
        object.__setattr__(self, "discrete", discrete)
        object.__setattr__(self, "continuous_axis", axis)

    @property
    def continuous_z(self) -> bool:
        """True when the object is invariant to any rotation about its own z axis (a cylinder standing up)."""
        return self.continuous_axis is not None and abs(float(self.continuous_axis[2])) >= 1.0 - ALIGNED

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
