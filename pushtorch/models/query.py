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

Fast path (:attr:`~pushtorch.kde.Evaluation.FAST`): the same draws without the ``(kernels × frames)`` weight
matrix (fused group sums and a two-level categorical draw), and several densities annealed in one batch
(:func:`optimise_query_densities`) with the pruned, fused :meth:`pushtorch.kde.PoseKDE.log_prob`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule, anneal, initial_candidates, polish_candidates
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import (
    Evaluation,
    KernelBandwidth,
    PoseKDE,
    descriptor_distance,
    descriptor_distance_unscaled,
    fused_function,
)
from pushtorch.kde.fused import chunk_bounds
from pushtorch.models.frames import DESCRIPTOR_SCALE, ContactFrames, embed_descriptors

Tensor = torch.Tensor

__all__ = [
    "QueryDensity",
    "QueryResult",
    "build_query_density",
    "feature_distance_heuristic",
    "heuristic_descriptors",
    "optimise_query_densities",
    "optimise_query_density",
    "neighbourhood_log_weights",
    "planar",
]

_BLOCK = 1 << 22  # elements of one (features x frames) block
_HEURISTIC_FEATURES = 2000  # features over which H_r's mean is estimated
_FRAME_GROUP = 64  # frames per group of the fast path's two-level categorical draw
_FAST_REDRAWS = 20  # rounds of redrawing unreachable features before the fast build defers to the dense one


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


def _heuristic_row_sums(r_rows: Tensor, r_frames: Tensor) -> Tensor:
    """Σ_j d'_r(r_i, r_j)^(1/4) per row ``(n,)`` (fused on the fast path)."""
    d = (r_rows[:, None, 0] - r_frames[None, :, 0]) ** 2 + (r_rows[:, None, 1] - r_frames[None, :, 1]) ** 2
    return torch.sqrt(torch.sqrt(d)).sum(-1)


def heuristic_descriptors(features: SurfaceFeatures) -> Tensor:
    """The descriptors ``H_r`` is estimated on: a fixed uniform subset of the cloud's features (seed 0,
    at most 2,000), so every model is scored on the same features and a cloud's ``H_r`` is reproducible."""
    sample = torch.randperm(len(features), generator=torch.Generator().manual_seed(0))[:_HEURISTIC_FEATURES]
    return features.r[sample.to(features.r.device)]


