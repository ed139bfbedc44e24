"""Batched rigid transforms in SE(3): poses v = (p, q), their group operations, distances and samplers.

Paper, Background (Surface Features, Rigid Body Motions): every pose v = (p, q) in SE(3), the inverse
v^-1 = (-q^-1 p, q^-1) and the composition operator used in h = v^-1 ∘ B^O; the quaternion distance
1 - |<q1, q2>| of the kernels (Kernel Density Estimation) and the perturbations of simulated annealing.

Conventions (the whole library):
    * ``p`` has shape ``(..., 3)`` in metres, ``q`` has shape ``(..., 4)``, unit, **w, x, y, z** order,
      the same as ``pytorch_kinematics.transforms``. Leading ``...`` batch dims broadcast.
    * ``compose(a, b)`` is ``a ∘ b``: first ``b`` then ``a`` (``T_a @ T_b`` as 4x4 matrices), so
      ``apply(compose(a, b), x) == apply(a, apply(b, x))``.
    * q and -q are the same rotation: every distance here is invariant to the sign.
    * pybullet and Rerun use x, y, z, w: convert only at those boundaries with :func:`wxyz_to_xyzw`.
    * The group operations (:func:`compose`, :func:`apply`, ...) assume unit quaternions and do not check
      them: they run inside every hot loop (a non-unit q scales, ``apply`` with |q| = 2 maps (1, 0, 0) to
      (4, 0, 0)). Public entries that take poses from a caller validate them once with
      :func:`check_pose` / :func:`check_unit_quaternion`, following ``torch.distributions``'
      ``validate_args`` convention: checks on by default, turned off only for the annealing's own queries.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidPoseError

Tensor = torch.Tensor

__all__ = [
    "Pose",
    "angle_between",
    "apply",
    "check_pose",
    "check_unit_quaternion",
    "compose",
    "from_matrix",
    "from_pybullet",
    "from_xy_yaw",
    "identity",
    "inverse",
    "mean_pose",
    "perturb",
    "quat_distance",
    "quat_normalize",
    "random_quaternion",
    "relative",
    "random_normal",
    "random_uniform",
    "sample_vmf_quaternion",
    "to_matrix",
    "to_pybullet",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
    "yaw_of",
    "yaw_quaternion",
]


class Pose(NamedTuple):
    """A batch of rigid poses: translation ``p (..., 3)`` and unit quaternion ``q (..., 4)`` wxyz.

    A ``NamedTuple`` so that it unpacks as ``p, q = pose`` and crosses process boundaries cheaply;
    the methods are thin wrappers of the module functions of the same name.
    """

    p: Tensor
    q: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        return torch.broadcast_shapes(self.p.shape[:-1], self.q.shape[:-1])

    def compose(self, other: Pose) -> Pose:
        return compose(self, other)

    def inverse(self) -> Pose:
        return inverse(self)

    def apply(self, points: Tensor) -> Tensor:
        return apply(self, points)

    def to(self, *args, **kwargs) -> Pose:
        return Pose(self.p.to(*args, **kwargs), self.q.to(*args, **kwargs))

    def take(self, index) -> Pose:
        """Index the batch dims, e.g. ``pose.take(0)`` or ``pose.take(mask)``."""
        shape = self.batch_shape
        return Pose(self.p.expand(*shape, 3)[index], self.q.expand(*shape, 4)[index])

    def expand(self, *shape: int) -> Pose:
        return Pose(self.p.expand(*shape, 3), self.q.expand(*shape, 4))

    def reshape(self, *shape: int) -> Pose:
        full = self.batch_shape
        return Pose(self.p.expand(*full, 3).reshape(*shape, 3), self.q.expand(*full, 4).reshape(*shape, 4))

    def unsqueeze(self, dim: int) -> Pose:
        """Insert a batch dim (``dim`` counts batch dims only; negative counts from the last one)."""
        d = dim if dim >= 0 else dim - 1
        return Pose(self.p.unsqueeze(d), self.q.unsqueeze(d))

    def vector(self) -> Tensor:
        """``(..., 7)`` as ``[p, q_wxyz]``: the event layout of a prediction's distribution."""
        shape = self.batch_shape
        return torch.cat([self.p.expand(*shape, 3), self.q.expand(*shape, 4)], -1)

    @staticmethod
    def from_vector(x: Tensor) -> Pose:
        """The pose ``(...)`` of ``[p, q_wxyz]`` vectors ``(..., 7)`` (views, no copy)."""
        if x.shape[-1:] != (7,):
            raise InvalidPoseError(f"pose vectors must have shape (..., 7) as [p, q_wxyz], got {tuple(x.shape)}")
        return Pose(x[..., :3], x[..., 3:])

    @staticmethod
    def cat(poses: list[Pose], dim: int = 0) -> Pose:
        d = dim if dim >= 0 else dim - 1
        return Pose(torch.cat([x.p for x in poses], d), torch.cat([x.q for x in poses], d))

    @staticmethod
    def stack(poses: list[Pose], dim: int = 0) -> Pose:
        d = dim if dim >= 0 else dim - 1
        return Pose(torch.stack([x.p for x in poses], d), torch.stack([x.q for x in poses], d))


