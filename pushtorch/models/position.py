"""Object position model and the centroid baseline (paper, §Object Position Model, §Pose Estimation).

A position frame ``c^p = (v, r, u^p)`` relates a surface feature of the full training cloud to the
object's origin: ``u^p = h = v⁻¹ ∘ B^O``. Its weight is the descriptor's distance from the mean
descriptor, ``w_i = d_r(r_i, r̄, σ_r)``: salient features (edges, corners) are rarer and pin the
object's pose down better than flat faces (:func:`fit_position_model`). At prediction the query
density (pushtorch.models.query) turns these frames into kernels over object poses.

Decision (docs/method.md, "pose hypotheses verified by the surface fit"): the paper keeps the annealing
candidate of highest query density. The density is a *sum* of kernels, so evidence that only a few
features carry (the modified cube's notch: ~10 % of the surface) barely separates the true orientation
from the orientations a plain cube would allow (measured: log densities within 0.05 of each other, and
90° errors). The annealed candidates are therefore verified against the training cloud the position
frames come from (:func:`surface_fit_scores`): the candidate whose surface best explains the observed
points wins (:func:`verify_pose_candidates`). The density still proposes every hypothesis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from pushtorch import se3
from pushtorch.errors import InvalidPointCloudError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import Evaluation
from pushtorch.models.frames import DESCRIPTOR_SCALE, ContactFrames, embed_descriptors
from pushtorch.models.query import QueryDensity, build_query_density
from pushtorch.models.settings import ModelSettings

Tensor = torch.Tensor

__all__ = [
    "PositionModel", "centroid_pose", "fit_position_model", "grid_fit_scores", "surface_fit_scores",
    "verify_pose_candidates",
]

# Observed points scored per candidate: the mean distance's standard error is then ~1/20 of its spread.
VERIFY_POINTS = 512
# Distance (m) beyond which an observed point counts as unexplained whatever its distance: a few
# outliers (table edge, spurious returns) must not outweigh the fit of the rest.
VERIFY_CAP = 0.02
# Observed points every candidate is screened on, and how many of the best go on to the full score:
# candidates gather in a few modes, so the screen only has to rank modes apart (~10x cheaper).
VERIFY_SCREEN_POINTS = 64
VERIFY_FINALISTS = 16
# The screen reads distances from a grid of the capped distance field (trilinear): cells of cap / 5
# (4 mm) keep its error below the spread between modes; at most this many cells along the longest side.
_GRID_CELLS_PER_CAP = 5
_GRID_MAX_CELLS = 96


@dataclass
class PositionModel:
    """Position frames of a training object, ``v`` stored relative to its origin ``B^O``."""

    frames: ContactFrames
    descriptor_std: Tensor  # (2,) std of the embedded r over the training cloud: σ_r of the saliency weight
    # built on first use for the pose verification: the frames' points indexed for nearest-neighbour
    # queries, and their capped distance field on a grid
    _search: object | None = field(default=None, repr=False, compare=False)
    _distance_grid: tuple[Tensor, Tensor, Tensor, float] | None = field(default=None, repr=False, compare=False)

    def pose_query(self, features: SurfaceFeatures, settings: ModelSettings, generator: torch.Generator | None,
                   method: Evaluation) -> QueryDensity:
        """This model's part of a push condition (paper, Object Position Model): the query density of the
        object's pose on a new cloud's features."""
        std = torch.full((2,), settings.descriptor_std)
        return build_query_density(
            self.frames, features, settings.query_kernels, std, settings.query_bandwidth,
            r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, generator=generator,
            method=method,
        )

    def __getstate__(self) -> dict:
        """Pickled without its built-on-use caches (the open3d index does not pickle; both are rebuilt on use)."""
        return {**self.__dict__, "_search": None, "_distance_grid": None}

    def nearest_search(self):
        """An open3d nearest-neighbour index over the frames' points (object frame), built once."""
        if self._search is None:
            self._search = _nearest_model_search(self.frames.v.p)
        return self._search

    def distance_grid(self, cap: float = VERIFY_CAP) -> tuple[Tensor, Tensor, Tensor, float]:
        """``(grid (1, 1, Z, Y, X), lo (3,), hi (3,), cap)``: distances (capped at ``cap``) from grid
        points over the frames' bounding box grown by ``cap`` to the nearest frame point (object frame)."""
        if self._distance_grid is None or self._distance_grid[3] != cap:
            self._distance_grid = _capped_distance_grid(self.frames.v.p, self.nearest_search(), cap)
        return self._distance_grid