def feature_distance_heuristic(r_features: Tensor, r_frames: Tensor,
                               method: Evaluation | str = Evaluation.DENSE) -> Tensor:
    """``H_r``: mean over cloud features i and model frames j of ``d'_r(r_i, r_j)^(1/4)``.

    The paper sums over the query kernels and the model's frames; the mean orders models the same way
    when they have equal frame counts and stays fair when they do not (docs/method.md). Chunked over i.
    :attr:`Evaluation.FAST` fuses the per-row sums (float32 rows, float64 total): the same value up to rounding.
    """
    if Evaluation.of(method) is Evaluation.FAST and r_features.shape[-1] == 2:
        rows = fused_function("heuristic_rows", _heuristic_row_sums, r_features.device)
        step = max(1, _BLOCK // max(1, r_frames.shape[0]))
        total = sum(rows(r_features[s : s + step], r_frames).double().sum()
                    for s in range(0, len(r_features), step))
        return (total / (r_features.shape[0] * r_frames.shape[0])).to(r_features.dtype)
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
    return se3.Pose.unchecked(torch.cat([pose.p[..., :2], torch.zeros_like(pose.p[..., :1])], -1), q)


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


def _group_weight_sums(
    e_rows: Tensor, frames_0: Tensor, frames_1: Tensor, log_w: Tensor, scale: Tensor, delta: float
) -> Tensor:
    """Σ over each group of frames of ``w^c_j N2(r_i | r_j)`` (cut off), ``(n, G)``.

    e_rows: ``(n, 2)`` embedded descriptors; frames_0, frames_1: ``(G, S)`` the grouped frames' two
    embedded coordinates (separate arrays: interleaved ones compile to scalar code, ~2x slower);
    log_w: ``(G, S)`` log ``w^c`` relative to the largest (−inf: padding); scale: ``(2,)`` β_r/σ_r;
    delta: the cut-off.
    """
    d = ((e_rows[:, None, None, 0] - frames_0) ** 2 * scale[0] + (e_rows[:, None, None, 1] - frames_1) ** 2 * scale[1])
    return torch.where(d < delta, torch.exp(log_w - d), torch.zeros_like(d)).sum(-1)


def _categorical_first_reaching(cumulative: Tensor, u: Tensor) -> Tensor:
    """Index of the first entry whose cumulative weight reaches ``u ∈ (0, 1]`` of the total, ``(n,)``."""
    target = u * cumulative[:, -1]
    return (cumulative < target.unsqueeze(-1)).sum(-1).clamp(max=cumulative.shape[-1] - 1)


def _fast_kernel_draws(
    e_features: Tensor, e_frames: Tensor, frame_weight: Tensor, r_std: Tensor, cutoff_std: float,
    n_kernels: int, generator: torch.Generator | None,
) -> tuple[Tensor, Tensor, Tensor] | None:
    """Features, frames and kernel log weights of a query density without the ``(K, N_c)`` matrix.

    The same law as the dense build at the first trial round: each kernel's feature uniform among the
    features with a frame in reach (unreachable draws are drawn again), its frame ∝ ``w^n_ij`` by a
    two-level draw (a group of frames by its summed weight, then a frame in it), its weight
    ``Σ_j w^n_ij``. Returns None (the caller builds densely) when reachable features are too rare
    for redrawing or the weights span more than the dtype can sum in the linear domain.
    """
    device = e_features.device
    log_wc = torch.log(frame_weight.clamp_min(0).to(e_features))
    top = log_wc.max()
    if not torch.isfinite(top):
        return None
    relative = log_wc - top
    dtype = e_features.dtype
    if relative[torch.isfinite(relative)].min() < math.log(torch.finfo(dtype).tiny) + 30.0:
        return None
    n_frames = e_frames.shape[0]
    groups = math.ceil(n_frames / _FRAME_GROUP)
    pad = groups * _FRAME_GROUP - n_frames
    grouped = torch.cat([e_frames, e_frames.new_zeros(pad, 2)]).reshape(groups, _FRAME_GROUP, 2)
    grouped_w = torch.cat([relative, relative.new_full((pad,), -math.inf)]).reshape(groups, _FRAME_GROUP)
    scale = 1.0 / (2 * r_std.to(e_features) ** 2)
    delta = cutoff_std**2 / 2
    sums_fn = fused_function("group_weight_sums", _group_weight_sums, device)
    grouped_0, grouped_1 = grouped[..., 0].contiguous(), grouped[..., 1].contiguous()
    step = max(1, _BLOCK // (groups * _FRAME_GROUP))

    def group_sums(rows: Tensor) -> Tensor:
        # a single row (one redraw) is sent twice: a size-1 dimension would make the compiler specialise
        # and recompile the fused function
        padded = rows.repeat(2) if len(rows) == 1 else rows
        sums = torch.cat([sums_fn(e_features[padded[a:b]], grouped_0, grouped_1, grouped_w, scale, delta)
                          for a, b in chunk_bounds(len(padded), step)])
        return sums[: len(rows)]

    pick = torch.randint(len(e_features), (n_kernels,), generator=generator).to(device)
    sums = group_sums(pick)
    for _ in range(_FAST_REDRAWS):
        unreachable = sums.sum(-1) <= 0
        count = int(unreachable.sum())
        if count == 0:
            break
        if count == n_kernels:  # nothing in reach among n draws: let the dense build scan and widen
            return None
        redraw = torch.randint(len(e_features), (count,), generator=generator).to(device)
        pick[unreachable] = redraw
        sums[unreachable] = group_sums(redraw)
    else:
        return None
    cumulative = sums.cumsum(-1)
    kernel_log_w = torch.log(cumulative[:, -1]) + top
    u = 1.0 - se3.random_uniform((2, n_kernels), generator, dtype).to(device)  # (0, 1]
    group = _categorical_first_reaching(cumulative, u[0])
    d = ((e_features[pick].unsqueeze(1) - grouped[group]) ** 2 * scale).sum(-1)  # (K, S)
    inner = torch.where(d < delta, torch.exp(grouped_w[group] - d), torch.zeros_like(d))
    frame_idx = group * _FRAME_GROUP + _categorical_first_reaching(inner.cumsum(-1), u[1])
    return pick, frame_idx, kernel_log_w


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
    method: Evaluation | str = Evaluation.DENSE,
) -> QueryDensity:
    """Build the query density of a contact/position model on a cloud's features (paper, Query Density).

    Drawing ``x`` uniformly and re-drawing while no model frame falls within the descriptor cut-off
    (the lineage retries) is the same as drawing uniformly among the features that have at least one
    frame in reach, which is what is done here, vectorised. If no feature has any, the descriptor
    bandwidth widens by trial rounds (β_r = α_T^(−T_r)) up to ``max_rounds``. With ``heuristic`` the
    selection heuristic ``H_r`` is estimated on :func:`heuristic_descriptors` (it is a mean).

    :attr:`Evaluation.FAST` draws the same law without the ``(kernels × frames)`` weight matrix
    (:func:`_fast_kernel_draws`, fused); it falls back to the dense build when features in reach are
    rare (then trial rounds may be needed). The seed's random stream differs between the two.

    Raises:
        InvalidPointCloudError: no features.
        ModelError: no feature matches any frame even after ``max_rounds`` rounds.
    """
    if len(features) == 0:
        raise InvalidPointCloudError("the query cloud has no surface features")
    r_std = r_std.to(features.r)
    method = Evaluation.of(method)
    e_features = embed_descriptors(features.r, descriptor_scale)
    e_frames = embed_descriptors(frames.r, descriptor_scale)
    draws = None
    if method is Evaluation.FAST:
        draws = _fast_kernel_draws(e_features, e_frames, frames.weight, r_std, r_cutoff_std, n_kernels,
                                   generator)
    if draws is not None:
        pick, frame_idx, kernel_log_w = draws
        rounds = 0
    else:
        pick, frame_idx, kernel_log_w, rounds = _dense_kernel_draws(
            e_features, e_frames, frames, r_std, r_cutoff_std, alpha_t, max_rounds, n_kernels, generator)
    v = se3.Pose.unchecked(features.p[pick], features.q[pick])
    u = se3.Pose.unchecked(frames.u.p[frame_idx], frames.u.q[frame_idx])
    kernels = ContactFrames(v, features.r[pick], u, kernel_log_w.exp())
    entity = se3.compose(v, u)
    if project_planar:
        entity = planar(entity)
    kde = PoseKDE(entity, pose_bandwidth, log_weights=kernel_log_w)
    h_r = feature_distance_heuristic(heuristic_descriptors(features), frames.r, method) if heuristic else None
    return QueryDensity(kernels, kde, h_r, rounds)


def _dense_kernel_draws(
    e_features: Tensor, e_frames: Tensor, frames: ContactFrames, r_std: Tensor, r_cutoff_std: float,
    alpha_t: float, max_rounds: int, n_kernels: int, generator: torch.Generator | None,
) -> tuple[Tensor, Tensor, Tensor, int]:
    """The reference build's draws: features scanned in random order, dense ``(K, N_c)`` weights."""
    order = torch.randperm(len(e_features), generator=generator).to(e_features.device)
    step = max(1, _BLOCK // max(1, len(frames)))
    for rounds in range(max_rounds + 1):
        beta_r = alpha_t ** (-rounds)
        pool_idx, pool_log_wn, found = [], [], 0
        # Blocks of features in random order until enough have a frame within reach: usually one or two.
        for start in range(0, len(e_features), step):
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
    frame_idx = se3.multinomial(torch.softmax(log_wn, -1), 1, generator).squeeze(-1)
    kernel_log_w = torch.logsumexp(log_wn, -1)
    return pick, frame_idx, kernel_log_w, rounds


def optimise_query_density(
    density: QueryDensity,
    n_candidates: int,
    schedule: AnnealSchedule,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    method: Evaluation | str = Evaluation.DENSE,
    polish_steps: int = 0,
) -> QueryResult:
    """Simulated annealing on the query density from candidates drawn at the kernel means by weight.

    ``method``: :attr:`Evaluation.DENSE` (reference) or :attr:`Evaluation.FAST` (pruned, fused density and cheaper
    proposals, see :meth:`pushtorch.kde.PoseKDE.log_prob` and :func:`pushtorch.anneal.anneal`). ``polish_steps``:
    mean-shift moves of every candidate after annealing (:func:`pushtorch.anneal.polish_candidates`).
    """
    if Evaluation.of(method) is Evaluation.FAST:
        return optimise_query_densities([density], n_candidates, schedule, [schedule.planar], generator,
                                        record_history, polish_steps)[0]
    init = initial_candidates(density.kde, n_candidates, generator)
    result = anneal(density.kde.log_prob, init, schedule, generator, record_history=record_history)
    result = polish_candidates(result, density.kde.mean_shift, density.kde.log_prob, polish_steps)
    return _query_result(density, result)


def _query_result(density: QueryDensity, result: AnnealResult) -> QueryResult:
    if not torch.isfinite(result.best_log_prob):
        raise ModelError("simulated annealing found no pose with non-zero query density")
    d = ((density.kde.means.p - result.best.p) ** 2).sum(-1)
    nearest = density.kernels.select(d.argmin().reshape(1))
    return QueryResult(result.best, result.best_log_prob, nearest, result, density)


def optimise_query_densities(
    densities: list[QueryDensity],
    n_candidates: int,
    schedule: AnnealSchedule,
    planar: list[bool],
    generator: torch.Generator | None = None,
    record_history: bool = False,
    polish_steps: int = 0,
) -> list[QueryResult]:
    """Anneal several query densities in one batch on the fast path (e.g. the robot's, planar, and the
    object's pose, free), so every step costs one pruned density call for all of them; then
    ``polish_steps`` mean-shift moves of every candidate (:func:`pushtorch.anneal.polish_candidates`).

    The densities must share bandwidth and dtype; kernel counts may differ (padding). Each result is
    the one :func:`optimise_query_density` would give with :attr:`Evaluation.FAST` up to the random stream.

    Raises:
        InvalidParameterError: ``planar`` does not match ``densities``.
        ModelError: some density has no finite candidate after annealing.
    """
    if len(planar) != len(densities) or not densities:
        raise InvalidParameterError(
            f"need one planar flag per density (and at least one density), got {len(planar)} for"
            f" {len(densities)}")
    kde = PoseKDE.stack([d.kde for d in densities])
    kde.validate_args = False  # its only queries are the annealing's own (finite, normalised) proposals
    init = initial_candidates(kde, n_candidates, generator)  # (D, C)
    mask = torch.tensor(planar, dtype=torch.bool, device=init.p.device)
    log_prob = partial(kde.log_prob, method=Evaluation.FAST)
    result = anneal(kde, init, schedule, generator, record_history=record_history, planar=mask,
                    method=Evaluation.FAST)
    result = polish_candidates(result, partial(kde.mean_shift, method=Evaluation.FAST), log_prob, polish_steps)
    out = []
    for i, density in enumerate(densities):
        out.append(_query_result(density, result.take(i)))
    return out