def identity(shape: tuple[int, ...] = (), dtype: torch.dtype = torch.float32, device=None) -> Pose:
    """The identity pose with batch shape ``shape``."""
    p = torch.zeros(*shape, 3, dtype=dtype, device=device)
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return Pose(p, q)


def quat_normalize(q: Tensor) -> Tensor:
    """Scale quaternions ``(..., 4)`` to unit length; raise on a zero or non-finite quaternion."""
    norm = q.norm(dim=-1, keepdim=True)
    if not torch.isfinite(q).all():
        raise InvalidPoseError("quaternion has NaN or infinite entries")
    if (norm < 1e-12).any():
        raise InvalidPoseError("quaternion of zero length cannot be normalised")
    return q / norm


def check_unit_quaternion(q: Tensor, atol: float = 1e-3, name: str = "q") -> Tensor:
    """Return ``q`` if every ``(..., 4)`` row is finite and unit length within ``atol``, else raise.

    Raises:
        InvalidPoseError: wrong trailing size, NaN/inf entries, or a norm further than ``atol`` from 1.
    """
    if q.shape[-1:] != (4,):
        raise InvalidPoseError(f"{name} must have shape (..., 4) in w,x,y,z order, got {tuple(q.shape)}")
    if not torch.isfinite(q).all():
        raise InvalidPoseError(f"{name} has NaN or infinite entries")
    err = (q.norm(dim=-1) - 1.0).abs()
    if q.numel() and err.max() > atol:
        raise InvalidPoseError(
            f"{name} must be a unit quaternion (w,x,y,z); worst norm is off by {err.max().item():.3g}"
        )
    return q


def check_pose(pose: Pose, name: str = "pose", atol: float = 1e-3) -> Pose:
    """Return ``pose`` if ``p (..., 3)`` is finite and ``q (..., 4)`` unit within ``atol``, else raise.

    Raises:
        InvalidPoseError: not a pair of floating tensors, wrong trailing sizes, NaN/inf, or a non-unit q.
    """
    if not (isinstance(pose, tuple) and len(pose) == 2 and all(isinstance(t, Tensor) for t in pose)):
        raise InvalidPoseError(f"{name} must be a Pose of two tensors (p, q), got {type(pose).__name__}")
    if not (pose.p.is_floating_point() and pose.q.is_floating_point()):
        raise InvalidPoseError(f"{name} must hold floating-point tensors, got {pose.p.dtype} and {pose.q.dtype}")
    if pose.p.shape[-1:] != (3,):
        raise InvalidPoseError(f"{name}.p must have shape (..., 3), got {tuple(pose.p.shape)}")
    if not torch.isfinite(pose.p).all():
        raise InvalidPoseError(f"{name}.p has NaN or infinite entries")
    check_unit_quaternion(pose.q, atol=atol, name=f"{name}.q")
    return pose


