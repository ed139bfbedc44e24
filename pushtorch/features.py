"""Surface features of a point cloud: a pose and two principal curvatures for every point.

Paper, Background, Surface Features: a surface feature is ``x = (v, r)`` with ``v = (p, q)`` in SE(3) and
``r = (r1, r2)`` the local principal curvatures at ``p``. The normal comes from PCA of the neighbourhood
(Kanatani); ``k1`` is the direction of the highest curvature ``r1``, ``k2`` the direction of ``r2`` and
perpendicular to ``k1``; the normal and the principal directions define the orientation ``q``.

How each quantity is computed here (batched over points, no Python loop over points):
    * neighbourhood: the points within ``radius`` of ``p`` (open3d hybrid search; at most
      ``max_neighbours``, the nearest ones), padded to a fixed size with a mask;
    * normal ``n``: eigenvector of the smallest eigenvalue of the neighbourhood covariance, oriented
      outward, i.e. towards the camera that saw the point (a visible surface faces its camera), or away
      from the cloud's centroid when the cloud has no view origins;
    * curvature: a quadric height field ``h = a u² + b uv + c v² + d u + e v + f`` fitted by least squares
      in the tangent frame of ``n``; the shape operator of that surface at ``(0, 0)`` (first fundamental
      form included, so a slightly tilted normal does not bias it) has eigenvalues ``r1 >= r2`` and
      eigenvectors ``k1, k2``;
    * frame: ``k1`` projected on the tangent plane, ``k2 = n × k1``; ``q`` is the rotation whose matrix
      columns are ``(k1, k2, n)`` (right-handed), w,x,y,z.

Sign convention: curvature is positive where the surface is convex, i.e. bends away from its outward
normal (a sphere of radius R has ``r1 = r2 = 1/R``, a cylinder ``r1 = 1/R, r2 = 0``, a concave crease is
negative). ``r1 >= r2`` as signed numbers. Units: m⁻¹.

Where principal directions are undefined (flat or umbilic patches, ``r1 ≈ r2``) the frame is aligned
with gravity instead, and every frame's sign is fixed so that it repeats between clouds
(:func:`align_frames_with_gravity`; pass ``up=None`` for the raw principal frames).

Points with fewer than ``min_neighbours`` neighbours (the quadric has 6 unknowns), or whose neighbourhood
is degenerate (collinear), are dropped; :attr:`SurfaceFeatures.index` maps every feature back to its point.

Default radius 0.012 m: the lineage (PCL principal curvatures in Golem) uses 0.005–0.015 m; 12 mm holds
~25–30 points of a cloud down-sampled at 4 mm, enough for a stable quadric, while edges of a 0.2 m cube
stay localised (features farther than 12 mm from an edge see a flat face).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError
from pushtorch.perception import PointCloud

Tensor = torch.Tensor

__all__ = [
    "DEFAULT_MAX_NEIGHBOURS",
    "DEFAULT_MIN_NEIGHBOURS",
    "DEFAULT_RADIUS",
    "SurfaceFeatures",
    "align_frames_with_gravity",
    "compute_surface_features",
    "radius_neighbourhoods",
]

#: Neighbourhood radius (m) of normals and curvatures.
DEFAULT_RADIUS = 0.012
#: Cap on the neighbourhood size (the nearest are kept): bounds memory on dense clouds.
DEFAULT_MAX_NEIGHBOURS = 64
#: Fewest neighbours (the point itself included) for a feature: 6 quadric unknowns plus a margin.
DEFAULT_MIN_NEIGHBOURS = 10
#: Curvature anisotropy |r1 - r2| (m⁻¹) below which principal directions are taken as undefined and the
#: frame is aligned with gravity instead: a patch flatter than a 0.5 m radius is "flat" at object scale.
DEFAULT_ISOTROPY_TOLERANCE = 2.0
_QUADRIC_UNKNOWNS = 6
# A neighbourhood whose second covariance eigenvalue is below this fraction of the largest is a line.
_COLLINEAR_RATIO = 1e-3


@dataclass
class SurfaceFeatures:
    """Surface features ``x = (v=(p, q), r)`` of N points (paper, Surface Features), plus their frames.

    Attributes:
        p: ``(N, 3)`` positions, metres, world frame.
        q: ``(N, 4)`` orientations, unit w,x,y,z: rotation matrix columns ``(k1, k2, normal)``.
        r: ``(N, 2)`` principal curvatures ``(r1, r2)``, ``r1 >= r2``, m⁻¹, convex positive.
        normal: ``(N, 3)`` outward unit normals.
        k1: ``(N, 3)`` unit direction of ``r1`` (tangent).
        k2: ``(N, 3)`` ``normal × k1``.
        index: ``(N,)`` int64 index of each feature's point in the input cloud.
    """

    p: Tensor
    q: Tensor
    r: Tensor
    normal: Tensor
    k1: Tensor
    k2: Tensor
    index: Tensor

    def __len__(self) -> int:
        return self.p.shape[0]

    @property
    def device(self) -> torch.device:
        return self.p.device

    @property
    def pose(self) -> se3.Pose:
        """The feature poses ``v = (p, q)`` as a batched :class:`~pushtorch.se3.Pose` ``(N,)``."""
        return se3.Pose.unchecked(self.p, self.q)

    @property
    def frames(self) -> Tensor:
        """Rotation matrices ``(N, 3, 3)`` with columns ``(k1, k2, normal)``."""
        return torch.stack([self.k1, self.k2, self.normal], -1)

    def to(self, *args, **kwargs) -> SurfaceFeatures:
        """Move/cast like ``Tensor.to``; ``index`` keeps its integer dtype."""
        moved = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value.is_floating_point():
                moved[f.name] = value.to(*args, **kwargs)
            else:
                device = _device_of(args, kwargs)
                moved[f.name] = value if device is None else value.to(device)
        return SurfaceFeatures(**moved)

    def select(self, idx: Tensor | slice | int) -> SurfaceFeatures:
        """The features at ``idx`` (index tensor, boolean mask, slice or int)."""
        return SurfaceFeatures(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    __getitem__ = select

    @staticmethod
    def cat(parts: list[SurfaceFeatures]) -> SurfaceFeatures:
        """Concatenate feature sets along the point dimension."""
        names = [f.name for f in fields(SurfaceFeatures)]
        return SurfaceFeatures(**{name: torch.cat([getattr(x, name) for x in parts]) for name in names})


def _device_of(args, kwargs) -> torch.device | None:
    for a in (*args, kwargs.get("device")):
        if isinstance(a, str | torch.device):
            return torch.device(a)
        if isinstance(a, Tensor):
            return a.device
    return None


def radius_neighbourhoods(
    points: Tensor, radius: float = DEFAULT_RADIUS, max_neighbours: int = DEFAULT_MAX_NEIGHBOURS
) -> tuple[Tensor, Tensor]:
    """Indices of the points within ``radius`` of each point (the point itself included), padded.

    Args:
        points: ``(N, 3)``.
        radius: metres.
        max_neighbours: K, the padded size; when more points lie within ``radius``, the nearest are kept.

    Returns:
        ``index (N, K)`` int64 (padding entries repeat the query point, so gathers stay valid) and
        ``mask (N, K)`` bool (true for real neighbours), both on ``points.device``.
    """
    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    # searched in float32 about the cloud's centre: a cloud far from the origin keeps its neighbourhoods
    centred = points.detach().cpu().double()
    data = o3d.core.Tensor(np.ascontiguousarray((centred - centred.mean(0)).numpy().astype(np.float32)))
    nns = o3d.core.nns.NearestNeighborSearch(data)
    nns.hybrid_index(float(radius))
    index, _, _ = nns.hybrid_search(data, float(radius), int(max_neighbours))
    index = torch.from_numpy(index.numpy().astype(np.int64)).to(points.device)
    mask = index >= 0
    self_index = torch.arange(points.shape[0], device=points.device).unsqueeze(-1)
    return torch.where(mask, index, self_index), mask


#: The coarsest spacing between representable coordinates, as a share of the feature radius, at which a cloud's
#: neighbourhoods still hold their shape: float32 spaces coordinates 1.2e-4 m apart 1 km from the origin and
#: 0.06 m apart 1,000 km away, where a 12 mm neighbourhood is a handful of grid points
RESOLUTION_SHARE = 0.05


def _check_resolution(points: Tensor, radius: float) -> None:
    """Refuse a cloud whose coordinates lie so far from the origin that its dtype cannot tell points within
    ``radius`` apart (a world frame centred elsewhere: a map's, a GPS datum's)."""
    far = float(points.detach().abs().amax())
    spacing = far * torch.finfo(points.dtype).eps
    if spacing > RESOLUTION_SHARE * radius:
        raise InvalidPointCloudError(
            f"the cloud lies {far:.3g} m from the origin, where {points.dtype} coordinates are up to {spacing:.2g} m "
            f"apart, too coarse for surface features within {radius} m: express it in a frame near the object "
            "(the robot's or the table's)"
        )


def compute_surface_features(
    cloud: PointCloud | Tensor,
    radius: float = DEFAULT_RADIUS,
    max_neighbours: int = DEFAULT_MAX_NEIGHBOURS,
    min_neighbours: int = DEFAULT_MIN_NEIGHBOURS,
    chunk_size: int = 16384,
    up: tuple[float, float, float] | None = (0.0, 0.0, 1.0),
    isotropy_tolerance: float = DEFAULT_ISOTROPY_TOLERANCE,
) -> SurfaceFeatures:
    """Surface features of every point of a cloud (paper, Background, Surface Features).

    Args:
        cloud: a :class:`~pushtorch.perception.PointCloud` (view origins orient the normals) or an
            ``(N, 3)`` tensor (normals then point away from the cloud's centroid, right for convex
            objects only).
        radius: neighbourhood radius (m), see the module docstring for the default.
        max_neighbours: neighbourhood cap K (nearest kept).
        min_neighbours: fewest points within ``radius`` (the point included) for a feature; at least 6.
        chunk_size: points processed per batch (bounds memory at ~``chunk_size × K × 6`` floats).
        up: the world's up direction (gravity reversed), or None to keep raw principal directions;
            see :func:`align_frames_with_gravity`.
        isotropy_tolerance: ``|r1 - r2|`` (m⁻¹) under which a patch counts as flat/umbilic.

    Returns:
        :class:`SurfaceFeatures` with ``M <= N`` rows on the cloud's device and dtype; points with a
        too small or degenerate neighbourhood are left out (``index`` maps rows to cloud points).

    Raises:
        InvalidPointCloudError: empty cloud, NaN/inf points, fewer points than ``min_neighbours``, a cloud so far
            from the origin that its dtype cannot resolve a neighbourhood (:data:`RESOLUTION_SHARE`), or no
            point with enough neighbours within ``radius`` (the cloud is too sparse for it).
        InvalidParameterError: non-positive radius, or ``min_neighbours`` below 6 or above ``max_neighbours``.
    """
    if not isinstance(cloud, PointCloud):
        cloud = PointCloud(cloud)
    if not (math.isfinite(radius) and radius > 0):
        raise InvalidParameterError(f"feature radius must be positive and finite (m), got {radius}")
    if min_neighbours < _QUADRIC_UNKNOWNS:
        raise InvalidParameterError(
            f"min_neighbours must be >= {_QUADRIC_UNKNOWNS} (unknowns of the curvature quadric), "
            f"got {min_neighbours}"
        )
    if max_neighbours < min_neighbours:
        raise InvalidParameterError(
            f"max_neighbours ({max_neighbours}) must be >= min_neighbours ({min_neighbours})"
        )
    if chunk_size < 1:
        raise InvalidParameterError(f"chunk_size must be positive, got {chunk_size}")
    n_points = len(cloud)
    if n_points < min_neighbours:
        raise InvalidPointCloudError(
            f"point cloud has {n_points} points; a surface-feature neighbourhood needs at least "
            f"{min_neighbours} points within {radius} m"
        )

    points = cloud.points
    _check_resolution(points, radius)
    neighbours, mask = radius_neighbourhoods(points, radius, max_neighbours)
    if cloud.view_origins is not None:
        outward_hint = cloud.view_origins - points
    else:
        outward_hint = points - points.mean(0)

    parts = []
    for start in range(0, n_points, chunk_size):  # chunks of points bound memory; each is fully batched
        sl = slice(start, start + chunk_size)
        parts.append(
            _features_of(
                points, points[sl], neighbours[sl], mask[sl], outward_hint[sl], radius, min_neighbours
            )
        )
    p_all, q_all, r_all, n_all, k1_all, k2_all, valid = (torch.cat(t) for t in zip(*parts, strict=True))
    if not valid.any():
        best = int(mask.sum(-1).max())
        raise InvalidPointCloudError(
            f"no point of the cloud has {min_neighbours} non-collinear neighbours within {radius} m "
            f"(the most any point has is {best}): the cloud is too sparse for this radius"
        )
    index = valid.nonzero().squeeze(-1)
    features = SurfaceFeatures(
        p=p_all[index], q=q_all[index], r=r_all[index], normal=n_all[index],
        k1=k1_all[index], k2=k2_all[index], index=index,
    )
    if up is not None:
        features = align_frames_with_gravity(features, up, isotropy_tolerance)
    return features


def align_frames_with_gravity(
    features: SurfaceFeatures,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    isotropy_tolerance: float = DEFAULT_ISOTROPY_TOLERANCE,
) -> SurfaceFeatures:
    """Make the rotation of each frame about its normal repeatable between clouds.

    The paper builds ``q`` from the normal and the principal directions, but on flat or umbilic
    patches (``|r1 − r2|`` below ``isotropy_tolerance``) the principal direction is noise, and a
    principal direction has no sign: two clouds of the same face would get frames rotated
    arbitrarily about the normal, and motions expressed in those frames (``m = v⁻¹ ∘ v'``) would not
    transfer. Gravity is known at training and prediction alike (the floor is level), so:

    * on flat/umbilic patches whose normal is not vertical, ``k1`` is the horizontal tangent
      ``up × n`` (as on a cylinder's side, where the true ``k1`` runs round it horizontally);
    * every frame's sign is chosen so that ``k2`` points up (``k2 · up ≥ 0``), or ``k1`` does when
      ``k2`` is horizontal; ``k2 = n × k1`` keeps the frame right-handed.

    Patches with well-defined principal directions keep them. Horizontal flat patches (a top face)
    keep their principal direction: nothing observable fixes their heading.
    """
    up_t = torch.as_tensor(up, dtype=features.p.dtype, device=features.p.device)
    up_t = up_t / up_t.norm()
    n, k1 = features.normal, features.k1
    horizontal = torch.cross(up_t.expand_as(n), n, dim=-1)
    h_norm = horizontal.norm(dim=-1, keepdim=True)
    isotropic = (features.r[:, 0] - features.r[:, 1]).abs() < isotropy_tolerance
    use_gravity = (isotropic & (h_norm.squeeze(-1) > 0.1)).unsqueeze(-1)
    k1 = torch.where(use_gravity, horizontal / h_norm.clamp_min(1e-12), k1)
    k2 = torch.cross(n, k1, dim=-1)
    k2_up = (k2 * up_t).sum(-1)
    k1_up = (k1 * up_t).sum(-1)
    flip = torch.where(k2_up.abs() > 0.1, k2_up < 0, k1_up < 0).unsqueeze(-1)
    k1 = torch.where(flip, -k1, k1)
    k2 = torch.where(flip, -k2, k2)
    q = pkt.matrix_to_quaternion(torch.stack([k1, k2, n], -1))
    q = q / q.norm(dim=-1, keepdim=True)
    return SurfaceFeatures(
        p=features.p, q=q, r=features.r, normal=n, k1=k1, k2=k2, index=features.index
    )


def _features_of(
    all_points: Tensor,
    points: Tensor,
    neighbours: Tensor,
    mask: Tensor,
    outward_hint: Tensor,
    radius: float,
    min_neighbours: int,
) -> tuple[Tensor, ...]:
    """Features of a chunk ``points (n, 3)`` with neighbourhoods ``(n, K)``; see the module docstring."""
    weight = mask.to(points.dtype)  # (n, K)
    count = weight.sum(-1)  # (n,)
    local = (all_points[neighbours] - points.unsqueeze(1)) / radius  # (n, K, 3), unitless, |local| <= 1

    # PCA normal (Kanatani): smallest-eigenvalue eigenvector of the neighbourhood covariance.
    mean = (local * weight.unsqueeze(-1)).sum(1) / count.unsqueeze(-1)
    centred = (local - mean.unsqueeze(1)) * weight.unsqueeze(-1)
    covariance = centred.transpose(1, 2) @ centred / count.view(-1, 1, 1)
    eigenvalues, eigenvectors = torch.linalg.eigh(covariance)  # ascending
    normal = eigenvectors[..., 0]
    flip = (normal * outward_hint).sum(-1) < 0
    normal = torch.where(flip.unsqueeze(-1), -normal, normal)
    tangent_u = eigenvectors[..., 2]
    tangent_v = torch.cross(normal, tangent_u, dim=-1)  # (u, v, n) right-handed

    # Quadric height field h(u, v) = a u² + b uv + c v² + d u + e v + f, least squares in the tangent frame.
    u = (local * tangent_u.unsqueeze(1)).sum(-1)
    v = (local * tangent_v.unsqueeze(1)).sum(-1)
    h = (local * normal.unsqueeze(1)).sum(-1)
    design = torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)], -1) * weight.unsqueeze(-1)
    gram = design.transpose(1, 2) @ design
    # A tiny ridge keeps degenerate (already rejected) neighbourhoods from producing NaN.
    ridge = torch.eye(_QUADRIC_UNKNOWNS, dtype=points.dtype, device=points.device)
    gram = gram + 1e-6 * count.view(-1, 1, 1) * ridge
    rhs = design.transpose(1, 2) @ (h * weight).unsqueeze(-1)
    a, b, c, du, dv, _ = torch.linalg.solve(gram, rhs).squeeze(-1).unbind(-1)

    # Shape operator S = -I⁻¹ II at (0, 0) (convex positive for the outward normal); coordinates were
    # divided by radius, so second derivatives scale by 1/radius and first derivatives are unchanged.
    first = torch.stack([1 + du * du, du * dv, du * dv, 1 + dv * dv], -1).view(-1, 2, 2)
    g = torch.sqrt(1 + du * du + dv * dv)
    second = torch.stack([2 * a, b, b, 2 * c], -1).view(-1, 2, 2) / (radius * g).view(-1, 1, 1)
    # Generalised symmetric eigenproblem -II x = λ I x; with I = L Lᵀ it is (L⁻¹ (-II) L⁻ᵀ) y = λ y,
    # x = L⁻ᵀ y.
    chol = torch.linalg.cholesky(first)
    eye2 = torch.eye(2, dtype=points.dtype, device=points.device).expand_as(first)
    chol_inv = torch.linalg.solve_triangular(chol, eye2, upper=False)
    symmetric = chol_inv @ (-second) @ chol_inv.transpose(1, 2)
    symmetric = 0.5 * (symmetric + symmetric.transpose(1, 2))
    curvatures, directions = torch.linalg.eigh(symmetric)  # ascending: column 1 is r1
    principal = chol_inv.transpose(1, 2) @ directions[..., 1:2]  # (n, 2, 1) in (u, v)
    k1 = principal[:, 0] * tangent_u + principal[:, 1] * tangent_v  # on the PCA tangent plane
    k1 = k1 / k1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k2 = torch.cross(normal, k1, dim=-1)
    r = curvatures.flip(-1)  # (r1, r2), r1 >= r2

    frames = torch.stack([k1, k2, normal], -1)
    q = pkt.matrix_to_quaternion(frames)
    q = q / q.norm(dim=-1, keepdim=True)

    valid = (
        (count >= min_neighbours)
        & (eigenvalues[..., 1] > _COLLINEAR_RATIO * eigenvalues[..., 2])
        & torch.isfinite(r).all(-1)
        & torch.isfinite(q).all(-1)
    )
    return points, q, r, normal, k1, k2, valid
