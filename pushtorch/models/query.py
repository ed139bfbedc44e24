"""Query density: a contact or position model applied to a new cloud (paper, §Query Density, §Model Selection).

For each new kernel a surface feature ``x`` of the (partial) cloud is drawn uniformly; every model frame
``j`` gets the neighbourhood weight ``w^n_ij = w^c_j · N2(r^x | r_j)`` (the descriptor kernel, cut off —
see docs/method.md: the paper prints ``d_r`` where its lineage and its own argument use the kernel);
a frame is drawn with probability ∝ ``w^n_ij``; the kernel is ``(v^x, r^x, u_j)`` placed at ``v^x ∘ u_j``
with weight ``w'_i = Σ_j w^n_ij`` (Eq. qd_kernel_weight). The resulting KDE over SE(3) (descriptor term
omitted, as the paper) is optimised by simulated annealing from candidates drawn from the kernel means;
for a manipulator model the kernel nearest the best candidate gives the manipulator contact frame.

The selection heuristic ``H_r`` (Eq. for H_r with d'_r) is computed at the same time
(:func:`feature_distance_heuristic`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule, anneal, initial_candidates
from pushtorch.errors import InvalidPointCloudError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import KernelBandwidth, PoseKDE, descriptor_distance, descriptor_distance_unscaled
from pushtorch.models.frames import DESCRIPTOR_SCALE, ContactFrames, embed_descriptors

Tensor = torch.Tensor

__all__ = [
    "QueryDensity",
    "QueryResult",
    "build_query_density",
    "feature_distance_heuristic",
    "neighbourhood_log_weights",
    "planar",
]

_BLOCK = 1 << 22  # elements of one (features x frames) block
_HEURISTIC_FEATURES = 2000  # features over which H_r's mean is estimated


def neighbourhood_log_weights(
    e_features: Tensor,
    e_frames: Tensor,
    frame_weight: Tensor,
    r_std: Tensor,
    cutoff_std: float,
    beta_r: float = 1.0,
) -> Tensor:
    """``log w^n_ij = log w^c_j − β_r d_r(r_i, r_j)`` with the descriptor cut-off (−inf beyond it).

    Args:
        e_features: ``(K, 2)`` embedded descriptors (:func:`embed_descriptors`) of cloud features.
        e_frames: ``(N_c, 2)`` embedded descriptors of the model's frames; frame_weight: their ``w^c``.
        r_std: ``(2,)`` descriptor stds in the embedded space (σ_r = 2 std²).
    Returns:
        ``(K, N_c)`` log weights.
    """
    sigma_r = 2 * r_std.to(e_features) ** 2
    d = descriptor_distance(e_features.unsqueeze(-2), e_frames.unsqueeze(-3), sigma_r) * beta_r
    log_w = torch.log(frame_weight.clamp_min(0)).unsqueeze(-2) - d
    return log_w.masked_fill(d >= cutoff_std**2 / 2, -math.inf)


def feature_distance_heuristic(r_features: Tensor, r_frames: Tensor) -> Tensor:
    """``H_r``: mean over cloud features i and model frames j of ``d'_r(r_i, r_j)^(1/4)``.

    The paper sums over the query kernels and the model's frames; the mean orders models the same way
    when they have equal frame counts and stays fair when they do not (docs/method.md). Chunked over i.
    """
    total = torch.zeros((), dtype=torch.float64, device=r_features.device)
    step = max(1, _BLOCK // max(1, r_frames.shape[0]))
    for start in range(0, r_features.shape[0], step):
        block = descriptor_distance_unscaled(r_features[start : start + step].unsqueeze(-2), r_frames)
        total = total + block.clamp_min(0).pow(0.25).double().sum()
    return (total / (r_features.shape[0] * r_frames.shape[0])).to(r_features.dtype)


def planar(pose: se3.Pose) -> se3.Pose:
    """Project poses onto the ground: z = 0 and only the heading about world z kept (a mobile base)."""
    yaw = se3.yaw_of(pose.q)
    half = yaw / 2
    zeros = torch.zeros_like(half)
    q = torch.stack([torch.cos(half), zeros, zeros, torch.sin(half)], -1)
    return se3.Pose(torch.cat([pose.p[..., :2], torch.zeros_like(pose.p[..., :1])], -1), q)


@dataclass
class QueryDensity:
    """Kernels built from a model and a cloud, their KDE over entity poses, and ``H_r``."""

    kernels: ContactFrames  # v: cloud features, r: their descriptors, u: from the model frames
    kde: PoseKDE  # over entity poses v ∘ u (planar-projected for the robot)
    feature_distance: Tensor | None  # H_r (scalar) when asked for
    descriptor_rounds: int  # trial rounds the descriptor cut-off needed (0 = none)


@dataclass
class QueryResult:
    """The optimised entity pose and the kernel nearest to it (the manipulator contact frame)."""

    pose: se3.Pose  # ()
    log_prob: Tensor  # ()
    nearest_kernel: ContactFrames  # one frame: (v, r, u) of the kernel closest to the best candidate
    anneal: AnnealResult
    density: QueryDensity | None = None  # the density that was optimised (kernels for Rerun, H_r)


def build_query_density(
    frames: ContactFrames,
    features: SurfaceFeatures,
    n_kernels: int,
    r_std: Tensor,
    pose_bandwidth: KernelBandwidth,
    r_cutoff_std: float = 5.0,
    descriptor_scale: float = DESCRIPTOR_SCALE,
    alpha_t: float = 2.0,
    max_rounds: int = 10,
    project_planar: bool = False,
    heuristic: bool = False,
    generator: torch.Generator | None = None,
) -> QueryDensity:
    """Build the query density of a contact/position model on a cloud's features (paper, Query Density).

    Drawing ``x`` uniformly and re-drawing while no model frame falls within the descriptor cut-off
    (the lineage retries) is the same as drawing uniformly among the features that have at least one
    frame in reach, which is what is done here, vectorised. If no feature has any, the descriptor
    bandwidth widens by trial rounds (β_r = α_T^(−T_r)) up to ``max_rounds``. With ``heuristic`` the
    selection heuristic ``H_r`` is estimated on a uniform subset of the cloud's features (it is a mean).

    Raises:
        InvalidPointCloudError: no features.
        ModelError: no feature matches any frame even after ``max_rounds`` rounds.
    """
    if len(features) == 0:
        raise InvalidPointCloudError("the query cloud has no surface features")
    r_std = r_std.to(features.r)
    e_features = embed_descriptors(features.r, descriptor_scale)
    e_frames = embed_descriptors(frames.r, descriptor_scale)
    order = torch.randperm(len(features), generator=generator).to(features.r.device)
    step = max(1, _BLOCK // max(1, len(frames)))
    for rounds in range(max_rounds + 1):
        beta_r = alpha_t ** (-rounds)
        pool_idx, pool_log_wn, found = [], [], 0
        # Blocks of features in random order until enough have a frame within reach: usually one or two.
        for start in range(0, len(features), step):
            idx = order[start : start + step]
            block = neighbourhood_log_weights(e_features[idx], e_frames, frames.weight, r_std, r_cutoff_std, beta_r)
            ok = torch.isfinite(block).any(-1)
            pool_idx.append(idx[ok])
            pool_log_wn.append(block[ok])
            found += int(ok.sum())
            if found >= n_kernels:
                break
        if found:
            break
    else:
        raise ModelError(
            f"no feature of the cloud resembles any of the model's {len(frames)} frames, even with the "
            f"descriptor bandwidth widened {max_rounds} times: the model does not fit this object"
        )
    pool = torch.cat(pool_idx)
    # uniform draws (with replacement) among reachable features: a random subset of them is the pool
    choice = torch.randint(found, (n_kernels,), generator=generator).to(pool.device)
    pick = pool[choice]
    log_wn = torch.cat(pool_log_wn)[choice]  # (K, Nc)
    frame_idx = torch.multinomial(torch.softmax(log_wn, -1), 1, generator=generator).squeeze(-1)
    kernel_log_w = torch.logsumexp(log_wn, -1)
    v = se3.Pose(features.p[pick], features.q[pick])
    u = se3.Pose(frames.u.p[frame_idx], frames.u.q[frame_idx])
    kernels = ContactFrames(v, features.r[pick], u, kernel_log_w.exp())
    entity = se3.compose(v, u)
    if project_planar:
        entity = planar(entity)
    kde = PoseKDE(entity, pose_bandwidth, log_weights=kernel_log_w)
    h_r = None
    if heuristic:
        sample = torch.randperm(len(features), generator=generator)[:_HEURISTIC_FEATURES].to(features.r.device)
        h_r = feature_distance_heuristic(features.r[sample], frames.r)
    return QueryDensity(kernels, kde, h_r, rounds)


def optimise_query_density(
    density: QueryDensity,
    n_candidates: int,
    schedule: AnnealSchedule,
    generator: torch.Generator | None = None,
    record_history: bool = False,
) -> QueryResult:
    """Simulated annealing on the query density from candidates drawn at the kernel means by weight."""
    init = initial_candidates(density.kde, n_candidates, generator)
    result = anneal(density.kde.log_prob, init, schedule, generator, record_history=record_history)
    if not torch.isfinite(result.best_log_prob):
        raise ModelError("simulated annealing found no pose with non-zero query density")
    d = ((density.kde.means.p - result.best.p) ** 2).sum(-1)
    nearest = density.kernels.select(d.argmin().reshape(1))
    return QueryResult(result.best, result.best_log_prob, nearest, result, density)
