"""Contact models: the manipulator contact model and the environment contact model (paper, §Contact Models).

Manipulator Contact Model: from the surface features of a full training cloud and the robot placed
against the object, every feature within ``δ_c`` of the bumper's triangles becomes a frame
``c^m = (v, r, u^m)`` with weight ``w^c = exp(-λ_c ||u^m||²)`` (``||u^m||`` the distance to the closest
point of the bumper mesh) and ``u^m = v⁻¹ ∘ robot`` (:func:`fit_manipulator_contact_model`).

Environment Contact Model: at training, environment contacts are sampled from the features with
``P(x | X, C^e) ∝ w_Z · w_CD · w_AG`` and related to the floor point below them
(:func:`environment_feature_weights`, :func:`sample_environment_contacts`); at prediction, candidates
drawn uniformly from the partial cloud are scored by the contact-frame density of Eq.
contact_frame_probability and the best is kept (:func:`place_environment_contacts`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import Evaluation
from pushtorch.models.frames import ContactFrames, embed_descriptors
from pushtorch.models.query import QueryDensity, build_query_density
from pushtorch.models.settings import ModelSettings
from pushtorch.parallel import return_freed_memory

Tensor = torch.Tensor

__all__ = [
    "ManipulatorContactModel",
    "bumper_contact_patch",
    "bumper_contact_patch_terms",
    "bumper_contacts",
    "closest_points_on_mesh",
    "environment_feature_weights",
    "feature_frames",
    "fit_manipulator_contact_model",
    "floor_relations",
    "patch_from_terms",
    "place_environment_contacts",
    "sample_environment_contacts",
    "sample_environment_contacts_in_blocks",
]


def closest_points_on_mesh(mesh: trimesh.Trimesh, points: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points on ``mesh``'s triangles to ``points (N, 3)`` and their distances ``(N,)``.

    open3d's ray-casting scene answers the query exactly (a BVH over the triangles), as the paper's
    "closest point of each triangular polygon in the mesh of the robot's manipulator".
    """
    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    query = o3d.core.Tensor(points.detach().cpu().numpy().astype(np.float32))
    closest = torch.from_numpy(scene.compute_closest_points(query)["points"].numpy()).to(points)
    return closest, (closest - points).norm(dim=-1)


def bumper_contacts(bumper: trimesh.Trimesh, points: Tensor, normals: Tensor, cutoff: float) -> tuple[Tensor, Tensor]:
    """Distances ``(N,)`` of ``points (N, 3)`` to the ``bumper`` mesh (same frame) and which touch it: within
    ``cutoff`` and with their outward ``normals (N, 3)`` not facing away from it (lineage: a point whose
    normal faces away from the link cannot be in contact with it). The one contact rule of the manipulator
    contact model, its motion kernels and a start the caller gives (paper, Manipulator Contact Model)."""
    closest, dist = closest_points_on_mesh(bumper, points)
    towards = ((closest - points) * normals).sum(-1) >= -1e-4
    return dist, (dist < cutoff) & towards


def feature_frames(features: SurfaceFeatures) -> se3.Pose:
    """The poses ``v = (p, q)`` of surface features, ``(N,)``."""
    return se3.Pose.unchecked(features.p, features.q)


@dataclass
class ManipulatorContactModel:
    """Frames ``c^m`` of the training object touching the bumper, stored in the object frame.

    ``frames.v`` are expressed relative to the training object's origin ``B^O`` (so the model can be
    moved with the object), ``frames.u`` relate each feature to the robot base pose.
    """

    frames: ContactFrames
    cutoff: float
    drop_off: float

    def robot_query(self, features: SurfaceFeatures, settings: ModelSettings, generator: torch.Generator | None,
                    method: Evaluation) -> QueryDensity:
        """This model's part of a push condition (paper, Query Density): the query density of the robot's start
        on a new cloud's features, projected onto the ground plane."""
        std = torch.full((2,), settings.descriptor_std)
        return build_query_density(
            self.frames, features, settings.query_kernels, std, settings.query_bandwidth,
            r_cutoff_std=settings.descriptor_cutoff_std, alpha_t=settings.alpha_t, project_planar=True,
            generator=generator, method=method,
        )


