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
      (4, 0, 0)). A caller's poses are validated once: ``Pose(p, q)`` checks what it is given (finite, unit
      q within 1e-4), public entries that take tensors check them with :func:`check_pose` /
      :func:`check_unit_quaternion` (``torch.distributions``' ``validate_args`` convention), and the library
      builds the poses it computes with ``Pose.unchecked``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.streams import KeyedStream, is_keyed

Tensor = torch.Tensor

#: How far from 1 the norm of a caller's quaternion may be in ``Pose(p, q)``.
USER_QUATERNION_ATOL = 1e-4

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
    "onto_plane_of",
    "perturb",
    "quat_distance",
    "quat_normalize",
    "random_quaternion",
    "relative",
    "random_normal",
    "random_uniform",
    "sample_vmf_quaternion",
    "truncated_gamma_1p5",
    "vmf_offsets",
    "to_matrix",
    "to_pybullet",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
    "yaw_of",
    "yaw_quaternion",
]


class _PoseFields(NamedTuple):
    p: Tensor
    q: Tensor


class Pose(_PoseFields):
    """A batch of rigid poses: translation ``p (..., 3)`` and unit quaternion ``q (..., 4)`` wxyz.

    A ``NamedTuple`` so that it unpacks as ``p, q = pose`` and crosses process boundaries cheaply;
    the methods are thin wrappers of the module functions of the same name.

    ``Pose(p, q)`` validates what a caller builds (:func:`check_pose` with ``atol=1e-4``: floating
    tensors of shapes ``(..., 3)`` and ``(..., 4)``, every entry finite, ``|q|`` within 1e-4 of 1) and
    raises :class:`~pushtorch.errors.InvalidPoseError` otherwise. The library builds the poses it
    computes with :meth:`unchecked`, which checks nothing: hot loops and compiled regions stay free of
    synchronising checks and guards.
    """

    __slots__ = ()

    def __new__(cls, p: Tensor, q: Tensor) -> Pose:
        return check_pose(tuple.__new__(cls, (p, q)), atol=USER_QUATERNION_ATOL)

    @classmethod
    def unchecked(cls, p: Tensor, q: Tensor) -> Pose:
        """The pose ``(p, q)`` as given, without any check (for poses the library computed itself)."""
        return tuple.__new__(cls, (p, q))

    def __reduce__(self):
        return (_unchecked_pose, (self.p, self.q))  # unpickled as it was pickled: checked once, when built

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
        return Pose.unchecked(self.p.to(*args, **kwargs), self.q.to(*args, **kwargs))

    def take(self, index) -> Pose:
        """Index the batch dims, e.g. ``pose.take(0)`` or ``pose.take(mask)``."""
        shape = self.batch_shape
        return Pose.unchecked(self.p.expand(*shape, 3)[index], self.q.expand(*shape, 4)[index])

    def expand(self, *shape: int) -> Pose:
        return Pose.unchecked(self.p.expand(*shape, 3), self.q.expand(*shape, 4))

    def reshape(self, *shape: int) -> Pose:
        full = self.batch_shape
        return Pose.unchecked(self.p.expand(*full, 3).reshape(*shape, 3), self.q.expand(*full, 4).reshape(*shape, 4))

    def unsqueeze(self, dim: int) -> Pose:
        """Insert a batch dim (``dim`` counts batch dims only; negative counts from the last one)."""
        d = dim if dim >= 0 else dim - 1
        return Pose.unchecked(self.p.unsqueeze(d), self.q.unsqueeze(d))

    def vector(self) -> Tensor:
        """``(..., 7)`` as ``[p, q_wxyz]``: the event layout of a prediction's distribution."""
        shape = self.batch_shape
        return torch.cat([self.p.expand(*shape, 3), self.q.expand(*shape, 4)], -1)

    @staticmethod
    def from_vector(x: Tensor) -> Pose:
        """The pose ``(...)`` of ``[p, q_wxyz]`` vectors ``(..., 7)`` (views, no copy)."""
        if x.shape[-1:] != (7,):
            raise InvalidPoseError(f"pose vectors must have shape (..., 7) as [p, q_wxyz], got {tuple(x.shape)}")
        return Pose.unchecked(x[..., :3], x[..., 3:])

    @staticmethod
    def cat(poses: list[Pose], dim: int = 0) -> Pose:
        d = dim if dim >= 0 else dim - 1
        return Pose.unchecked(torch.cat([x.p for x in poses], d), torch.cat([x.q for x in poses], d))

    @staticmethod
    def stack(poses: list[Pose], dim: int = 0) -> Pose:
        d = dim if dim >= 0 else dim - 1
        return Pose.unchecked(torch.stack([x.p for x in poses], d), torch.stack([x.q for x in poses], d))