def fit_position_model(
    features: SurfaceFeatures, object_pose: se3.Pose, descriptor_scale: float = DESCRIPTOR_SCALE
) -> PositionModel:
    """Position frames ``u^p = v⁻¹ ∘ B^O`` weighted by descriptor saliency (paper, Object Position Model).

    The saliency ``d_r(r_i, r̄, σ_r)`` is taken on embedded descriptors (:func:`embed_descriptors`)
    with ``σ_r`` from their per-dimension standard deviation over the training cloud (σ_r = 2·std²,
    the units of pushtorch.kde): the weight reads "squared standard deviations from the mean / 2".
    """
    if len(features) < 2:
        raise InvalidPointCloudError("a position model needs at least 2 surface features")
    v = se3.Pose.unchecked(features.p, features.q)
    u = se3.relative(v, object_pose)
    r = features.r
    embedded = embed_descriptors(r, descriptor_scale)
    std = embedded.std(0).clamp_min(1e-6)
    weight = (((embedded - embedded.mean(0)) / std) ** 2).sum(-1) / 2
    v_object = se3.compose(se3.inverse(object_pose), v)
    return PositionModel(ContactFrames(v_object, r, u, weight), std)


def centroid_pose(points: Tensor) -> se3.Pose:
    """The baseline of earlier work: the cloud's centroid, with the identity orientation.

    The centroid of a single-shot cloud lies on the visible surface, not inside the object: that
    bias is exactly what the paper's comparison (7.06 cm vs 1.41 cm) measures.
    """
    if points.ndim != 2 or points.shape[0] == 0:
        raise InvalidPointCloudError("the centroid of an empty cloud is undefined")
    q = torch.zeros(4, dtype=points.dtype, device=points.device)
    q[0] = 1.0
    return se3.Pose.unchecked(points.mean(0), q)


def _nearest_model_search(model_points: Tensor):
    """An open3d nearest-neighbour index over the model points (object frame)."""
    import numpy as np

    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    if model_points.shape[0] == 0:
        raise InvalidPointCloudError("surface fit needs model points")
    search = o3d.core.nns.NearestNeighborSearch(
        o3d.core.Tensor(np.ascontiguousarray(model_points.detach().cpu().numpy(), dtype=np.float32)))
    search.knn_index()
    return search


def _capped_distance_grid(model_points: Tensor, search, cap: float) -> tuple[Tensor, Tensor, Tensor, float]:
    lo = model_points.amin(0) - cap
    hi = model_points.amax(0) + cap
    cell = max(cap / _GRID_CELLS_PER_CAP, float((hi - lo).max()) / _GRID_MAX_CELLS)
    counts = [int(math.ceil(float(extent) / cell)) + 1 for extent in (hi - lo)]
    hi = lo + cell * (torch.tensor(counts, dtype=lo.dtype, device=lo.device) - 1)
    axes = [torch.linspace(float(lo[k]), float(hi[k]), counts[k], dtype=lo.dtype, device=lo.device) for k in range(3)]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    nodes = torch.stack([x, y, z], -1).reshape(-1, 3)
    distance = _nearest_distances(search, nodes).clamp(max=cap)
    return distance.reshape(1, 1, counts[2], counts[1], counts[0]), lo, hi, cap


