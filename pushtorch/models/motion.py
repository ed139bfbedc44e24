"""Motion model: contact-frame motions from push records and their product of experts (paper, §Motion Model).

Training (:func:`fit_motion_model`). For every push record of one action, contact frames are placed on
the training object at its initial pose ``B0``: manipulator frames where the features touch the bumper
at the push's robot start pose (weights ``exp(-λ_c d²)`` as the contact model), environment frames drawn
with ``w_Z w_CD w_AG``. Contact frames are rigidly attached to the object, so each one's local motion
follows from the object's motion alone: ``m = w0⁻¹ ∘ w1 = w0⁻¹ ∘ W ∘ w0`` with ``W = B1 ∘ B0⁻¹``.
A kernel stores ``(r, u, m, g)``.

Prediction (:class:`~pushtorch.models.experts.MotionDensity`). For each contact frame ``c_e = (v_e, r_e, u_e)``
placed on the new object and the estimated object pose ``B0'`` (``h_e = w_e⁻¹ ∘ B0'``), the training kernel ``j`` of the
same kind becomes a kernel over the object's final pose ``w_e ∘ m_j ∘ h_e`` ("shifted by h into the
same motion space") with weight ``K^c(c_e | c_j) / P(c_e)`` (Eq. pdf_motion, the contact-frame kernel
compares ``r`` and ``u``, Eq. contact_frame_probability). The experts' product (Eq. poe) with
``w^P = N_K^{c^e} / N_K^{c^m}`` for the manipulator expert (as an exponent, below) is optimised by
simulated annealing.

Decision (docs/method.md): motions are expressed in the robot's start frame (:func:`motion_frames`):
every contact frame's motion is tracked in the frame of the pusher that causes it, ``w = R0``, not in
the feature's own orientation ``v`` nor at the contact point. Two measurements led here. In the
feature's orientation, horizontal faces have no defined heading and transferred motions rotate by it
(environment experts 17–20 cm off on the cube). At the contact point with the robot's heading, a
kernel's motion conjugated to a test contact ``δ`` away gains ``(I − R_D) δ`` under a turning push
(a few cm within the ``g`` cut-off), so experts disagree: on 30 fresh cube pushes H_acc 0.086 against
0.067 in the robot frame (mean training motion: 0.064), transfer to the prisms unchanged or better.
The contact frames keep their role as the paper's conditioning: which training pushes a contact
resembles (``K^c`` over ``u``, ``r`` and ``g``) sets every kernel's weight in its expert.

Decision (docs/method.md): the contact-frame kernel also compares ``g``, the frame's position in the
robot's start frame. The paper's ``u^e`` (the floor below the frame) cannot tell a contact at the
front edge from one at the back edge, and under a turning push those move differently: a motion ``D``
conjugated by an offset ``δ`` between frames gains ``(I − R_D) δ``, up to ~19 cm after the 40° turn of
the ±10°/s actions. Measured on the cube, environment experts' kernel means were 18–20 cm from the
truth without ``g`` and the product was pulled off the manipulator expert's (0.9 cm) answer.
``g`` is observable at prediction (the robot start pose is chosen first) and transfers across objects
as "where the contact is relative to the pusher".

Decisions of issue 17 (docs/method.md): every kernel also carries its push's contact patch on the bumper
(:func:`~pushtorch.models.contact.bumper_contact_patch`), compared by ``K^c`` beside ``(u, r, g)``, so
the experts weigh the training pushes whose object sat where this one sits; and ``w^P`` weighs the experts
as exponents (:func:`expert_exponents`) rather than as a constant added to the log product.

The product of experts these kernels make for a new push condition, and its annealing, are in
:mod:`pushtorch.models.experts`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import KernelBandwidth, PoseKDE
from pushtorch.models.contact import (
    bumper_contact_patch_terms,
    bumper_contacts,
    floor_relations,
    patch_from_terms,
    place_environment_contacts,
    sample_environment_contacts_in_blocks,
)
from pushtorch.models.frames import ContactFrames, embed_descriptors
from pushtorch.models.settings import ModelSettings

Tensor = torch.Tensor

__all__ = [
    "CONTACT_DESCRIPTOR_DIM",
    "MotionKernels",
    "MotionModel",
    "contact_distances",
    "contact_log_weights",
    "expert_exponents",
    "fit_motion_model",
    "local_motions",
    "nearest_in_contact",
    "motion_frames",
    "TRAINING_BLOCK_PAIRS",
    "training_blocks",
]


@dataclass
class MotionKernels:
    """Training kernels of one contact kind.

    Attributes:
        r: descriptors ``(N, 2)``.
        u: relations ``(N,)`` (to the robot for manipulator frames, to the floor for environment frames).
        m: local motions ``v0⁻¹ ∘ v1`` ``(N,)``.
        g: positions ``(N, 3)`` of the frames in the robot's start frame (see :class:`MotionDensity`).
        patch: ``(N, 3)`` where and how the object sat on the bumper in the kernel's push: the lateral extent
            and heading of its contact patch in the robot's start frame
            (:func:`~pushtorch.models.contact.bumper_contact_patch`).
    """

    r: Tensor
    u: se3.Pose
    m: se3.Pose
    g: Tensor
    patch: Tensor
    #: ``(N,)`` int64 the index (within its action) of each kernel's push, where known: set by
    #: :func:`fit_motion_model` for the bandwidth search, not kept in model files
    push: Tensor | None = None
    #: ``(N, 2)`` the ground friction coefficient and the mass (kg) its push was simulated with (kept in
    #: model files; what :mod:`pushtorch.models.conditioning` groups the kernels by); None where unknown
    physics: Tensor | None = None
    #: ``(N, 3)`` where the robot itself ended in its push, in its start frame (x, y m, yaw rad): what the
    #: robot's odometry reports, kept in model files (:mod:`pushtorch.models.conditioning`); None where unknown
    robot_motion: Tensor | None = None
    #: ``(N,)`` each kernel's log weight from conditioning on observed pushes (0 everywhere, or None: the
    #: trained model; :mod:`pushtorch.models.conditioning`), added to its contact weight in every expert
    log_weight: Tensor | None = None

    def __len__(self) -> int:
        return int(self.r.shape[0])

    def take(self, index: Tensor) -> MotionKernels:
        def pick(t: Tensor | None) -> Tensor | None:
            return None if t is None else t[index]

        return MotionKernels(self.r[index], self.u.take(index), self.m.take(index), self.g[index], self.patch[index],
                             pick(self.push), pick(self.physics), pick(self.robot_motion), pick(self.log_weight))

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> MotionKernels:
        """The kernels on ``device`` and in the floating ``dtype`` (``push`` keeps its integer dtype)."""
        def move(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(device, dtype)

        return MotionKernels(self.r.to(device, dtype), self.u.to(device, dtype), self.m.to(device, dtype),
                             self.g.to(device, dtype), self.patch.to(device, dtype),
                             None if self.push is None else self.push.to(device), move(self.physics),
                             move(self.robot_motion), move(self.log_weight))

    def arrays(self, prefix: str) -> dict[str, Tensor]:
        out = {
            f"{prefix}.r": self.r, f"{prefix}.u_p": self.u.p, f"{prefix}.u_q": self.u.q,
            f"{prefix}.m_p": self.m.p, f"{prefix}.m_q": self.m.q, f"{prefix}.g": self.g,
            f"{prefix}.patch": self.patch,
        }
        if self.physics is not None:
            out[f"{prefix}.physics"] = self.physics
        if self.robot_motion is not None:
            out[f"{prefix}.robot_motion"] = self.robot_motion
        if self.log_weight is not None:
            out[f"{prefix}.log_weight"] = self.log_weight
        return out

    @staticmethod
    def from_arrays(arrays: dict[str, Tensor], prefix: str) -> MotionKernels:
        return MotionKernels(
            arrays[f"{prefix}.r"],
            se3.Pose.unchecked(arrays[f"{prefix}.u_p"], arrays[f"{prefix}.u_q"]),
            se3.Pose.unchecked(arrays[f"{prefix}.m_p"], arrays[f"{prefix}.m_q"]),
            arrays[f"{prefix}.g"],
            arrays[f"{prefix}.patch"],
            physics=arrays.get(f"{prefix}.physics"),
            robot_motion=arrays.get(f"{prefix}.robot_motion"),
            log_weight=arrays.get(f"{prefix}.log_weight"),
        )


@dataclass
class MotionModel:
    """Motion kernels of one action ``a = (speed m/s, yaw rate rad/s)`` for both contact kinds.

    ``mean_motion`` is the training pushes' average object motion in the robot's start frame
    (``R0⁻¹ ∘ B1 ∘ B0⁻¹ ∘ R0``), kept for the mean-motion baseline.
    """

    action: Tensor  # (2,)
    manipulator: MotionKernels
    environment: MotionKernels
    mean_motion: se3.Pose

    def environment_frames(self, features: SurfaceFeatures, settings: ModelSettings,
                           generator: torch.Generator | None) -> ContactFrames:
        """This model's part of a push condition (paper, Environment Contact Model, prediction time): the
        environment contacts placed on a new cloud's features by (at most ``environment_kernels`` of) this
        action's environment kernels (:func:`~pushtorch.models.contact.place_environment_contacts`)."""
        kernels = self.environment
        if len(kernels) > settings.environment_kernels:
            kernels = kernels.take(torch.randperm(len(kernels), generator=generator)[:settings.environment_kernels])
        return place_environment_contacts(
            features, kernels.r, kernels.u, settings.environment_contact_bandwidth,
            settings.environment_contacts, settings.environment_samples, generator,
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> MotionModel:
        """The model on ``device`` and in ``dtype``."""
        return MotionModel(self.action.to(device, dtype), self.manipulator.to(device, dtype),
                           self.environment.to(device, dtype), self.mean_motion.to(device, dtype))


def local_motions(frames: se3.Pose, world_motion: se3.Pose) -> se3.Pose:
    """``m = w⁻¹ ∘ W ∘ w``: the motion of a frame ``w`` (world) carried by the object's world motion
    ``W = B1 ∘ B0⁻¹``, expressed in the frame itself, so ``w ∘ m = W ∘ w``; batch dims broadcast."""
    return se3.compose(se3.inverse(frames), se3.compose(world_motion, frames))


def motion_frames(points: Tensor, robot_start: se3.Pose) -> se3.Pose:
    """The frames the motions of contacts at ``points (*P, 3)`` are expressed in: the robot's start pose
    (broadcast to ``*P``), see the module docstring."""
    shape = torch.broadcast_shapes(points.shape[:-1], robot_start.batch_shape)
    return se3.Pose.unchecked(robot_start.p.expand(*shape, 3), robot_start.q.expand(*shape, 4))


#: Feature-push pairs :func:`fit_motion_model` places at a time (a block of pushes × the cloud's features): its
#: points, normals, contact weights and draws, some 100 bytes a pair, instead of all pushes' at once.
TRAINING_BLOCK_PAIRS = 1 << 20


def training_blocks(n_push: int, n_features: int, block_pushes: int | None = None) -> list[slice]:
    """Consecutive slices covering ``range(n_push)``, each of ``block_pushes`` to ``2 block_pushes - 1`` pushes
    (all of them in one when there are fewer than ``2 block_pushes``); ``block_pushes`` None: as many as make
    :data:`TRAINING_BLOCK_PAIRS` pairs with ``n_features`` features (at least 2)."""
    if block_pushes is None:
        block_pushes = max(2, TRAINING_BLOCK_PAIRS // max(n_features, 1))
    if block_pushes < 1:
        raise InvalidParameterError(f"block_pushes must be >= 1, got {block_pushes}")
    count = max(1, n_push // block_pushes)
    edges = [k * n_push // count for k in range(count + 1)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _manipulator_picks(features: SurfaceFeatures, object_in_robot: se3.Pose, bumper: trimesh.Trimesh,
                       blocks: list[slice], per_push: int, cutoff: float, drop_off: float,
                       generator: torch.Generator | None) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, ...]]:
    """The manipulator frames of :func:`fit_motion_model`, block by block of pushes: the touching pushes' rows
    and picked features ``(K,)``, the picked features' positions in the robot's start frame ``(K, 3)`` and every
    push's :func:`~pushtorch.models.contact.bumper_contact_patch_terms` ``(P,)`` each.

    Weights beyond the cut-off are exactly 0, so only the features within ``cutoff`` (and a float margin) of
    the bumper's bounding box are measured against its mesh; the others keep weight 0. Every touching push
    draws its picks from its full row of ``N`` weights, one ``torch.multinomial`` call per block: rows draw one
    after another, so the picks, and the generator after them, are those of one call over all pushes."""
    lo, hi = torch.tensor(bumper.bounds, dtype=features.p.dtype, device=features.p.device)
    margin = cutoff + 1e-3  # the distances are measured in float32
    rows, picks, points, terms = [], [], [], []
    for block in blocks:
        pose = object_in_robot.take(block)
        points_robot = se3.apply(pose.unsqueeze(-1), features.p)  # (B, N, 3)
        terms.append(bumper_contact_patch_terms(points_robot, cutoff))
        near = ((points_robot >= lo - margin) & (points_robot <= hi + margin)).all(-1)  # (B, N)
        weight = torch.zeros(points_robot.shape[:-1], dtype=points_robot.dtype, device=points_robot.device)
        if near.any():
            normals = se3.apply(se3.Pose.unchecked(torch.zeros_like(pose.p), pose.q).unsqueeze(-1), features.normal)
            dist, touching = bumper_contacts(bumper, points_robot[near], normals[near], cutoff)
            weight[near] = torch.exp(-drop_off * dist**2) * touching
        touched = (weight.sum(-1) > 0).nonzero().squeeze(-1)
        if len(touched) == 0:
            continue
        pick = torch.multinomial(weight[touched], per_push, replacement=True, generator=generator)
        touched = touched.unsqueeze(-1).expand_as(pick).reshape(-1)
        pick = pick.reshape(-1)
        rows.append(touched + block.start)
        picks.append(pick)
        points.append(points_robot[touched, pick])
    empty = torch.empty(0, dtype=torch.long, device=features.p.device)
    return (torch.cat(rows) if rows else empty, torch.cat(picks) if picks else empty,
            torch.cat(points) if points else features.p[:0], tuple(torch.cat(t) for t in zip(*terms, strict=True)))


def fit_motion_model(
    features_object: SurfaceFeatures,
    initial: se3.Pose,
    final: se3.Pose,
    robot_start: se3.Pose,
    bumper_mesh_robot: trimesh.Trimesh,
    action: Tensor,
    environment_contacts: int = 10,
    manipulator_kernels_per_push: int = 1,
    contact_cutoff: float = 0.01,
    contact_drop_off: float = 100.0,
    generator: torch.Generator | None = None,
    physics: Tensor | None = None,
    robot_motion: Tensor | None = None,
    block_pushes: int | None = None,
) -> MotionModel:
    """Motion kernels of one action from its push records (paper, Motion Model; Environment Contact Model).

    Args:
        features_object: surface features of the full training cloud in the object frame ``B^O``.
        initial, final: object poses ``(P,)`` before and after each push (world).
        robot_start: robot base poses ``(P,)`` at the start of each push (world).
        bumper_mesh_robot: the bumper's collision mesh in the robot base frame.
        action: ``(2,)`` the action these pushes share.
        environment_contacts: environment frames per push (paper: 10).
        manipulator_kernels_per_push: manipulator frames drawn per push among those touching the bumper.
        physics: ``(P, 2)`` each push's ground friction and mass (kg): every kernel keeps its push's
            (:attr:`MotionKernels.physics`), or None.
        robot_motion: ``(P, 3)`` where the robot ended in each push, in its start frame (x, y, yaw), or None.
        block_pushes: pushes placed at a time (:func:`training_blocks`; None: as many as make
            :data:`TRAINING_BLOCK_PAIRS` feature-push pairs). The model is the same, bit for bit, for every
            value; memory grows with it, not with the number of pushes.
    Raises:
        ModelError: no push has a feature within ``contact_cutoff`` of the bumper.
    """
    n_push = initial.p.shape[0]
    if n_push == 0:
        raise InvalidParameterError("a motion model needs at least one push record")
    x = se3.Pose.unchecked(features_object.p, features_object.q)  # (N,)
    world_motion = se3.compose(final, se3.inverse(initial))  # W = B1 ∘ B0^-1, (P,)
    blocks = training_blocks(n_push, len(x.p), block_pushes)

    # Manipulator frames: features within the cut-off of the bumper at each push's start pose.
    robot_in_object = se3.relative(initial, robot_start)  # (P,)
    rows, pick, points, terms = _manipulator_picks(features_object, se3.inverse(robot_in_object), bumper_mesh_robot,
                                                   blocks, manipulator_kernels_per_push, contact_cutoff,
                                                   contact_drop_off, generator)
    if len(rows) == 0:
        raise ModelError(
            f"no push record has a training feature within {contact_cutoff} m of the bumper at its start pose"
        )
    patches = patch_from_terms(*terms)  # (P, 3)
    xm = se3.Pose.unchecked(x.p[pick], x.q[pick])
    manipulator = MotionKernels(
        features_object.r[pick],
        se3.relative(xm, robot_in_object.take(rows)),  # u^m = v^-1 ∘ robot, frame-invariant form
        local_motions(
            motion_frames(se3.apply(initial.take(rows), xm.p), robot_start.take(rows)), world_motion.take(rows)
        ),
        points,
        patches[rows],
        rows,
        None if physics is None else physics[rows].to(x.p.dtype),
        None if robot_motion is None else robot_motion[rows].to(x.p.dtype),
    )

    # Environment frames: drawn per push at the push's initial pose (z above the floor matters).
    env_idx = sample_environment_contacts_in_blocks(
        lambda block: se3.apply(initial.take(block).unsqueeze(-1), x.p),  # (B, N, 3)
        n_push, environment_contacts, blocks, generator, x.p.device,
    ).reshape(-1)
    env_rows = torch.arange(n_push, device=env_idx.device).repeat_interleave(environment_contacts)
    xe = se3.Pose.unchecked(x.p[env_idx], x.q[env_idx])
    v_world = se3.compose(initial.take(env_rows), xe)
    environment = MotionKernels(
        features_object.r[env_idx],
        floor_relations(v_world),
        local_motions(motion_frames(v_world.p, robot_start.take(env_rows)), world_motion.take(env_rows)),
        se3.apply(se3.inverse(robot_start.take(env_rows)), v_world.p),
        patches[env_rows],
        env_rows,
        None if physics is None else physics[env_rows].to(x.p.dtype),
        None if robot_motion is None else robot_motion[env_rows].to(x.p.dtype),
    )
    in_robot = se3.compose(se3.inverse(robot_start), se3.compose(world_motion, robot_start))
    return MotionModel(torch.as_tensor(action, dtype=x.p.dtype), manipulator, environment, se3.mean_pose(in_robot))


def expert_exponents(n_manipulator_kernels: int, n_environment_kernels: int, n_environment_experts: int,
                     pool_sharpness: float = 1.0, dtype: torch.dtype = torch.float32) -> Tensor:
    """``(1 + E,)`` exponents ``γ_e`` of the product's experts, manipulator first: the paper's weights
    ``w^P = N_K^{c^e} / N_K^{c^m}`` for the manipulator expert and 1 for each environment expert, scaled to
    sum to ``pool_sharpness``.

    Decision (docs/method.md, "Expert weights"): the paper adds ``log w^P`` to the product, a constant that
    moves no mode and cancels in every normalised density. As exponents they weigh the experts' evidence:
    with ``Σγ = 1`` the product is a logarithmic opinion pool, as wide as one expert, where the paper's
    product of ``1 + E`` experts (each exponent 1) is ``√(1 + E)`` times narrower than any of them although
    its experts re-use the same training pushes.
    """
    if pool_sharpness <= 0 or not math.isfinite(pool_sharpness):
        raise InvalidParameterError(f"pool_sharpness must be a positive number, got {pool_sharpness!r}")
    w = torch.ones(1 + n_environment_experts, dtype=torch.float64)
    w[0] = n_environment_kernels / max(n_manipulator_kernels, 1)
    return (pool_sharpness * w / w.sum()).to(dtype)


#: Descriptor dims of the contact-frame kernel ``K^c`` of the motion model: embedded curvatures (2), the
#: frame's position in the robot's start frame ``g`` (3) and the push's contact patch on the bumper: its
#: lateral extent (2) and heading (1).
CONTACT_DESCRIPTOR_DIM = 8


def contact_log_weights(frames: ContactFrames, kernels: MotionKernels, robot_start: se3.Pose,
                        contact_bandwidth: KernelBandwidth, patch: Tensor) -> Tensor:
    """``(F, N)`` log ``K^c(c_e | c_j)``: how much each of the frames ``c_e`` (world) resembles each training
    kernel ``c_j`` of one contact kind, over ``(u, r, g, patch)`` (Eq. contact_frame_probability and the
    ``g`` and patch terms of the module docstring), each frame's contact density widened by its own trial
    rounds until some kernel reaches it. ``patch``: ``(3,)`` this push's contact patch on the bumper
    (:func:`~pushtorch.models.contact.bumper_contact_patch`).

    Many pushes at once: frames ``(C, F)``, ``robot_start (C,)`` and ``patch (C, 3)`` give ``(C, F, N)``, each
    push's frames fitted as they are alone (a planner's candidates, one call for all of them)."""
    batched = robot_start.p.dim() == 2
    batch = frames.r.shape[:-1] if batched else frames.r.reshape(-1, 2).shape[:1]  # (C, F) or (F,)
    n_kernels = len(kernels)
    dim = CONTACT_DESCRIPTOR_DIM
    contact_kde = PoseKDE(
        se3.Pose.unchecked(kernels.u.p.expand(*batch, n_kernels, 3), kernels.u.q.expand(*batch, n_kernels, 4)),
        contact_bandwidth,
        descriptors=torch.cat([embed_descriptors(kernels.r), kernels.g, kernels.patch], -1).expand(
            *batch, n_kernels, dim),
    )
    query_u = se3.Pose.unchecked(frames.u.p.reshape(*batch, 1, 3), frames.u.q.reshape(*batch, 1, 4))
    to_robot = se3.inverse(robot_start)
    if batched:  # each push's frames into its own start frame
        to_robot = to_robot.unsqueeze(-1)
    frame_g = se3.apply(to_robot, frames.v.p.reshape(*batch, 3))
    frame_patch = torch.as_tensor(patch, dtype=frame_g.dtype, device=frame_g.device).reshape(-1, 3)
    if batched:
        frame_patch = frame_patch.unsqueeze(-2)
    query_r = torch.cat([embed_descriptors(frames.r.reshape(*batch, 2)), frame_g, frame_patch.expand(*batch, 3)],
                        -1).unsqueeze(-2)
    _, log_w = contact_kde.fitted_log_kernels(query_u, query_r)
    return log_w.squeeze(-2)


def contact_distances(frames: ContactFrames, kernels: MotionKernels, robot_start: se3.Pose,
                      contact_bandwidth: KernelBandwidth, patch: Tensor) -> Tensor:
    """``(F, N)`` squared distances, in the contact kernel's standard deviations, from each of the frames
    ``c_e`` (world) to each training kernel ``c_j`` over ``(u, r, g, patch)``: what ``K^c`` compares, without
    its cut-offs and trial rounds (a contact metres from every training one keeps a finite, large distance).
    The rotation of ``u`` counts by its angle over ``rot_std``."""
    n_frames = frames.r.reshape(-1, 2).shape[0]
    dtype = kernels.r.dtype
    u_p, u_q = frames.u.p.reshape(-1, 1, 3).to(dtype), frames.u.q.reshape(-1, 1, 4).to(dtype)
    d2 = ((u_p - kernels.u.p.unsqueeze(0)) ** 2).sum(-1) / contact_bandwidth.p_std**2
    angle = se3.angle_between(u_q.expand(n_frames, len(kernels), 4), kernels.u.q.unsqueeze(0).expand(n_frames, -1, 4))
    d2 = d2 + (angle / contact_bandwidth.rot_std) ** 2
    frame_g = se3.apply(se3.inverse(robot_start), frames.v.p.reshape(-1, 3)).to(dtype)
    frame_patch = torch.as_tensor(patch, dtype=dtype, device=frame_g.device).reshape(1, 3).expand(n_frames, 3)
    query = torch.cat([embed_descriptors(frames.r.reshape(-1, 2).to(dtype)), frame_g, frame_patch], -1)
    known = torch.cat([embed_descriptors(kernels.r), kernels.g, kernels.patch], -1)
    std = torch.as_tensor(contact_bandwidth.r_std, dtype=dtype, device=known.device)
    return d2 + torch.cdist(query / std, known / std) ** 2


def nearest_in_contact(frames: ContactFrames, kernels: MotionKernels, robot_start: se3.Pose,
                       contact_bandwidth: KernelBandwidth, patch: Tensor, count: int) -> MotionKernels:
    """The ``count`` kernels nearest in contact (:func:`contact_distances`) to any of ``frames``: the kernel
    budget of a prediction (all of them when there are no more than ``count``).

    Decision (docs/method.md, "Kernel budget"): a model pooled over many shapes holds far more kernels than a
    prediction evaluates, and the ones that weigh in an expert are those whose contact resembles this push's;
    a uniform draw would keep mostly kernels ``K^c`` then weighs near zero. Keeping the nearest is the
    truncated kernel density (the dropped kernels are the lightest)."""
    if len(kernels) <= count:
        return kernels
    d2 = contact_distances(frames, kernels, robot_start, contact_bandwidth, patch).amin(0)
    return kernels.take(torch.topk(d2, count, largest=False).indices.sort().values)