_check_pose = check_pose  # the former private name


def compose(a: Pose, b: Pose) -> Pose:
    """``a ∘ b``: the pose of frame b expressed through a (``T_a @ T_b``). Batch dims broadcast."""
    return Pose(a.p + pkt.quaternion_apply(a.q, b.p), pkt.quaternion_raw_multiply(a.q, b.q))


def inverse(a: Pose) -> Pose:
    """``a^-1 = (-q^-1 p, q^-1)`` (paper, Rigid Body Motions)."""
    q_inv = pkt.quaternion_invert(a.q)
    return Pose(-pkt.quaternion_apply(q_inv, a.p), q_inv)


def relative(a: Pose, b: Pose) -> Pose:
    """``a^-1 ∘ b``: the pose of b in the frame of a (the paper's h = v^-1 ∘ B^O with a=v, b=B^O)."""
    return compose(inverse(a), b)


def apply(a: Pose, points: Tensor) -> Tensor:
    """Transform points ``(..., 3)`` by poses ``a``; batch dims broadcast."""
    return a.p + pkt.quaternion_apply(a.q, points)


def quat_distance(q1: Tensor, q2: Tensor) -> Tensor:
    """``1 - |<q1, q2>|`` in [0, 1]: 0 for the same rotation, sign-invariant (paper, d_q)."""
    return 1.0 - (q1 * q2).sum(-1).abs().clamp(max=1.0)


def angle_between(q1: Tensor, q2: Tensor) -> Tensor:
    """Geodesic angle in radians, in [0, pi], between the rotations q1 and q2 (sign-invariant).

    ``2 atan2(|v|, |w|)`` of the relative rotation ``q1⁻¹ q2 = (w, v)``: exact near 0, where ``2 acos|<q1, q2>|``
    loses half the float digits and its gradient grows without bound (about 5e3 a few µrad from 0).
    """
    q1, q2 = torch.broadcast_tensors(q1, q2)
    relative = pkt.quaternion_raw_multiply(pkt.quaternion_invert(q1), q2)
    return 2.0 * torch.atan2(relative[..., 1:].norm(dim=-1), relative[..., 0].abs())


#: dtype of every normal and uniform draw (cast to the caller's dtype afterwards): torch's samplers draw a
#: different stream per dtype, and a float64 copy of a model must predict what the float32 one does.
DRAW_DTYPE = torch.float32


def random_normal(shape, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                  device=None) -> Tensor:
    """Standard normal draws of ``shape``, the same numbers for every floating ``dtype``
    (:data:`DRAW_DTYPE`)."""
    return torch.randn(shape, generator=generator, dtype=DRAW_DTYPE, device=device).to(dtype)


def random_uniform(shape, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                   device=None) -> Tensor:
    """Uniform draws on [0, 1) of ``shape``, the same numbers for every floating ``dtype``
    (:data:`DRAW_DTYPE`)."""
    return torch.rand(shape, generator=generator, dtype=DRAW_DTYPE, device=device).to(dtype)


def random_quaternion(
    shape: tuple[int, ...] | torch.Size,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device=None,
) -> Tensor:
    """Rotations uniform on SO(3) (normalised 4-D Gaussians), shape ``(*shape, 4)``, w >= 0."""
    g = random_normal((*shape, 4), generator, dtype, device)
    g = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(g[..., :1] < 0, -g, g)