def _nearest_distances(search, points: Tensor) -> Tensor:
    """Distance of each of ``points (..., 3)`` to its nearest indexed point."""
    import numpy as np

    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    queries = o3d.core.Tensor(np.ascontiguousarray(points.reshape(-1, 3).detach().cpu().numpy(), dtype=np.float32))
    _, squared = search.knn_search(queries, 1)
    return torch.from_numpy(squared.numpy()).to(points).reshape(points.shape[:-1]).clamp_min(0).sqrt()


def grid_fit_scores(position: PositionModel, observed: Tensor, candidates: se3.Pose, cap: float = VERIFY_CAP
                    ) -> Tensor:
    """:func:`surface_fit_scores` read from the position model's distance grid (trilinear, cells of
    ``cap / 5``): ``(C,)``, metres; an approximation for ranking many candidates cheaply."""
    if observed.shape[0] == 0:
        raise InvalidPointCloudError("surface fit needs observed points")
    grid, lo, hi, _ = position.distance_grid(cap)
    local = se3.apply(se3.inverse(candidates).unsqueeze(-1), observed)  # (C, M, 3)
    coords = (2.0 * (local - lo) / (hi - lo) - 1.0).to(grid.dtype)  # grid_sample's x, y, z in [-1, 1]
    # outside the grid a point is further than cap from the model: the border cells hold cap
    sampled = torch.nn.functional.grid_sample(grid, coords.reshape(1, *local.shape[:2], 1, 3), mode="bilinear",
                                              padding_mode="border", align_corners=True)
    return sampled.reshape(local.shape[:2]).to(observed.dtype).mean(-1)


def surface_fit_scores(position: PositionModel, observed: Tensor, candidates: se3.Pose, cap: float = VERIFY_CAP
                       ) -> Tensor:
    """How badly each candidate object pose explains the observed points: ``(C,)``, metres.

    The observed points (world) are moved into each candidate's object frame and matched to their
    nearest point of the position model's frames (the training cloud, object frame; open3d's
    nearest-neighbour search, :meth:`PositionModel.nearest_search`); the score is the mean of those
    distances, each capped at ``cap``.

    Args:
        position: the model whose frames' points are the surface ``B^O``.
        observed: ``(M, 3)`` observed surface points, world frame.
        candidates: object poses ``(C,)``.
    """
    if observed.shape[0] == 0:
        raise InvalidPointCloudError("surface fit needs observed points")
    local = se3.apply(se3.inverse(candidates).unsqueeze(-1), observed)  # (C, M, 3)
    return _nearest_distances(position.nearest_search(), local).clamp(max=cap).mean(-1)


def verify_pose_candidates(
    position: PositionModel, observed: Tensor, candidates: se3.Pose, log_prob: Tensor,
    generator: torch.Generator | None = None, points: int = VERIFY_POINTS, cap: float = VERIFY_CAP,
    screen_points: int = VERIFY_SCREEN_POINTS, finalists: int = VERIFY_FINALISTS,
) -> Tensor:
    """Index of the candidate (among those of non-zero density) whose surface best fits the observation.

    Two stages keep it cheap: every candidate is screened on ``screen_points`` of the observed points
    ``(M, 3)`` (world) with distances read from the model's distance grid (:func:`grid_fit_scores`), the
    ``finalists`` best are scored exactly on ``points`` (:func:`surface_fit_scores`). Ties (symmetric
    poses) go to the higher density. Raises InvalidPointCloudError without observed points.
    """
    order = torch.randperm(observed.shape[0], generator=generator).to(observed.device)
    alive = torch.isfinite(log_prob)
    score = grid_fit_scores(position, observed[order[:screen_points]], candidates, cap)
    score = torch.where(alive, score, torch.full_like(score, math.inf))
    shortlist = score.argsort()[: min(finalists, int(alive.sum().clamp_min(1)))]
    final = surface_fit_scores(position, observed[order[:points]], candidates.take(shortlist), cap)
    tied = final <= final.min() + 1e-6
    return shortlist[torch.where(tied, log_prob[shortlist], torch.full_like(final, -math.inf)).argmax()]