def fit_manipulator_contact_model(
    features: SurfaceFeatures,
    object_pose: se3.Pose,
    robot_pose: se3.Pose,
    bumper_mesh_world: trimesh.Trimesh,
    cutoff: float = 0.01,
    drop_off: float = 100.0,
    min_contacts: int = 10,
) -> ManipulatorContactModel:
    """Build the manipulator contact model (paper, Manipulator Contact Model).

    Args:
        features: surface features of the full training cloud, world frame.
        object_pose: ``B^O`` of the training object in the world.
        robot_pose: the robot base pose of the training placement (the paper's relation to L:
            the bumper is rigid on the base, so relating to the base is the same model and gives the
            start pose the simulator takes).
        bumper_mesh_world: the bumper's collision mesh at ``robot_pose``, world frame.
        cutoff: ``δ_c`` in metres; features farther from the bumper are dropped.
        drop_off: ``λ_c`` in m⁻²: ``w = exp(-λ_c d²)``.
        min_contacts: fewer surviving frames than this raises (the placement does not touch).
    Raises:
        InvalidParameterError: non-positive cut-off or negative drop-off.
        ModelError: fewer than ``min_contacts`` features touch the bumper.
    """
    if not cutoff > 0 or not drop_off >= 0:
        raise InvalidParameterError(f"contact cut-off must be > 0 and λ_c >= 0, got {cutoff}, {drop_off}")
    dist, keep = bumper_contacts(bumper_mesh_world, features.p, features.normal, cutoff)
    if int(keep.sum()) < min_contacts:
        raise ModelError(
            f"only {int(keep.sum())} surface features lie within {cutoff} m of the bumper "
            f"(need {min_contacts}): is the robot placed against the object?"
        )
    v_world = se3.Pose.unchecked(features.p[keep], features.q[keep])
    u = se3.relative(v_world, robot_pose)
    weight = torch.exp(-drop_off * dist[keep] ** 2)
    v_object = se3.compose(se3.inverse(object_pose), v_world)
    return ManipulatorContactModel(ContactFrames(v_object, features.r[keep], u, weight), cutoff, drop_off)


def bumper_contact_patch(points_robot: Tensor, depth: float = 0.01) -> Tensor:
    """Where and how the object sits on the bumper, ``(..., N, 3)`` points in the robot's base frame →
    ``(..., 3)``: the lateral extent ``(y_min, y_max)`` (m) of the surface the bumper meets first and its
    heading (rad): the angle of the least-squares line ``x = a + b y`` through it (0: square to the plate;
    positive: the object's left side is further ahead).

    The points within the plate's width and height band whose distance along the approach (base x) is within
    ``depth`` of the foremost one are the contact patch. Measured along the approach rather than from the
    plate, so a start backed off from the object (:func:`pushtorch.prediction.clear_robot_start`) and the
    training placement's 2 mm gap give the same patch. A cloud with no point in the band (a bumper that
    would miss it) falls back to the height band alone: the patch of the surface nearest the plate's line.

    Decision (docs/method.md, "Where the object sits on the bumper"): the paper's manipulator kernel holds
    one contact feature per push; the patch says where the object is along the 0.4 m plate, how wide it meets
    it and how square, which decide how a turning push slides it along the plate.
    """
    return patch_from_terms(*bumper_contact_patch_terms(points_robot, depth))


