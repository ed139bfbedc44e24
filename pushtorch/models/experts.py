"""The product of experts over an object's final pose, and its annealing (paper, §Motion Model, Eq. poe).

:class:`MotionDensity` is one push condition's density ``P(B1 | a)``: for each contact frame placed on the
new object (the manipulator frame and the environment frames), the action's training kernels of the same
kind (:class:`~pushtorch.models.motion.MotionKernels`) become kernels over the object's final pose, weighted
by the contact-frame kernel ``K^c``; the experts' product is optimised by simulated annealing
(:meth:`MotionDensity.predict`). :func:`anneal_motion_densities` anneals the products of many push
conditions in one batch on the fast path: each kind's kernels, shared by all of its experts, are evaluated
once per query (:class:`pushtorch.kde.SharedKernelProduct`), and the candidates are polished by mean shift.
A planner's candidates of one cloud skip the density objects: :func:`candidate_products` builds their products
stacked, :func:`draw_starts` and :func:`widen_stacked` give their annealing starts and trial rounds, and
:func:`anneal_stacked` anneals them.
How the kernels are trained, and the decisions behind their frames, are in :mod:`pushtorch.models.motion`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule, anneal, polish_candidates
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.kde import Evaluation, KernelBandwidth, PoseKDE, ProductOfExperts, SharedKernelProduct
from pushtorch.kde.sampling import sample_kernel_offsets
from pushtorch.models.frames import ContactFrames
from pushtorch.models.motion import CONTACT_DESCRIPTOR_DIM, MotionModel, contact_log_weights, expert_exponents
from pushtorch.se3 import multinomial
from pushtorch.streams import is_keyed

Tensor = torch.Tensor

__all__ = [
    "MotionDensity",
    "MotionPrediction",
    "StackedProducts",
    "anneal_motion_densities",
    "anneal_stacked",
    "candidate_products",
    "concat_products",
    "draw_starts",
    "stack_products",
    "widen_stacked",
]


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
            same density, evaluated the straightforward way (the dense reference, :attr:`Evaluation.DENSE`).
        pool_sharpness: ``Σ_e γ_e`` of the experts' exponents (:func:`expert_exponents`).
        density_bandwidth: the motion kernels of the density the prediction returns (the calibrated width,
            :attr:`~pushtorch.models.settings.ModelSettings.density_bandwidth`); None: ``motion_bandwidth``.
            Annealing and :meth:`log_prob` use ``motion_bandwidth``.
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
        density_bandwidth: KernelBandwidth | None = None,
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
        self.density_bandwidth = motion_bandwidth if density_bandwidth is None else density_bandwidth

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

    def log_prob(self, final_pose: se3.Pose, method: Evaluation | str = Evaluation.DENSE) -> Tensor:
        """``log P(B1 | a)`` up to the constant of the unnormalised kernels, for poses ``(..., M)``.

        ``method``: :attr:`Evaluation.DENSE` (reference) or :attr:`Evaluation.FAST` (:meth:`shared_product`:
        each contact kind's kernels evaluated once for all of its experts, fused; same values up to float
        rounding), or its string.

        Raises:
            InvalidPoseError: (both methods alike) misshaped, non-finite or non-unit poses.
            InvalidParameterError: an unknown method.
        """
        method = Evaluation.of(method)
        se3.check_pose(final_pose, "final pose")
        if method is Evaluation.FAST:
            flat = se3.Pose.unchecked(final_pose.p.reshape(-1, 3), final_pose.q.reshape(-1, 4))
            return self.shared_product().log_prob(flat).reshape(final_pose.p.shape[:-1])
        return ProductOfExperts(self.experts, expert_exponent=self.expert_exponent).log_prob(final_pose,
                                                                                             method=method)

    def proposal(self, n: int, generator: torch.Generator | None = None) -> se3.Pose:
        """``n`` poses drawn from the experts' mixture (equal shares): annealing's starting candidates."""
        samples, _ = self.experts.sample(max(1, math.ceil(n / self.num_experts)), generator)  # (E, k)
        flat = samples.reshape(-1)
        if is_keyed(generator):
            return flat.take(generator.permutation(flat.p.shape[0]).to(flat.p.device)[:n])
        return flat.take(torch.randperm(flat.p.shape[0], generator=generator)[:n])

    def widen_until_supported(
        self, candidates: se3.Pose, max_rounds: int = 10, method: Evaluation = Evaluation.DENSE
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
        method: Evaluation | str = Evaluation.DENSE,
        polish_steps: int = 0,
    ) -> MotionPrediction:
        """Simulated annealing on the product of experts from candidates drawn from the experts.

        ``method``: :attr:`Evaluation.DENSE` (reference) or :attr:`Evaluation.FAST` (pruned, fused product
        and cheaper proposals; the same law, another random stream), or its string. See
        :func:`anneal_motion_densities` for many at once. ``polish_steps``: mean-shift moves of every
        candidate afterwards (:func:`pushtorch.anneal.polish_candidates`).
        """
        if Evaluation.of(method) is Evaluation.FAST:
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
    density_bandwidth: KernelBandwidth  # the density's (MotionDensity.density_bandwidth)

    def take(self, index: Tensor) -> StackedProducts:
        """The products at ``index`` (a subset or a reordering of the problems)."""
        return replace(self, means=se3.Pose.unchecked(self.means.p[index], self.means.q[index]),
                       log_weights=self.log_weights[:, index], exponent=self.exponent[:, index],
                       trial_rounds=self.trial_rounds[index])


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
        if experts.bandwidth != first.bandwidth or experts.dtype != dtype \
                or density.density_bandwidth != densities[0].density_bandwidth:
            raise InvalidParameterError("products stacked together need one motion bandwidth and dtype")
        e, n = weights.shape
        p[b, :n], q[b, :n] = means.p, means.q
        log_w[:e, b, :n] = weights
        log_w[e:, b, :n] = weights[0]
        rounds[b] = density.shared_product().rounds
        exponent[:e, b] = density.expert_exponent.to(dtype)
    return StackedProducts(se3.Pose.unchecked(p, q), log_w, exponent, rounds, first.bandwidth,
                           densities[0].density_bandwidth)


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
    dim (:func:`stack_products`), then annealed together (:func:`anneal_stacked`). Each condition's start
    candidates and trial rounds are its own (:meth:`MotionDensity.proposal`,
    :meth:`MotionDensity.widen_until_supported`); a batch of one anneals exactly as :meth:`MotionDensity.predict`'s
    fast path.

    Returns:
        One :class:`MotionPrediction` per density, in order.

    Raises:
        InvalidParameterError: no densities, or densities of different dtype/bandwidth.
        ModelError: as :meth:`MotionDensity.widen_until_supported`.
    """
    if not densities:
        raise InvalidParameterError("anneal_motion_densities needs at least one density")
    keyed = is_keyed(generator)
    if keyed and len(generator) != len(densities):
        raise InvalidParameterError(f"a keyed stream of {len(generator)} problems cannot draw for {len(densities)} "
                                    "densities")
    proposals = generator.fork() if keyed else generator  # keyed: each problem's start draws are its own
    starts = []
    for b, density in enumerate(densities):
        init = density.proposal(n_candidates, proposals.take(b) if keyed else generator)
        starts.append(density.widen_until_supported(init, method=Evaluation.FAST))
    init = se3.Pose.unchecked(torch.stack([s.p for s in starts]), torch.stack([s.q for s in starts]))  # (B, C)
    result = anneal_stacked(stack_products(densities), init, schedule, generator, record_history, polish_steps)
    out = []
    for b in range(len(densities)):
        part = result.take(b)
        out.append(MotionPrediction(part.best, part.best_log_prob, part))
    return out