def _unchecked_pose(p: Tensor, q: Tensor) -> Pose:
    return Pose.unchecked(p, q)


def identity(shape: tuple[int, ...] = (), dtype: torch.dtype = torch.float32, device=None) -> Pose:
    """The identity pose with batch shape ``shape``."""
    p = torch.zeros(*shape, 3, dtype=dtype, device=device)
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return Pose.unchecked(p, q)


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
    return Pose.unchecked(a.p + pkt.quaternion_apply(a.q, b.p), pkt.quaternion_raw_multiply(a.q, b.q))


def inverse(a: Pose) -> Pose:
    """``a^-1 = (-q^-1 p, q^-1)`` (paper, Rigid Body Motions)."""
    q_inv = pkt.quaternion_invert(a.q)
    return Pose.unchecked(-pkt.quaternion_apply(q_inv, a.p), q_inv)


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


def draw_device(generator: torch.Generator | KeyedStream | None, device=None):
    """Where a draw from ``generator`` runs: on the generator's own device (the draws are moved after), so a CPU
    generator seeds a model on any device, with the same numbers on each; without a generator, on ``device``. A
    :class:`~pushtorch.streams.KeyedStream` draws on its keys' device."""
    return device if generator is None else generator.device


def _uniform64(shape, generator, device) -> Tensor:
    """Float64 uniforms on [0, 1) of ``shape`` on ``device``, from a generator or a keyed stream."""
    if is_keyed(generator):
        return generator.uniform(shape, torch.float64).to(device)
    draws = torch.rand(shape, generator=generator, dtype=torch.float64, device=draw_device(generator, device))
    return draws.to(device)


def _normal64(shape, generator, device) -> Tensor:
    """Float64 standard normals of ``shape`` on ``device``, from a generator or a keyed stream."""
    if is_keyed(generator):
        return generator.normal(shape, torch.float64).to(device)
    draws = torch.randn(shape, generator=generator, dtype=torch.float64, device=draw_device(generator, device))
    return draws.to(device)


def multinomial(weights: Tensor, n: int, generator: torch.Generator | KeyedStream | None = None,
                replacement: bool = True) -> Tensor:
    """``torch.multinomial`` drawn where the generator is (:func:`draw_device`), indices on ``weights``' device; a
    keyed stream draws with replacement by the inverse of each row's cumulative weights."""
    if is_keyed(generator):
        if not replacement:
            raise InvalidParameterError("a keyed stream draws kernel indices with replacement only")
        return generator.multinomial(weights, n).to(weights.device)
    where = draw_device(generator, weights.device)
    return torch.multinomial(weights.to(where), n, replacement=replacement, generator=generator).to(weights.device)


def random_normal(shape, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                  device=None) -> Tensor:
    """Standard normal draws of ``shape``, the same numbers for every floating ``dtype``
    (:data:`DRAW_DTYPE`) and device (:func:`draw_device`)."""
    if is_keyed(generator):
        return generator.normal(shape, DRAW_DTYPE).to(device=device, dtype=dtype)
    draws = torch.randn(shape, generator=generator, dtype=DRAW_DTYPE, device=draw_device(generator, device))
    return draws.to(device=device, dtype=dtype)


def random_uniform(shape, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                   device=None) -> Tensor:
    """Uniform draws on [0, 1) of ``shape``, the same numbers for every floating ``dtype``
    (:data:`DRAW_DTYPE`) and device (:func:`draw_device`)."""
    if is_keyed(generator):
        return generator.uniform(shape, DRAW_DTYPE).to(device=device, dtype=dtype)
    draws = torch.rand(shape, generator=generator, dtype=DRAW_DTYPE, device=draw_device(generator, device))
    return draws.to(device=device, dtype=dtype)


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