def bumper_contact_patch_terms(points_robot: Tensor, depth: float = 0.01) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`bumper_contact_patch` before its ``atan2``: ``(y_min, y_max, Σ dx·dy, Σ dy²)``, each ``(...,)``
    (:func:`patch_from_terms` makes the patch of them)."""
    from pushtorch.robot import bumper_geometry

    geometry = bumper_geometry()
    centre_y = float(geometry.mount.p[1]) + float(geometry.box_centre[1])
    half_width = float(geometry.size[1]) / 2
    z_low, z_high = geometry.z_range
    x, y, z = points_robot.unbind(-1)
    in_height = (z >= z_low) & (z <= z_high)
    band = in_height & ((y - centre_y).abs() <= half_width)
    band = torch.where(band.any(-1, keepdim=True), band, in_height)
    band = torch.where(band.any(-1, keepdim=True), band, torch.ones_like(band))
    inf = torch.full_like(x, math.inf)
    front = torch.where(band, x, inf).amin(-1, keepdim=True)
    patch = band & (x <= front + depth)
    weight = patch.to(x.dtype)
    count = weight.sum(-1, keepdim=True)
    mean_x = (weight * x).sum(-1, keepdim=True) / count
    mean_y = (weight * y).sum(-1, keepdim=True) / count
    dx, dy = (x - mean_x) * weight, (y - mean_y) * weight
    y_min, y_max = torch.where(patch, y, inf).amin(-1), torch.where(patch, y, -inf).amax(-1)
    return y_min, y_max, (dx * dy).sum(-1), (dy * dy).sum(-1)


def patch_from_terms(y_min: Tensor, y_max: Tensor, sxy: Tensor, syy: Tensor) -> Tensor:
    """The contact patch ``(..., 3)`` from :func:`bumper_contact_patch_terms`' reductions: its heading is their
    ``atan2``. Kept apart so blocks of pushes can gather the terms and take the ``atan2`` once over all of them
    (:func:`pushtorch.models.motion.fit_motion_model`): torch's vectorised and scalar ``atan2`` differ in the last
    bit, so where an element falls in the tensor decides its value."""
    # a patch of one point (or a line along x) has no heading: atan2(0, 0) = 0, square
    return torch.stack([y_min, y_max, torch.atan2(sxy, syy)], -1)


def floor_relations(v: se3.Pose) -> se3.Pose:
    """``u^e = v⁻¹ ∘ F`` with F the floor point straight below ``v`` (identity rotation, z = 0).

    The paper writes ``u^e = (0, 0, -z)``: the closest point of the floor is z below the feature. As a
    full relative pose it also holds the feature's orientation relative to the (level) floor.
    """
    floor = se3.Pose.unchecked(torch.cat([v.p[..., :2], torch.zeros_like(v.p[..., :1])], -1), torch.zeros_like(v.q))
    floor.q[..., 0] = 1.0
    return se3.relative(v, floor)


def environment_feature_weights(points: Tensor, chosen: Tensor | None = None) -> Tensor:
    """``w_Z · w_CD · w_AG`` for every feature (paper, Environment Contact Model), batched.

    Args:
        points: feature positions ``(..., N, 3)`` in the world (z above the floor).
        chosen: positions of the contacts placed so far ``(..., C, 3)`` (``w_AG``), or ``None``.
    Returns:
        ``(..., N)`` non-negative weights.
    """
    weight = _height_and_spread_weights(points)
    if chosen is not None and chosen.shape[-2] > 0:
        weight = weight * _apart_ratios(points, chosen).prod(-1)
    return weight


def _height_and_spread_weights(points: Tensor) -> Tensor:
    """``w_Z · w_CD`` ``(..., N)``: low and far from the centroid."""
    z = points[..., 2]
    w_z = torch.exp(-z / z.amax(-1, keepdim=True).clamp_min(1e-9))
    centroid = points.mean(-2, keepdim=True)
    d2 = ((points - centroid) ** 2).sum(-1)
    w_cd = d2 / d2.amax(-1, keepdim=True).clamp_min(1e-12)
    return w_z * w_cd


def _apart_ratios(points: Tensor, chosen: Tensor) -> Tensor:
    """``(..., N, C)`` each feature's squared distance to each chosen contact over the farthest feature's: their
    product over ``C`` is ``w_AG``. A column depends on its own contact only, so columns computed one contact
    at a time are the same numbers."""
    d2c = ((points.unsqueeze(-2) - chosen.unsqueeze(-3)) ** 2).sum(-1)  # (..., N, C)
    return d2c / d2c.amax(-2, keepdim=True).clamp_min(1e-12)


def sample_environment_contacts(
    points: Tensor, count: int, generator: torch.Generator | None = None
) -> Tensor:
    """Indices ``(..., count)`` of environment contacts drawn one after another from
    ``P(x | X, C^e) ∝ w_Z w_CD w_AG`` (each draw lowers the weight near what is already chosen).

    Batched over leading dims (e.g. one row per training push); the loop runs over the ``count``
    contact slots only.
    """
    batch = points.shape[:-2]
    flat = points.reshape(-1, *points.shape[-2:])
    rows = flat.shape[0]
    chosen_idx = sample_environment_contacts_in_blocks(lambda block: flat[block], rows, count, [slice(0, rows)],
                                                       generator, points.device)
    return chosen_idx.reshape(*batch, count)


#: How far training's resident memory may grow between two trims of the heap (:func:`return_freed_memory`).
TRIM_SLACK_MB = 256.0


def sample_environment_contacts_in_blocks(points_of: Callable[[slice], Tensor], rows: int, count: int,
                                          blocks: list[slice], generator: torch.Generator | None = None,
                                          device=None) -> Tensor:
    """:func:`sample_environment_contacts` of ``rows`` clouds whose points ``(B, N, 3)`` ``points_of(block)``
    makes for each of the consecutive ``blocks`` (slices covering ``range(rows)``): only one block's points
    and weights are held at a time. Indices ``(rows, count)``.

    Each of the ``count`` slots draws every row before the next slot, block after block: the rows of a
    ``torch.multinomial`` call draw one after another from the generator, so the draws, and the generator after
    them, are those of one call over all rows (and the same for any blocks)."""
    if count < 1:
        raise InvalidParameterError(f"number of environment contacts must be >= 1, got {count}")
    chosen_idx = torch.empty(rows, 0, dtype=torch.long, device=device)
    # one block (the usual case): its points, w_Z·w_CD and the w_AG columns of the contacts chosen so far are
    # kept between slots, each slot adding its new contact's column (the same numbers as computing them anew)
    held = None
    for _ in range(count):
        picks = []
        for block in blocks:
            if held is None:
                flat = points_of(block)
                base, ratios = _height_and_spread_weights(flat), flat.new_empty(*flat.shape[:-1], 0)
            else:
                flat, base, ratios = held
            chosen = torch.gather(flat, 1, chosen_idx[block].unsqueeze(-1).expand(-1, -1, 3))
            if chosen.shape[-2] > ratios.shape[-1]:  # the columns of the contacts not yet in ratios
                ratios = torch.cat([ratios, _apart_ratios(flat, chosen[:, ratios.shape[-1]:])], -1)
            weight = base * ratios.prod(-1) if ratios.shape[-1] else base
            # a degenerate cloud (all weight zero) falls back to a uniform draw rather than failing
            weight = torch.where(weight.sum(-1, keepdim=True) > 0, weight, torch.ones_like(weight))
            picks.append(se3.multinomial(weight, 1, generator))
            if len(blocks) == 1:
                held = (flat, base, ratios)
            else:  # the block's tensors are freed: their pages go back once the heap has grown (parallel.py)
                del flat, base, ratios, chosen, weight
                return_freed_memory(TRIM_SLACK_MB)
        chosen_idx = torch.cat([chosen_idx, torch.cat(picks)], -1)
    return chosen_idx


def place_environment_contacts(
    features: SurfaceFeatures,
    kernels_r: Tensor,
    kernels_u: se3.Pose,
    bandwidth,
    count: int = 5,
    samples: int = 100,
    generator: torch.Generator | None = None,
) -> ContactFrames:
    """Environment contacts on a new cloud (paper, Environment Contact Model, prediction time).

    Each of the ``count`` contacts is the best of ``samples`` candidates drawn uniformly from the
    cloud's features, scored by the contact-frame density ``P(c)`` (Eq. contact_frame_probability)
    whose kernels are the training environment frames ``(r, u^e)``. All ``count × samples``
    candidates are scored in one batched call; trial rounds widen the density if none is covered.

    Args:
        features: the cloud's surface features (world frame, z above the floor).
        kernels_r, kernels_u: the training environment frames' descriptors ``(N, 2)`` and relations ``(N,)``.
        bandwidth: a :class:`pushtorch.kde.KernelBandwidth` with ``r_std`` (the contact-frame kernel;
            descriptors are compared after :func:`~pushtorch.models.frames.embed_descriptors`).
    Returns:
        ``count`` frames ``(v, r, u^e)`` with weight ``exp(log P(c))`` (relative).
    """
    from pushtorch.kde import PoseKDE

    if count < 1 or samples < 1:
        raise InvalidParameterError(f"need at least one contact and one sample, got {count}, {samples}")
    density = PoseKDE(kernels_u, bandwidth, descriptors=embed_descriptors(kernels_r))
    pick = torch.randint(len(features), (count, samples), generator=generator,
                         device=se3.draw_device(generator, features.p.device)).to(features.p.device)
    v = se3.Pose.unchecked(features.p[pick], features.q[pick])  # (count, samples)
    u = floor_relations(v)
    r = embed_descriptors(features.r[pick])
    log_p = density.log_prob(u, r, method=Evaluation.FAST)  # (count, samples)
    if not torch.isfinite(log_p).any():  # trial rounds only when no pair survives: one pass otherwise
        density = density.fit_trial_rounds(u.reshape(1, -1), r.reshape(1, -1, 2))
        log_p = density.log_prob(u, r)
    best = log_p.argmax(-1)
    rows = torch.arange(count, device=best.device)
    chosen = pick[rows, best]
    frames_v = se3.Pose.unchecked(features.p[chosen], features.q[chosen])
    return ContactFrames(frames_v, features.r[chosen], floor_relations(frames_v), log_p[rows, best].exp())