def sample_vmf_quaternion(
    mean: Tensor,
    kappa: float | Tensor,
    generator: torch.Generator | None = None,
    max_rounds: int = 64,
) -> Tensor:
    """Sample unit quaternions from a von Mises–Fisher density on S^3 around ``mean (..., 4)``.

    Wood's (1994) rejection sampler, vectorised: every row draws in parallel and only the rejected
    ones draw again. ``kappa`` (scalar or broadcastable to ``mean.shape[:-1]``) is the concentration;
    the angular spread is about ``1/sqrt(kappa)`` rad per axis for large kappa, kappa = 0 is uniform.
    Because q and -q are one rotation, this is also a sample of the antipodal pair Θ of the paper.
    """
    shape = mean.shape[:-1]
    dtype, device = mean.dtype, mean.device
    kappa_t = torch.as_tensor(kappa, dtype=torch.float64, device=device).expand(shape).clone()
    if (kappa_t < 0).any() or not torch.isfinite(kappa_t).all():
        raise InvalidPoseError("vMF concentration kappa must be finite and >= 0")
    dim_m1 = 3.0  # d - 1 with d = 4
    # b written in the cancellation-free form (d-1) / (2k + sqrt(4k^2 + (d-1)^2)).
    b = dim_m1 / (2 * kappa_t + torch.sqrt(4 * kappa_t**2 + dim_m1**2))
    x0 = (1 - b) / (1 + b)
    c = kappa_t * x0 + dim_m1 * torch.log1p(-x0 * x0)
    w = torch.empty(shape, dtype=torch.float64, device=device)
    pending = torch.ones(shape, dtype=torch.bool, device=device)
    for _ in range(max_rounds):
        n = int(pending.sum())
        if n == 0:
            break
        z = _beta_1p5(n, generator, device)
        bb, xx, cc, kk = b[pending], x0[pending], c[pending], kappa_t[pending]
        w_try = (1 - (1 + bb) * z) / (1 - (1 - bb) * z)
        u = torch.rand(n, generator=generator, dtype=torch.float64, device=device)
        ok = kk * w_try + dim_m1 * torch.log1p(-xx * w_try) - cc >= torch.log(u)
        idx = pending.nonzero(as_tuple=True)
        w[tuple(i[ok] for i in idx)] = w_try[ok]
        pending[tuple(i[ok] for i in idx)] = False
    if pending.any():  # acceptance is > 50 % for every kappa: reaching here means a broken generator
        w[pending] = x0[pending]
    v = torch.randn(*shape, 3, generator=generator, dtype=torch.float64, device=device)
    v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    around_identity = torch.cat([w.unsqueeze(-1), torch.sqrt((1 - w * w).clamp_min(0)).unsqueeze(-1) * v], -1)
    return pkt.quaternion_raw_multiply(mean, around_identity.to(dtype))


def _beta_1p5(n: int, generator: torch.Generator | None, device) -> Tensor:
    """Beta(1.5, 1.5) samples: the x-coordinate of a uniform point in a disc, mapped to [0, 1]."""
    # If (X, Y) is uniform in the unit disc, (X + 1) / 2 ~ Beta(1.5, 1.5).
    r = torch.sqrt(torch.rand(n, generator=generator, dtype=torch.float64, device=device))
    theta = 2 * math.pi * torch.rand(n, generator=generator, dtype=torch.float64, device=device)
    return (r * torch.cos(theta) + 1) / 2


def perturb(
    pose: Pose,
    sigma_p: float | Tensor,
    kappa: float | Tensor,
    generator: torch.Generator | None = None,
) -> Pose:
    """Random poses around ``pose``: Gaussian translation (std ``sigma_p`` m per axis) and a vMF
    rotation of concentration ``kappa`` applied in the body frame (``q ⊗ δq``)."""
    shape = pose.batch_shape
    p = pose.p.expand(*shape, 3)
    noise = random_normal(p.shape, generator, p.dtype, p.device)
    sigma = torch.as_tensor(sigma_p, dtype=p.dtype, device=p.device)
    if sigma.dim() > 0:
        sigma = sigma.unsqueeze(-1)
    delta = sample_vmf_quaternion(
        torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=pose.q.dtype, device=pose.q.device).expand(*shape, 4),
        kappa,
        generator,
    )
    return Pose(p + sigma * noise, pkt.quaternion_raw_multiply(pose.q.expand(*shape, 4), delta))