#: Above this bound on ``κ s`` (``P(Gamma(3/2) > 30) ≈ 1e-12``) a cut-off is out of reach and the proposal
#: is drawn the cheap way (:func:`vmf_offsets`).
_UNCUT_BOUND = 30.0
# Safeguarded Newton steps of the truncated Gamma(3/2) inverse CDF: 16 reach float64 round-off of the CDF
# for every truncation from 1e-3 to none (measured); 20 leave a margin.
_NEWTON_STEPS = 20


def _gamma_1p5_cdf(x: Tensor) -> Tensor:
    """Regularised lower incomplete gamma P(3/2, x) (``torch.special.gammainc``)."""
    return torch.special.gammainc(torch.full_like(x, 1.5), x)


def truncated_gamma_1p5(upper: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Gamma(3/2, 1) samples conditioned on ``x < upper`` (float64, any shape), by inverse CDF.

    Both kernel factors reduce to this law: β d_p of a 3-D Gaussian sample is χ²_3/2 ~ Gamma(3/2), and
    κ(1 − |w|) of the vMF on S^3 has density ∝ s^(1/2) e^(−s) √(2 − s/κ), i.e. Gamma(3/2) times a bounded
    factor. Inverting the CDF needs no rejection however tight the cut-off: Newton steps on
    F(x) = u, safeguarded by a shrinking bracket (a step that leaves it bisects instead). torch has the CDF
    (``gammainc``) but no truncated or inverse-CDF gamma sampler.
    """
    upper = upper.clamp(max=80.0)  # P(3/2, 80) = 1 in float64: beyond is the untruncated law
    u = _uniform64(upper.shape, generator, upper.device)
    target = u * _gamma_1p5_cdf(upper)
    lo = torch.zeros_like(upper)
    hi = upper.clone()
    x = torch.minimum(torch.full_like(upper, 1.2), 0.5 * upper)  # near the median of Gamma(3/2)
    for _ in range(_NEWTON_STEPS):
        error = _gamma_1p5_cdf(x) - target
        lo = torch.where(error < 0, x, lo)
        hi = torch.where(error < 0, hi, x)
        density = 2.0 * torch.sqrt(x / math.pi) * torch.exp(-x)
        step = x - error / density.clamp_min(1e-300)
        inside = (step >= lo) & (step <= hi)
        x = torch.where(inside, step, 0.5 * (lo + hi))
    return x


def vmf_offsets(kappa: float | Tensor, shape: tuple[int, ...] | torch.Size, generator: torch.Generator | None = None,
                dtype: torch.dtype = torch.float32, device=None, delta: float = math.inf,
                max_rounds: int = 64) -> Tensor:
    """Unit quaternions ``(*shape, 4)`` around the identity (w ≥ 0) with density ∝ ``exp(−κ (1 − |w|))``
    on SO(3) — the antipodal von Mises–Fisher pair Θ of the paper's rotation kernels — cut at
    ``κ (1 − |w|) < delta`` (inf: no cut-off). The library's one vMF sampler (the kernels', the
    annealing's and :func:`sample_vmf_quaternion`'s; scipy's ``vonmises_fisher`` is the tests' oracle).

    ``s = 1 − w`` has density ∝ ``e^(−κ s) √(s (2 − s))`` on ``[0, min(1, delta/κ)]``: ``κ s`` is drawn from
    Gamma(3/2) truncated at ``min(delta, κ)`` and accepted with probability ``√((2 − s)/2) ≥ 1/√2``.
    Where that bound is beyond reach (≥ 30) the proposal is ``|n|²/2`` for a 3-D standard normal ``n``,
    whose direction is independent and uniform and gives the axis (one draw: the annealing's hot path);
    otherwise the truncated inverse CDF (:func:`truncated_gamma_1p5`). ``kappa``: scalar or a tensor
    broadcastable to ``shape``; ``κ = 0`` is the uniform distribution. Drawn in float64 for every ``dtype``.
    """
    shape = torch.Size(shape)
    kappa = torch.as_tensor(kappa, dtype=torch.float64, device=device).expand(shape)
    if not torch.isfinite(kappa).all() or (kappa < 0).any():
        raise InvalidPoseError("vMF concentration kappa must be finite and >= 0")
    kappa = kappa.clamp_min(1e-9)  # κ → 0: the proposal's truncation at κ makes it uniform in s
    bound = torch.clamp(kappa, max=delta)
    cheap = bound >= _UNCUT_BOUND

    def propose(n: Tensor, kappa: Tensor, bound: Tensor, cheap: Tensor, draws) -> tuple[Tensor, Tensor]:
        """``s`` proposals for normal draws ``n (..., 3)`` and whether each is accepted."""
        proposal = (n * n).sum(-1) / 2.0
        if is_keyed(draws):  # every row drawn (fixed shapes and call counts: a row's numbers are its own)
            gamma_draws = draws.fork()
            if not bool(cheap.all()):
                proposal = torch.where(cheap, proposal, truncated_gamma_1p5(bound, gamma_draws))
        elif not bool(cheap.all()):  # only where a cut-off is within reach: the inverse CDF costs 20 Newton steps
            proposal[~cheap] = truncated_gamma_1p5(bound[~cheap], draws)
        s = proposal / kappa
        u = _uniform64(s.shape, draws, device)
        return s, (proposal < bound) & (2.0 * u * u < 2.0 - s)

    # every row at once, then the rejected ones (~1/(4κ) of them, more near a tight cut-off) again
    n = _normal64((*shape, 3), generator, device)
    s, accepted = propose(n, kappa, bound, cheap, generator)
    pending = ~accepted
    rounds = generator.fork() if is_keyed(generator) else generator  # a keyed stream's retries are their own phase
    for _ in range(max_rounds):
        if not bool(pending.any()):
            break
        if is_keyed(rounds):  # every row again, the pending ones keep theirs
            fresh = _normal64((*shape, 3), rounds, device)
            s_try, ok = propose(fresh, kappa, bound, cheap, rounds)
            ok = ok & pending
            s, n = torch.where(ok, s_try, s), torch.where(ok.unsqueeze(-1), fresh, n)
            pending = pending & ~ok
            continue
        rows = pending.nonzero(as_tuple=True)
        fresh = torch.randn(rows[0].shape[0], 3, generator=rounds, dtype=torch.float64,
                            device=draw_device(rounds, device)).to(device)
        s_try, ok = propose(fresh, kappa[rows], bound[rows], cheap[rows], rounds)
        chosen = tuple(i[ok] for i in rows)
        s[chosen], n[chosen] = s_try[ok], fresh[ok]
        pending[chosen] = False
    # acceptance is >= 71 % per round: rows still pending after max_rounds mean a broken generator; they
    # keep s = 0 (the identity) rather than loop forever
    s = torch.where(pending, torch.zeros_like(s), s)
    axis = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    w = 1.0 - s
    return torch.cat([w.unsqueeze(-1), torch.sqrt((s * (2.0 - s)).clamp_min(0.0)).unsqueeze(-1) * axis], -1).to(dtype)


def sample_vmf_quaternion(mean: Tensor, kappa: float | Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Unit quaternions around ``mean (..., 4)`` from the antipodal vMF pair of concentration ``kappa``
    (:func:`vmf_offsets` applied in the body frame, ``mean ⊗ δq``); the angular spread is about
    ``2/√κ`` rad per axis for large κ, κ = 0 is uniform."""
    offsets = vmf_offsets(kappa, mean.shape[:-1], generator, mean.dtype, mean.device)
    return pkt.quaternion_raw_multiply(mean, offsets)


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
    return Pose.unchecked(p + sigma * noise, pkt.quaternion_raw_multiply(pose.q.expand(*shape, 4), delta))


def mean_pose(poses: Pose, dim: int = -1) -> Pose:
    """The average of poses over batch dim ``dim``: mean translation and the rotation maximising the
    summed squared alignment (Markley's eigenvector average, sign-invariant)."""
    d = dim if dim >= 0 else dim - 1
    p = poses.p.mean(d)
    q = poses.q.movedim(d, -2)  # (..., N, 4)
    scatter = q.transpose(-1, -2) @ q  # (..., 4, 4)
    _, vectors = torch.linalg.eigh(scatter.double())
    mean_q = vectors[..., -1].to(q.dtype)
    return Pose.unchecked(p, torch.where(mean_q[..., :1] < 0, -mean_q, mean_q))


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
    return Pose.unchecked(m[..., :3, 3].clone(), pkt.matrix_to_quaternion(m[..., :3, :3]))


#: Reorder quaternions from the library's w,x,y,z to pybullet/Rerun's x,y,z,w (pytorch_kinematics' own).
wxyz_to_xyzw = pkt.wxyz_to_xyzw
#: Reorder quaternions from pybullet/Rerun's x,y,z,w to the library's w,x,y,z (pytorch_kinematics' own).
xyzw_to_wxyz = pkt.xyzw_to_wxyz


def to_pybullet(pose: Pose) -> tuple[list[float], list[float]]:
    """A single pose as pybullet's ``(position, orientation_xyzw)`` lists."""
    if pose.batch_shape != torch.Size([]):
        raise InvalidPoseError(f"to_pybullet takes one pose, got batch shape {tuple(pose.batch_shape)}")
    return pose.p.tolist(), wxyz_to_xyzw(pose.q).tolist()


def from_pybullet(position, orientation_xyzw, dtype: torch.dtype = torch.float32) -> Pose:
    """A pose from pybullet's position and x,y,z,w orientation (any sequences or arrays)."""
    p = torch.as_tensor(position, dtype=dtype)
    q = xyzw_to_wxyz(torch.as_tensor(orientation_xyzw, dtype=dtype))
    return Pose.unchecked(p, q)


def yaw_quaternion(yaw: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` of turns by ``yaw (...)`` rad about the world z axis, in ``yaw``'s dtype."""
    half = 0.5 * yaw
    zeros = torch.zeros_like(half)
    return torch.stack([torch.cos(half), zeros, zeros, torch.sin(half)], -1)


def from_xy_yaw(x: Tensor | float, y: Tensor | float, yaw: Tensor | float, z: Tensor | float = 0.0) -> Pose:
    """Planar poses: position (x, y, z) and a rotation of ``yaw`` rad about the world z axis (float32)."""
    x, y, z, yaw = torch.broadcast_tensors(*(torch.as_tensor(v, dtype=torch.float32) for v in (x, y, z, yaw)))
    return Pose.unchecked(torch.stack([x, y, z], -1), yaw_quaternion(yaw))


def yaw_of(q: Tensor) -> Tensor:
    """Heading in rad: the angle of the rotated x axis in the world xy plane (``(..., 4)`` → ``(...)``)."""
    w, x, y, z = q.unbind(-1)
    return torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def onto_plane_of(pose: Pose, reference: Pose) -> Pose:
    """Poses moved onto the plane of ``reference`` (batch dims broadcast): their x and y, ``reference``'s height,
    and the twist about world z of their rotation relative to ``reference`` applied to it,
    ``q' = twist_z(q q_ref⁻¹) q_ref``; the rest of the rotation (the tilt) is dropped. A rotation whose twist is
    undefined (a half turn about a horizontal axis) keeps ``reference``'s orientation."""
    relative_q = pkt.quaternion_raw_multiply(pose.q, pkt.quaternion_invert(reference.q))
    w, z = relative_q[..., 0], relative_q[..., 3]
    norm = torch.sqrt(w * w + z * z)
    flat = norm < 1e-9
    safe = torch.where(flat, torch.ones_like(norm), norm)
    zeros = torch.zeros_like(w)
    twist = torch.stack([torch.where(flat, torch.ones_like(w), w / safe), zeros, zeros,
                         torch.where(flat, zeros, z / safe)], -1)
    q = pkt.quaternion_raw_multiply(twist, reference.q.expand_as(twist))
    height = reference.p[..., 2:].expand_as(pose.p[..., 2:])
    return Pose.unchecked(torch.cat([pose.p[..., :2], height], -1), q)