def _product(stacked: StackedProducts, validate_args: bool = True) -> SharedKernelProduct:
    return SharedKernelProduct(stacked.means, stacked.log_weights, stacked.bandwidth, stacked.trial_rounds,
                               validate_args=validate_args, expert_exponent=stacked.exponent)


def anneal_stacked(
    stacked: StackedProducts,
    init: se3.Pose,
    schedule: AnnealSchedule,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    polish_steps: int = 0,
) -> AnnealResult:
    """Anneal stacked products of experts ``(B,)`` from their start candidates ``init (B, n)`` on the fast path
    and polish every candidate by ``polish_steps`` mean-shift steps; the result ``(B,)`` in the products' order.

    The problems anneal in order of kernel count, so that the product's chunks of neighbouring problems each
    evaluate about their own count rather than the batch's largest (``SharedKernelProduct.chunk_layout``); a
    keyed stream's steps are drawn by each problem's own key, in that order (a ``torch.Generator`` draws for the
    sorted batch). The steps are drawn before the loop and the loop has no host synchronisation
    (:class:`~pushtorch.kde.FusedAnnealing`).
    """
    weighted = torch.isfinite(stacked.log_weights).any(0)  # (B, K)
    counts = (weighted * torch.arange(1, weighted.shape[-1] + 1, device=weighted.device)).amax(-1).tolist()
    order = sorted(range(len(counts)), key=lambda b: counts[b])
    index = torch.tensor(order, device=init.p.device)
    if is_keyed(generator):
        generator = generator.fork().take(order)
    product = _product(stacked.take(index), validate_args=False)  # its own normalised candidates only
    start = se3.Pose.unchecked(init.p[index], init.q[index])
    result = anneal(product, start, schedule, generator, record_history=record_history, method=Evaluation.FAST)
    result = polish_candidates(result, product.mean_shift, product.log_prob, polish_steps)
    return result.take(torch.argsort(index))