def mean_pose(poses: Pose, dim: int = -1) -> Pose:
    """The average of poses over batch dim ``dim``: mean translation and the rotation maximising the
    summed squared alignment (Markley's eigenvector average, sign-invariant)."""
    d = dim if dim >= 0 else dim - 1
    p = poses.p.mean(d)
    q = poses.q.movedim(d, -2)  # (..., N, 4)
    scatter = q.transpose(-1, -2) @ q  # (..., 4, 4)
    _, vectors = torch.linalg.eigh(scatter.double())
    mean_q = vectors[..., -1].to(q.dtype)
    return Pose(p, torch.where(mean_q[..., :1] < 0, -mean_q, mean_q))


def to_matrix(pose: Pose) -> Tensor:
    """Homogeneous matrices ``(..., 4, 4)`` (column-vector convention, as pytorch_kinematics)."""
    shape = pose.batch_shape
    m = torch.zeros(*shape, 4, 4, dtype=pose.p.dtype, device=pose.p.device)
    m[..., :3, :3] = pkt.quaternion_to_matrix(pose.q.expand(*shape, 4))
    m[..., :3, 3] = pose.p.expand(*shape, 3)
    m[..., 3, 3] = 1.0
    return m


def from_matrix(m: Tensor) -> Pose:
    """Poses from homogeneous matrices ``(..., 4, 4)``; the rotation block must be orthonormal."""
    if m.shape[-2:] != (4, 4):
        raise InvalidPoseError(f"expected (..., 4, 4) matrices, got {tuple(m.shape)}")
    return Pose(m[..., :3, 3].clone(), pkt.matrix_to_quaternion(m[..., :3, :3]))


def wxyz_to_xyzw(q: Tensor) -> Tensor:
    """Reorder quaternions from the library's w,x,y,z to pybullet/Rerun's x,y,z,w."""
    return torch.cat([q[..., 1:], q[..., :1]], -1)


def xyzw_to_wxyz(q: Tensor) -> Tensor:
    """Reorder quaternions from pybullet/Rerun's x,y,z,w to the library's w,x,y,z."""
    return torch.cat([q[..., 3:], q[..., :3]], -1)


def to_pybullet(pose: Pose) -> tuple[list[float], list[float]]:
    """A single pose as pybullet's ``(position, orientation_xyzw)`` lists."""
    if pose.batch_shape != torch.Size([]):
        raise InvalidPoseError(f"to_pybullet takes one pose, got batch shape {tuple(pose.batch_shape)}")
    return pose.p.tolist(), wxyz_to_xyzw(pose.q).tolist()


def from_pybullet(position, orientation_xyzw, dtype: torch.dtype = torch.float32) -> Pose:
    """A pose from pybullet's position and x,y,z,w orientation (any sequences or arrays)."""
    p = torch.as_tensor(position, dtype=dtype)
    q = xyzw_to_wxyz(torch.as_tensor(orientation_xyzw, dtype=dtype))
    return Pose(p, q)


def yaw_quaternion(yaw: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` of turns by ``yaw (...)`` rad about the world z axis, in ``yaw``'s dtype."""
    half = 0.5 * yaw
    zeros = torch.zeros_like(half)
    return torch.stack([torch.cos(half), zeros, zeros, torch.sin(half)], -1)


def from_xy_yaw(x: Tensor | float, y: Tensor | float, yaw: Tensor | float, z: Tensor | float = 0.0) -> Pose:
    """Planar poses: position (x, y, z) and a rotation of ``yaw`` rad about the world z axis (float32)."""
    x, y, z, yaw = torch.broadcast_tensors(*(torch.as_tensor(v, dtype=torch.float32) for v in (x, y, z, yaw)))
    return Pose(torch.stack([x, y, z], -1), yaw_quaternion(yaw))


def yaw_of(q: Tensor) -> Tensor:
    """Heading in rad: the angle of the rotated x axis in the world xy plane (``(..., 4)`` → ``(...)``)."""
    w, x, y, z = q.unbind(-1)
    return torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
