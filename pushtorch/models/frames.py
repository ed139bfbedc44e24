"""Contact and position frames ``c = (v, r, u)``: the shared currency of every model (paper, §TPMM).

Paper, Rigid Body Motions: a contact frame is ``c = (v, r, u)`` — the pose ``v`` and descriptor ``r`` of
the surface feature it stands on, and a relative pose ``u`` to the entity it relates to (the robot for a
manipulator contact ``c^m``, the floor for an environment contact ``c^e``, the object's origin for a
position frame ``c^p``). Composition order (docs/method.md): ``v ∘ u`` is the related entity's pose in
the world, i.e. ``u = v⁻¹ ∘ entity`` — the paper's "kernels positioned at u ∘ v" in its own notation.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pushtorch import se3

Tensor = torch.Tensor

__all__ = ["DESCRIPTOR_SCALE", "ContactFrames", "embed_descriptors"]

#: Curvature (m⁻¹) at which descriptor comparison turns from linear to logarithmic.
DESCRIPTOR_SCALE = 5.0


def embed_descriptors(r: Tensor, scale: float = DESCRIPTOR_SCALE) -> Tensor:
    """Map principal curvatures to the space in which kernels compare them: ``asinh(r / scale)``.

    Curvatures span three orders of magnitude: ~0 on faces, 10 on a 0.1 m cylinder, 50–300 m⁻¹ near
    edges and creases (their value depends on how far the point is from the crease). A Gaussian with
    one bandwidth cannot both tell 0 from 10 and match 150 with 250. ``asinh`` is linear below
    ``scale`` and logarithmic above it, so one bandwidth does both (docs/method.md). Sign is kept:
    concave creases stay distinct from convex edges.
    """
    return torch.asinh(r / scale)


@dataclass
class ContactFrames:
    """A batch of frames ``(..., N)``: surface poses ``v``, descriptors ``r``, relations ``u``, weights.

    Attributes:
        v: surface-feature poses in the world, ``p (..., N, 3)``, ``q (..., N, 4)``.
        r: descriptors ``(..., N, 2)`` (principal curvatures, m⁻¹).
        u: relative poses ``v⁻¹ ∘ entity`` ``(..., N)``.
        weight: non-negative, unnormalised ``(..., N)``.
    """

    v: se3.Pose
    r: Tensor
    u: se3.Pose
    weight: Tensor

    def __len__(self) -> int:
        return int(self.r.shape[-2])

    @property
    def entity(self) -> se3.Pose:
        """Pose of the related entity implied by each frame: ``v ∘ u``."""
        return se3.compose(self.v, self.u)

    def select(self, index) -> ContactFrames:
        """Frames at ``index`` of the last batch dim (a tensor of indices or a mask)."""
        return ContactFrames(
            se3.Pose.unchecked(self.v.p[..., index, :], self.v.q[..., index, :]),
            self.r[..., index, :],
            se3.Pose.unchecked(self.u.p[..., index, :], self.u.q[..., index, :]),
            self.weight[..., index],
        )

    @staticmethod
    def stack(frames: list[ContactFrames]) -> ContactFrames:
        """Frames of the same count stacked along a new leading dim ``(len(frames), ..., N)``."""
        return ContactFrames(se3.Pose.stack([f.v for f in frames]), torch.stack([f.r for f in frames]),
                             se3.Pose.stack([f.u for f in frames]), torch.stack([f.weight for f in frames]))

    def expand(self, count: int) -> ContactFrames:
        """These ``(N,)`` frames repeated (a view) along a new leading dim: ``(count, N)``."""
        n = len(self)
        return ContactFrames(self.v.expand(count, n), self.r.expand(count, n, 2), self.u.expand(count, n),
                             self.weight.expand(count, n))

    def to(self, *args, **kwargs) -> ContactFrames:
        return ContactFrames(
            self.v.to(*args, **kwargs), self.r.to(*args, **kwargs), self.u.to(*args, **kwargs),
            self.weight.to(*args, **kwargs),
        )

    def transformed(self, pose: se3.Pose) -> ContactFrames:
        """The same frames after moving the object they stand on by ``pose`` (``u`` is local: unchanged)."""
        return ContactFrames(se3.compose(pose, self.v), self.r, self.u, self.weight)

    def arrays(self, prefix: str) -> dict[str, Tensor]:
        """Flat tensors for a model file."""
        return {
            f"{prefix}.v_p": self.v.p, f"{prefix}.v_q": self.v.q, f"{prefix}.r": self.r,
            f"{prefix}.u_p": self.u.p, f"{prefix}.u_q": self.u.q, f"{prefix}.weight": self.weight,
        }

    @staticmethod
    def from_arrays(arrays: dict[str, Tensor], prefix: str) -> ContactFrames:
        return ContactFrames(
            se3.Pose.unchecked(arrays[f"{prefix}.v_p"], arrays[f"{prefix}.v_q"]),
            arrays[f"{prefix}.r"],
            se3.Pose.unchecked(arrays[f"{prefix}.u_p"], arrays[f"{prefix}.u_q"]),
            arrays[f"{prefix}.weight"],
        )