def candidate_products(
    motion: MotionModel,
    manipulator_frames: ContactFrames,
    environment_frames: ContactFrames,
    object_pose: se3.Pose,
    robot_starts: se3.Pose,
    contact_patches: Tensor,
    contact_bandwidth: KernelBandwidth,
    motion_bandwidth: KernelBandwidth,
    density_bandwidth: KernelBandwidth | None = None,
    pool_sharpness: float = 1.0,
) -> StackedProducts:
    """The products of experts of ``B`` candidate pushes of one cloud and one action, built at once: the stacked
    layout (:func:`stack_products`) of the :class:`MotionDensity` (fast path) of each candidate, without building
    any of them.

    Args:
        motion: the action's motion kernels (all of them: within the prediction's kernel budget).
        manipulator_frames: ``(B, 1)`` each candidate's manipulator contact frame.
        environment_frames: ``(E,)`` the cloud's environment contact frames, shared by the candidates.
        object_pose: ``()`` the cloud's pose estimate.
        robot_starts: ``(B,)`` start poses; contact_patches: ``(B, 3)``.
        contact_bandwidth, motion_bandwidth, density_bandwidth, pool_sharpness: as :class:`MotionDensity`.

    Each candidate's contact weights come from one batched call per contact kind
    (:func:`~pushtorch.models.motion.contact_log_weights` over ``(B, F)`` frames), its final-pose kernels from
    one broadcast composition ``R0 ∘ m_j ∘ R0⁻¹ ∘ B0'``, and its kernels that no expert weighs are moved behind
    the weighted ones (a stable sort: the weighted ones keep their order) and cut after the batch's largest
    weighted count, so that each product evaluates about its own kernels, as a :class:`MotionDensity` that drops
    its cut kernels does. Trial rounds start at zero (:func:`widen_stacked` fits them).
    """
    count = robot_starts.batch_shape[0]
    to_final = se3.relative(robot_starts, object_pose)  # (B,)
    weights, finals = [], []
    for frames, kernels in ((manipulator_frames, motion.manipulator),
                            (environment_frames.expand(count), motion.environment)):
        log_w = contact_log_weights(frames, kernels, robot_starts, contact_bandwidth, contact_patches)
        log_w = log_w.reshape(count, -1, len(kernels)).transpose(0, 1)  # (F, B, N)
        if kernels.log_weight is not None:  # a conditioned model: the posterior's weight of each kernel
            log_w = log_w + kernels.log_weight.to(log_w)
        weights.append(log_w)
        finals.append(se3.compose(se3.compose(robot_starts.unsqueeze(-1), kernels.m), to_final.unsqueeze(-1)))
    (w_m, w_e), n_m, n_e = weights, weights[0].shape[-1], weights[1].shape[-1]
    n_env = w_e.shape[0]
    log_w = torch.cat([torch.cat([w_m, torch.full((1, count, n_e), -math.inf).to(w_m)], -1),
                       torch.cat([torch.full((n_env, count, n_m), -math.inf).to(w_e), w_e], -1)], 0)  # (1+E, B, K)
    p = torch.cat([f.p for f in finals], 1)  # (B, K, 3)
    q = torch.cat([f.q for f in finals], 1)
    weighted = torch.isfinite(log_w).any(0)  # (B, K)
    kept = max(1, int(weighted.sum(-1).max()))  # one synchronisation, before any annealing
    order = torch.argsort((~weighted).to(torch.int8), dim=-1, stable=True)[:, :kept]  # (B, K')
    p = torch.gather(p, 1, order.unsqueeze(-1).expand(count, kept, 3))
    q = torch.gather(q, 1, order.unsqueeze(-1).expand(count, kept, 4))
    log_w = torch.gather(log_w, 2, order.unsqueeze(0).expand(1 + n_env, count, kept))
    dtype = object_pose.p.dtype
    exponent = expert_exponents(n_m, n_e, n_env, pool_sharpness, dtype).to(log_w.device)
    rounds = torch.zeros(count, 3, dtype=torch.int64, device=log_w.device)
    exponent = exponent.unsqueeze(-1).expand(1 + n_env, count).clone()
    density_bandwidth = motion_bandwidth if density_bandwidth is None else density_bandwidth
    return StackedProducts(se3.Pose.unchecked(p, q), log_w, exponent, rounds, motion_bandwidth, density_bandwidth)


