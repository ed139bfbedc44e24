"""Motion model: contact-frame motions from push records and their product of experts (paper, §Motion Model).

Training (:func:`fit_motion_model`). For every push record of one action, contact frames are placed on
the training object at its initial pose ``B0``: manipulator frames where the features touch the bumper
at the push's robot start pose (weights ``exp(-λ_c d²)`` as the contact model), environment frames drawn
with ``w_Z w_CD w_AG``. Contact frames are rigidly attached to the object, so each one's local motion
follows from the object's motion alone: ``m = w0⁻¹ ∘ w1 = w0⁻¹ ∘ W ∘ w0`` with ``W = B1 ∘ B0⁻¹``.
A kernel stores ``(r, u, m, g)``.

Prediction (:class:`MotionDensity`). For each contact frame ``c_e = (v_e, r_e, u_e)`` placed on the new
object and the estimated object pose ``B0'`` (``h_e = w_e⁻¹ ∘ B0'``), the training kernel ``j`` of the
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

Fast path: :func:`anneal_motion_densities` anneals the products of experts of many push conditions in
one batch; each kind's kernels, shared by all of its experts, are evaluated once per query
(:class:`pushtorch.kde.SharedKernelProduct`), and the candidates are polished by mean shift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import trimesh

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule, anneal, polish_candidates
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.features import SurfaceFeatures
from pushtorch.kde import KernelBandwidth, PoseKDE, ProductOfExperts, SharedKernelProduct
from pushtorch.models.contact import (
    bumper_contact_patch,
    bumper_contacts,
    floor_relations,
    sample_environment_contacts,
)
from pushtorch.models.frames import ContactFrames, embed_descriptors

Tensor = torch.Tensor

__all__ = [
    "CONTACT_DESCRIPTOR_DIM",
    "MotionDensity",
    "MotionKernels",
    "MotionModel",
    "anneal_motion_densities",
    "contact_distances",
    "contact_log_weights",
    "expert_exponents",
    "fit_motion_model",
    "local_motions",
    "nearest_in_contact",
    "motion_frames",
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
            physics=arrays[f"{prefix}.physics"],
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
    Raises:
        ModelError: no push has a feature within ``contact_cutoff`` of the bumper.
    """
    n_push = initial.p.shape[0]
    if n_push == 0:
        raise InvalidParameterError("a motion model needs at least one push record")
    x = se3.Pose.unchecked(features_object.p, features_object.q)  # (N,)
    world_motion = se3.compose(final, se3.inverse(initial))  # W = B1 ∘ B0^-1, (P,)

    # Manipulator frames: features within the cut-off of the bumper at each push's start pose.
    robot_in_object = se3.relative(initial, robot_start)  # (P,)
    points_robot = se3.apply(se3.inverse(robot_in_object).unsqueeze(-1), x.p)  # (P, N, 3)
    normals_robot = se3.apply(
        se3.Pose.unchecked(torch.zeros_like(robot_in_object.p), se3.inverse(robot_in_object).q).unsqueeze(-1),
        features_object.normal,
    )
    dist, touching = bumper_contacts(bumper_mesh_robot, points_robot.reshape(-1, 3), normals_robot.reshape(-1, 3),
                                     contact_cutoff)
    dist, touching = dist.reshape(n_push, -1), touching.reshape(n_push, -1)
    weight = torch.exp(-contact_drop_off * dist**2) * touching
    touched = weight.sum(-1) > 0
    if not touched.any():
        raise ModelError(
            f"no push record has a training feature within {contact_cutoff} m of the bumper at its start pose"
        )
    patches = bumper_contact_patch(points_robot, contact_cutoff)  # (P, 3)
    rows = touched.nonzero().squeeze(-1)
    pick = torch.multinomial(weight[rows], manipulator_kernels_per_push, replacement=True, generator=generator)
    rows = rows.unsqueeze(-1).expand_as(pick).reshape(-1)
    pick = pick.reshape(-1)
    xm = se3.Pose.unchecked(x.p[pick], x.q[pick])
    manipulator = MotionKernels(
        features_object.r[pick],
        se3.relative(xm, robot_in_object.take(rows)),  # u^m = v^-1 ∘ robot, frame-invariant form
        local_motions(
            motion_frames(se3.apply(initial.take(rows), xm.p), robot_start.take(rows)), world_motion.take(rows)
        ),
        points_robot[rows, pick],
        patches[rows],
        rows,
        None if physics is None else physics[rows].to(x.p.dtype),
        None if robot_motion is None else robot_motion[rows].to(x.p.dtype),
    )

    # Environment frames: drawn per push at the push's initial pose (z above the floor matters).
    world_points = se3.apply(initial.unsqueeze(-1), x.p)  # (P, N, 3)
    env_idx = sample_environment_contacts(world_points, environment_contacts, generator).reshape(-1)
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
    (:func:`~pushtorch.models.contact.bumper_contact_patch`)."""
    n_frames, n_kernels = frames.r.reshape(-1, 2).shape[0], len(kernels)
    dim = CONTACT_DESCRIPTOR_DIM
    contact_kde = PoseKDE(
        se3.Pose.unchecked(kernels.u.p.expand(n_frames, n_kernels, 3), kernels.u.q.expand(n_frames, n_kernels, 4)),
        contact_bandwidth,
        descriptors=torch.cat([embed_descriptors(kernels.r), kernels.g, kernels.patch], -1).expand(
            n_frames, n_kernels, dim),
    )
    query_u = se3.Pose.unchecked(frames.u.p.reshape(-1, 1, 3), frames.u.q.reshape(-1, 1, 4))
    frame_g = se3.apply(se3.inverse(robot_start), frames.v.p.reshape(-1, 3))
    frame_patch = torch.as_tensor(patch, dtype=frame_g.dtype, device=frame_g.device).reshape(1, 3)
    query_r = torch.cat([embed_descriptors(frames.r.reshape(-1, 2)), frame_g, frame_patch.expand(len(frame_g), 3)],
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


def _block_diagonal(blocks: list[Tensor], fill: float) -> Tensor:
    """Matrices placed along the diagonal of one matrix, ``fill`` elsewhere."""
    rows, cols = sum(b.shape[0] for b in blocks), sum(b.shape[1] for b in blocks)
    out = torch.full((rows, cols), fill, dtype=blocks[0].dtype, device=blocks[0].device)
    r = c = 0
    for b in blocks:
        out[r : r + b.shape[0], c : c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return out


@dataclass
class MotionPrediction:
    """Result of :meth:`MotionDensity.predict`: the best final pose and the annealed candidates."""

    final_pose: se3.Pose  # ()
    log_prob: Tensor  # ()
    anneal: AnnealResult


class MotionDensity:
    """The density ``P(B1 | a)`` over the object's final pose (Eq. poe), built for one push condition.

    Args:
        model: the action's motion kernels.
        manipulator_frame: the manipulator contact frame ``c^m`` on the new object (one frame, world).
        environment_frames: environment contact frames ``(E,)`` on the new object (world).
        object_pose: the estimated initial object pose ``B0'``.
        robot_start: the robot's start pose for this push.
        contact_patch: ``(3,)`` where and how the object sits on the bumper at ``robot_start``
            (:func:`~pushtorch.models.contact.bumper_contact_patch` of the observed cloud).
        contact_bandwidth: bandwidth of the contact-frame kernel ``K^c`` over ``(u, r, g, patch)``: ``r``
            compared after :func:`~pushtorch.models.frames.embed_descriptors` (2 stds), ``g``, the frame's
            position in the robot's start frame (3 stds, m), and the contact patch (2 stds, m, and 1, rad) — see the
            module docstring.
        motion_bandwidth: bandwidth of the motion kernels over the final pose.
        drop_cut_kernels: leave out the kernels whose contact weight ``K^c`` is zero (cut off) before
            anything is evaluated (default; the fast path). False keeps every kernel, with weight 0: the
            same density, evaluated the straightforward way (the dense reference, ``method="dense"``).
        pool_sharpness: ``Σ_e γ_e`` of the experts' exponents (:func:`expert_exponents`).
    """

    def __init__(
        self,
        model: MotionModel,
        manipulator_frame: ContactFrames,
        environment_frames: ContactFrames,
        object_pose: se3.Pose,
        robot_start: se3.Pose,
        contact_patch: Tensor,
        contact_bandwidth: KernelBandwidth,
        motion_bandwidth: KernelBandwidth,
        drop_cut_kernels: bool = True,
        pool_sharpness: float = 1.0,
    ) -> None:
        if contact_bandwidth.descriptor_dim != CONTACT_DESCRIPTOR_DIM:
            raise InvalidParameterError(
                f"the contact bandwidth needs {CONTACT_DESCRIPTOR_DIM} descriptor stds: 2 for the embedded "
                "curvatures, 3 (m) for the frame's position in the robot frame and 3 for the contact patch "
                f"on the bumper; got {contact_bandwidth.descriptor_dim}"
            )
        frames = [(manipulator_frame, model.manipulator), (environment_frames, model.environment)]
        # Motions are expressed in the robot's start frame (motion_frames), the same for every contact
        # frame: each kind's kernels become one set of final poses R0 ∘ m_j ∘ R0⁻¹ ∘ B0' that all of its
        # experts share; the experts differ only in their contact weights K^c.
        to_final = se3.relative(robot_start, object_pose)
        experts, shared_means, shared_weights = [], [], []
        for frame, kernels in frames:
            n_frames = frame.r.reshape(-1, 2).shape[0]
            log_w = contact_log_weights(frame, kernels, robot_start, contact_bandwidth, contact_patch)  # (F, N)
            if kernels.log_weight is not None:  # a conditioned model: the posterior's weight of each kernel
                log_w = log_w + kernels.log_weight.to(log_w)
            finals = se3.compose(se3.compose(robot_start, kernels.m), to_final)  # (N,)
            # kernels the contact kernel cut off carry no weight
            keep = torch.isfinite(log_w) | (not drop_cut_kernels)  # (F, N)
            for i in range(n_frames):  # a handful of experts (1 + E), not kernels
                experts.append(PoseKDE(finals.take(keep[i]), motion_bandwidth, log_w[i, keep[i]]))
            used = keep.any(0)
            shared_means.append(finals.take(used))
            shared_weights.append(torch.where(keep, log_w, -math.inf)[:, used])
        self.experts = PoseKDE.stack(experts)
        self._shared_means = se3.Pose.unchecked(torch.cat([m.p for m in shared_means]),
                                                torch.cat([m.q for m in shared_means]))
        self._shared_log_weights = _block_diagonal(shared_weights, -math.inf)  # (1 + E, K)
        self._shared_product: SharedKernelProduct | None = None
        self.expert_exponent = expert_exponents(len(model.manipulator), len(model.environment), len(experts) - 1,
                                                pool_sharpness, object_pose.p.dtype)
        self.object_pose = object_pose

    @property
    def num_experts(self) -> int:
        return int(self.experts.batch_shape[0])

    def shared_kernels(self) -> tuple[se3.Pose, Tensor]:
        """The experts' kernels laid out for the fast path: final poses ``(K,)`` shared by the experts of
        one contact kind and each expert's log weights ``(1 + E, K)`` (``-inf``: not in that expert)."""
        return self._shared_means, self._shared_log_weights

    def shared_product(self) -> SharedKernelProduct:
        """The product of experts as a :class:`~pushtorch.kde.SharedKernelProduct` (the fast path): each
        kind's kernels evaluated once for all of its experts."""
        if self._shared_product is None:
            rounds = self.experts.trial_rounds
            if not bool((rounds == rounds[0]).all()):
                raise ModelError("the experts of one product must share their trial rounds")
            self._shared_product = SharedKernelProduct(self._shared_means, self._shared_log_weights,
                                                       self.experts.bandwidth, rounds[0],
                                                       expert_exponent=self.expert_exponent)
        return self._shared_product

    def log_prob(self, final_pose: se3.Pose, method: str = "dense") -> Tensor:
        """``log P(B1 | a)`` up to the constant of the unnormalised kernels, for poses ``(..., M)``.

        ``method``: ``"dense"`` (reference) or ``"fast"`` (:meth:`shared_product`: each contact kind's
        kernels evaluated once for all of its experts, fused; same values up to float rounding).

        Raises:
            InvalidPoseError: (both methods alike) misshaped, non-finite or non-unit poses.
            InvalidParameterError: an unknown method.
        """
        if method not in ("dense", "fast"):
            raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}")
        se3.check_pose(final_pose, "final pose")
        if method == "fast":
            flat = se3.Pose.unchecked(final_pose.p.reshape(-1, 3), final_pose.q.reshape(-1, 4))
            return self.shared_product().log_prob(flat).reshape(final_pose.p.shape[:-1])
        return ProductOfExperts(self.experts, expert_exponent=self.expert_exponent).log_prob(final_pose,
                                                                                             method=method)

    def proposal(self, n: int, generator: torch.Generator | None = None) -> se3.Pose:
        """``n`` poses drawn from the experts' mixture (equal shares): annealing's starting candidates."""
        samples, _ = self.experts.sample(max(1, math.ceil(n / self.num_experts)), generator)  # (E, k)
        flat = samples.reshape(-1)
        return flat.take(torch.randperm(flat.p.shape[0], generator=generator)[:n])

    def widen_until_supported(
        self, candidates: se3.Pose, max_rounds: int = 10, method: str = "dense"
    ) -> se3.Pose:
        """Trial rounds for the product: widen every expert until some candidate has non-zero density."""
        for _ in range(max_rounds + 1):
            if torch.isfinite(self.log_prob(candidates, method)).any():
                return candidates
            rounds = self.experts.trial_rounds.clone()
            rounds[..., :2] += 1  # translation and rotation of the motion kernels (no descriptors here)
            self.experts = self.experts.with_trial_rounds(rounds)
            self._shared_product = None
        raise ModelError(
            f"the {self.num_experts} experts share no final pose even after {max_rounds} trial rounds: "
            "the contact frames' predictions contradict each other"
        )

    def mean_shift(self, final_pose: se3.Pose) -> se3.Pose:
        """One mean-shift step of poses ``(..., M)`` towards a local mode of the product
        (:meth:`pushtorch.kde.SharedKernelProduct.mean_shift`)."""
        flat = se3.Pose.unchecked(final_pose.p.reshape(-1, 3), final_pose.q.reshape(-1, 4))
        moved = self.shared_product().mean_shift(flat)
        return se3.Pose.unchecked(moved.p.reshape(final_pose.p.shape), moved.q.reshape(final_pose.q.shape))

    def predict(
        self,
        n_candidates: int,
        schedule: AnnealSchedule,
        generator: torch.Generator | None = None,
        record_history: bool = False,
        method: str = "dense",
        polish_steps: int = 0,
    ) -> MotionPrediction:
        """Simulated annealing on the product of experts from candidates drawn from the experts.

        ``method``: ``"dense"`` (reference) or ``"fast"`` (pruned, fused product and cheaper proposals;
        the same law, another random stream). See :func:`anneal_motion_densities` for many at once.
        ``polish_steps``: mean-shift moves of every candidate afterwards
        (:func:`pushtorch.anneal.polish_candidates`).
        """
        if method == "fast":
            return anneal_motion_densities([self], n_candidates, schedule, generator, record_history,
                                           polish_steps)[0]
        init = self.proposal(n_candidates, generator)
        init = self.widen_until_supported(init)
        result = anneal(self.log_prob, init, schedule, generator, record_history=record_history)
        result = polish_candidates(result, self.mean_shift, self.log_prob, polish_steps)
        return MotionPrediction(result.best, result.best_log_prob, result)