def draw_starts(stacked: StackedProducts, n: int, generator: torch.Generator | None = None) -> se3.Pose:
    """``(B, n)`` annealing start candidates of stacked products, each drawn from its problem's experts' mixture
    with equal shares (each counted expert a kernel density over the final pose, :meth:`PoseKDE.sample`'s exact
    truncated kernel draws): :meth:`MotionDensity.proposal` for many problems in one draw. A keyed stream draws
    along the problems (each problem's numbers its own)."""
    log_w = stacked.log_weights.double()  # (E, B, K)
    n_experts, count, n_kernels = log_w.shape
    counted = (stacked.exponent > 0).unsqueeze(-1)  # (E, B, 1): padding experts are not drawn from
    share = torch.where(counted, torch.softmax(log_w, -1), 0.0) / counted.sum(0).clamp_min(1)
    index = multinomial(share.transpose(0, 1).reshape(count, n_experts * n_kernels), n, generator) % n_kernels
    p = torch.gather(stacked.means.p, 1, index.unsqueeze(-1).expand(count, n, 3))
    q = torch.gather(stacked.means.q, 1, index.unsqueeze(-1).expand(count, n, 4))
    bandwidth = stacked.bandwidth
    beta = torch.pow(torch.tensor(bandwidth.alpha_t, dtype=torch.float64, device=p.device),
                     -stacked.trial_rounds.double()).to(p.dtype).double()  # (B, 3), as PoseKDE's
    delta_p, delta_q, _ = bandwidth.delta
    offset, around_identity = sample_kernel_offsets(
        (bandwidth.p_std / torch.sqrt(beta[:, 0])).unsqueeze(-1).expand(count, n),
        (beta[:, 1] / bandwidth.sigma_q).unsqueeze(-1).expand(count, n), delta_p, delta_q, generator)
    turn = pkt.quaternion_raw_multiply(q.double(), around_identity)
    return se3.Pose.unchecked(p + offset.to(p.dtype), (turn / turn.norm(dim=-1, keepdim=True)).to(p.dtype))


def widen_stacked(stacked: StackedProducts, candidates: se3.Pose, max_rounds: int = 10) -> StackedProducts:
    """Trial rounds for each stacked product ``(B,)``: widen the kernels of every problem none of whose
    ``candidates (B, n)`` has a non-zero density, until all have one (:meth:`MotionDensity.widen_until_supported`
    for many problems; one synchronisation per round, before any annealing).

    Raises:
        ModelError: a problem still without support after ``max_rounds``.
    """
    for _ in range(max_rounds + 1):
        unsupported = ~torch.isfinite(_product(stacked).log_prob(candidates)).any(-1)  # (B,)
        if not bool(unsupported.any()):
            return stacked
        rounds = stacked.trial_rounds.clone()
        rounds[:, :2] += unsupported.unsqueeze(-1).to(rounds.dtype)
        stacked = replace(stacked, trial_rounds=rounds)
    raise ModelError(
        f"the experts of {int(unsupported.sum())} of {len(unsupported)} products share no final pose even after "
        f"{max_rounds} trial rounds: the contact frames' predictions contradict each other"
    )


def concat_products(parts: list[StackedProducts]) -> StackedProducts:
    """Stacked products of several batches joined along the problems, padded to common kernel and expert counts
    as :func:`stack_products` pads (padding kernels weigh nothing; a padding expert copies its problem's first
    and counts for nothing).

    Raises:
        InvalidParameterError: no parts, or parts of different dtype or bandwidths.
    """
    if not parts:
        raise InvalidParameterError("joining stacked products needs at least one")
    first = parts[0]
    if any(p.bandwidth != first.bandwidth or p.density_bandwidth != first.density_bandwidth
           or p.log_weights.dtype != first.log_weights.dtype for p in parts):
        raise InvalidParameterError("products stacked together need one motion bandwidth and dtype")
    if len(parts) == 1:
        return first
    n_experts = max(p.log_weights.shape[0] for p in parts)
    n_kernels = max(p.log_weights.shape[2] for p in parts)
    ps, qs, weights, exponents = [], [], [], []
    for part in parts:
        e, count, k = part.log_weights.shape
        pad = n_kernels - k
        ps.append(torch.nn.functional.pad(part.means.p, (0, 0, 0, pad)))
        qs.append(torch.nn.functional.pad(part.means.q, (0, 0, 0, pad)))
        qs[-1][:, k:, 0] = 1.0  # padding kernels at the identity
        w = torch.nn.functional.pad(part.log_weights, (0, pad), value=-math.inf)
        weights.append(torch.cat([w, w[:1].expand(n_experts - e, count, n_kernels)], 0))
        exponents.append(torch.nn.functional.pad(part.exponent, (0, 0, 0, n_experts - e)))
    return StackedProducts(se3.Pose.unchecked(torch.cat(ps), torch.cat(qs)), torch.cat(weights, 1),
                           torch.cat(exponents, 1), torch.cat([p.trial_rounds for p in parts]), first.bandwidth,
                           first.density_bandwidth)