@dataclass
class StackedProducts:
    """The products of experts of several conditions, padded to common kernel and expert counts and stacked
    along a problem dim ``B`` (:func:`stack_products`)."""

    means: se3.Pose  # (B, K) shared kernel means (padding: the identity)
    log_weights: Tensor  # (E, B, K) each expert's kernel log weights (-inf: not in it, or padding)
    exponent: Tensor  # (E, B) the experts' exponents (0: a padding expert)
    trial_rounds: Tensor  # (B, 3)
    bandwidth: KernelBandwidth


def stack_products(densities: list[MotionDensity]) -> StackedProducts:
    """Every density's :meth:`MotionDensity.shared_kernels`, padded and stacked: padding kernels weigh
    nothing; a padding expert copies the condition's first expert (so no expert is empty) and counts for
    nothing (exponent 0).

    Raises:
        InvalidParameterError: no densities, or densities of different dtype or motion bandwidth.
    """
    if not densities:
        raise InvalidParameterError("stacking products of experts needs at least one density")
    layouts = [d.shared_kernels() for d in densities]
    n_experts = max(w.shape[0] for _, w in layouts)
    n_kernels = max(w.shape[1] for _, w in layouts)
    first = densities[0].experts
    dtype, device = first.dtype, first.device
    p = torch.zeros(len(densities), n_kernels, 3, dtype=dtype, device=device)
    q = torch.zeros(len(densities), n_kernels, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    log_w = torch.full((n_experts, len(densities), n_kernels), -math.inf, dtype=dtype, device=device)
    rounds = torch.zeros(len(densities), 3, dtype=torch.int64, device=device)
    exponent = torch.zeros(n_experts, len(densities), dtype=dtype, device=device)
    for b, (density, (means, weights)) in enumerate(zip(densities, layouts, strict=True)):
        experts = density.experts
        if experts.bandwidth != first.bandwidth or experts.dtype != dtype:
            raise InvalidParameterError("products stacked together need one motion bandwidth and dtype")
        e, n = weights.shape
        p[b, :n], q[b, :n] = means.p, means.q
        log_w[:e, b, :n] = weights
        log_w[e:, b, :n] = weights[0]
        rounds[b] = density.shared_product().rounds
        exponent[:e, b] = density.expert_exponent.to(dtype)
    return StackedProducts(se3.Pose.unchecked(p, q), log_w, exponent, rounds, first.bandwidth)


def anneal_motion_densities(
    densities: list[MotionDensity],
    n_candidates: int,
    schedule: AnnealSchedule,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    polish_steps: int = 0,
) -> list[MotionPrediction]:
    """Anneal the products of experts of several push conditions in one batch on the fast path, then
    move every candidate ``polish_steps`` mean-shift steps up (:func:`pushtorch.anneal.polish_candidates`).

    Every condition's :meth:`MotionDensity.shared_kernels` are padded to common kernel and expert
    counts (padding kernels weigh nothing, padding experts are masked out) and stacked along a problem
    dim, in order of kernel count, so each annealing step is one fused evaluation per chunk of
    conditions, each chunk up to its own largest count (:class:`pushtorch.kde.SharedKernelProduct`).
    Each condition's start candidates and trial rounds are its own (:meth:`MotionDensity.proposal`,
    :meth:`MotionDensity.widen_until_supported`); a batch of one anneals exactly as
    :meth:`MotionDensity.predict`'s fast path.

    Returns:
        One :class:`MotionPrediction` per density, in order.

    Raises:
        InvalidParameterError: no densities, or densities of different dtype/bandwidth.
        ModelError: as :meth:`MotionDensity.widen_until_supported`.
    """
    if not densities:
        raise InvalidParameterError("anneal_motion_densities needs at least one density")
    starts = []
    for density in densities:
        init = density.proposal(n_candidates, generator)
        starts.append(density.widen_until_supported(init, method="fast"))
    # problems in order of kernel count: the product's chunks of neighbouring problems then evaluate about
    # their own counts, not the batch's largest (SharedKernelProduct.chunk_layout)
    order = sorted(range(len(densities)), key=lambda b: densities[b].shared_kernels()[1].shape[1])
    densities, starts = [densities[b] for b in order], [starts[b] for b in order]
    stacked = stack_products(densities)
    # its only queries are the annealing's own (finite, normalised) candidates: no per-step checks
    product = SharedKernelProduct(stacked.means, stacked.log_weights, stacked.bandwidth, stacked.trial_rounds,
                                  validate_args=False, expert_exponent=stacked.exponent)
    init = se3.Pose.unchecked(torch.stack([s.p for s in starts]), torch.stack([s.q for s in starts]))  # (B, C)
    result = anneal(product, init, schedule, generator, record_history=record_history, method="fast")
    result = polish_candidates(result, product.mean_shift, product.log_prob, polish_steps)
    out: list[MotionPrediction | None] = [None] * len(densities)
    for b, original in enumerate(order):
        part = AnnealResult(
            best=se3.Pose.unchecked(result.best.p[b], result.best.q[b]),
            best_log_prob=result.best_log_prob[b],
            candidates=se3.Pose.unchecked(result.candidates.p[b], result.candidates.q[b]),
            log_prob=result.log_prob[b],
            history=(None if result.history is None
                     else se3.Pose.unchecked(result.history.p[:, b], result.history.q[:, b])),
            history_log_prob=None if result.history_log_prob is None else result.history_log_prob[:, b],
        )
        out[original] = MotionPrediction(part.best, part.best_log_prob, part)
    return out  # type: ignore[return-value]
