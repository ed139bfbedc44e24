"""A prediction as a ``torch.distributions.Distribution`` over final poses (issue 23, item 1).

Paper, §Motion Model, Eq. poe: the prediction is the product of experts ``P(B1 | a) ∝ Π_e P_e(B1)^γ_e``
(:class:`pushtorch.models.motion.MotionDensity`; ``γ_e`` the experts' exponents). Here it is a torch
distribution with ``event_shape (7,)``, the pose as ``[p, q_wxyz]``, and ``batch_shape (B,)`` for a batch of
clouds (``()`` for one). Decisions (docs/method.md, "The prediction as a distribution"):

* **Normalised.** ``log_prob`` is a log density with respect to Lebesgue measure on positions (m³) times
  the uniform *probability* measure on unit quaternions with q ≡ −q (so in nats, like
  :func:`pushtorch.evaluation.likelihood.nll`). Each expert is its normalised mixture of the model's *cut-off*
  kernels — each kernel's integral inside its cut-off (:func:`pushtorch.kde.normaliser.log_kernel_normaliser`)
  included — and the product's normaliser ``Z = ∫ Π_e p_e^γ_e`` is estimated once, on first use, by
  importance sampling (:func:`pushtorch.kde.normaliser.log_normaliser`, seeded: the same value every time).
  Outside every kernel's cut-off the density is 0 and ``log_prob`` −inf.
* **Evaluation methods.** :attr:`Evaluation.FAST` (default) evaluates the shared-kernel product
  (:class:`pushtorch.kde.SharedKernelProduct`), ``"dense"`` every expert's kernels densely
  (:class:`pushtorch.kde.PoseKDE`); both give the same values (float rounding), broadcast alike, and let
  gradients flow to the query poses.
* **Sampling** is importance resampling: a pool drawn from the experts' equal mixture (exact draws of the
  cut-off kernels) is resampled by the weights ``Π_e p_e^γ_e / mixture``. With ``Σ γ_e = 1`` (the default
  ``pool_sharpness``) the weights are bounded (a weighted geometric mean is at most the arithmetic mean),
  so the pool of ``max(4 n, 512 E)`` draws represents the product well; duplicates among ``n`` samples are
  possible, as with any resampling.
* ``mode`` is the annealed prediction (``Prediction.final_pose``); ``mean`` is not defined (a mean of
  rotations needs a choice of metric the method does not make).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch.distributions import Distribution, constraints

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import Evaluation, KernelBandwidth, PoseKDE, SharedKernelProduct
from pushtorch.kde.normaliser import (
    NO_CUTOFF,
    expert_log_probs,
    log_kernel_normaliser,
    log_normaliser,
    log_normalisers,
)
from pushtorch.models.experts import StackedProducts, stack_products
from pushtorch.models.settings import DEFAULT_SEED, as_generator
from pushtorch.streams import KeyedStream

Tensor = torch.Tensor

__all__ = ["KERNELS", "DefensiveMixture", "FinalPoseDistribution"]

#: The kernels a distribution evaluates: the model's cut-off kernels, or the full ones they approximate.
KERNELS = ("cut", "full")

#: Proposals per expert and part of the normaliser's importance sampler (``kde.normaliser.log_normaliser``): on
#: the quickstart's cube predictions (6 experts, ~450 kernels) log Z varies by ~0.005 nats between seeds
#: and costs ~0.1 s, once per distribution (the scoring's 64 vary by ~0.02).
NORMALISER_SAMPLES = 1024
#: Proposal draws per expert of the resampling pool, at least (``sample``).
MIN_POOL_PER_EXPERT = 512


class FinalPoseDistribution(Distribution):
    """The product of experts of one prediction (or a batch of them) over the object's final pose.

    Build it with :meth:`from_motion_densities`; ``predict`` returns it as ``Prediction.density``.

    Args:
        means: the experts' shared kernel means ``(*B, K)`` (padding: any unit pose).
        log_weights: ``(E, *B, K)`` each expert's kernel log weights (``-inf``: not in that expert).
        bandwidth: the motion kernels' bandwidth and cut-offs; trial_rounds: ``(*B, 3)``.
        exponent: ``(E, *B)`` the experts' exponents ``γ_e`` (0: a padding expert).
        mode: ``(*B, 7)`` the annealed final pose of each prediction.
        method: :attr:`Evaluation.FAST` or :attr:`Evaluation.DENSE`, or its string (module docstring).
        normaliser_centres: ``(*B, C)`` poses where the product's modes are (the annealed candidates);
            they guide the importance sampler of the normaliser.
        validate_args: check every query (torch's convention); an invalid one raises
            :class:`~pushtorch.errors.InvalidPoseError` (a ValueError). Default True, whatever
            ``torch.distributions.Distribution``'s global default is: torch.compile turns that off for the whole
            process once it first runs (``torch._dynamo``'s patches), and a compiled prediction must not stop
            refusing bad queries; ``False`` skips the checks.
        normaliser_samples: proposals per expert and part of the normaliser's importance sampler (default
            :data:`NORMALISER_SAMPLES`; its cost grows linearly with them).
        normaliser_keys: ``(*B,)`` integer keys, one per prediction (a planner's candidates: each one's key): the
            normalisers are then estimated all at once, each from draws keyed by its prediction
            (:func:`pushtorch.kde.normaliser.log_normalisers`); None: one after the other, each from a generator
            seeded with :data:`~pushtorch.models.settings.DEFAULT_SEED`. Either way a prediction's normaliser is the
            same alone and in any batch.
    """

    arg_constraints: dict = {}
    support = constraints.independent(constraints.real, 1)
    has_rsample = False

    def __init__(self, means: se3.Pose, log_weights: Tensor, bandwidth: KernelBandwidth, trial_rounds: Tensor,
                 exponent: Tensor, mode: Tensor | None, method: Evaluation | str = Evaluation.FAST,
                 normaliser_centres: se3.Pose | None = None, validate_args: bool | None = None, *,
                 kernels: str = "cut", frame: tuple[se3.Pose, se3.Pose] | None = None,
                 log_z: Tensor | None = None, normaliser_samples: int = NORMALISER_SAMPLES,
                 normaliser_keys: Tensor | None = None) -> None:
        method = Evaluation.of(method)
        if isinstance(normaliser_samples, bool) or not isinstance(normaliser_samples, int) or normaliser_samples < 1:
            raise InvalidParameterError(f"normaliser_samples must be an integer >= 1, got {normaliser_samples!r}")
        if kernels not in KERNELS:
            raise InvalidParameterError(f"kernels must be one of {', '.join(map(repr, KERNELS))}, got {kernels!r}")
        batch = means.batch_shape[:-1]
        if log_weights.shape[1:] != means.batch_shape or exponent.shape != log_weights.shape[:-1]:
            raise InvalidParameterError(
                f"log_weights (E, *B, K) and exponent (E, *B) must match means {tuple(means.batch_shape)}; got "
                f"{tuple(log_weights.shape)} and {tuple(exponent.shape)}")
        if kernels == "full":
            bandwidth = dataclasses.replace(bandwidth, cutoff_std=NO_CUTOFF)
        self.means, self.log_weights, self.bandwidth = means, log_weights, bandwidth
        self.trial_rounds = trial_rounds.expand(*batch, 3)
        self.exponent, self.method, self.kernels, self.frame = exponent, method, kernels, frame
        self._mode = mode
        self.normaliser_centres, self.normaliser_samples = normaliser_centres, normaliser_samples
        if normaliser_keys is not None and (normaliser_keys.shape != batch or normaliser_keys.is_floating_point()):
            raise InvalidParameterError(f"normaliser_keys must be integers of the batch shape {tuple(batch)}")
        self.normaliser_keys = normaliser_keys
        self._log_z: Tensor | None = log_z
        self._log_kernel: Tensor | None = None
        self._experts: PoseKDE | None = None
        self._product: SharedKernelProduct | None = None
        super().__init__(batch_shape=batch, event_shape=torch.Size([7]),
                         validate_args=True if validate_args is None else validate_args)

    @staticmethod
    def from_motion_densities(densities, modes: se3.Pose, centres: list[se3.Pose] | None = None,
                              method: Evaluation | str = Evaluation.FAST,
                              validate_args: bool | None = None) -> FinalPoseDistribution:
        """One distribution over the predictions of ``densities`` (a :class:`MotionDensity`, or a list of
        them: ``batch_shape (B,)``, kernels and experts padded and masked inside).

        Args:
            modes: the predictions' annealed final poses, ``()`` for one density or ``(B,)``.
            centres: each prediction's annealed candidates (the normaliser's proposal centres).
        """
        single = not isinstance(densities, list | tuple)
        densities = [densities] if single else list(densities)
        if not densities:
            raise InvalidParameterError("a distribution needs at least one prediction")
        centres_pose = None
        if centres is not None:
            counts = {c.p.shape[0] for c in centres}
            centres_pose = se3.Pose.stack(centres) if len(counts) == 1 else None  # ragged: default centres
        dist = FinalPoseDistribution.from_stacked(stack_products(densities), modes, centres_pose, method,
                                                  validate_args)
        return dist[0] if single else dist

    @staticmethod
    def from_stacked(stacked: StackedProducts, modes: se3.Pose, centres: se3.Pose | None = None,
                     method: Evaluation | str = Evaluation.FAST, validate_args: bool | None = None,
                     normaliser_samples: int = NORMALISER_SAMPLES,
                     normaliser_keys: Tensor | None = None) -> FinalPoseDistribution:
        """One distribution of ``batch_shape (B,)`` over stacked products of experts
        (:class:`~pushtorch.models.experts.StackedProducts`: a planner's candidates, built batched), their annealed
        ``modes (B,)`` and candidates ``centres (B, n)`` (the normaliser's proposal centres; None: default);
        ``normaliser_samples``, ``normaliser_keys``: as the constructor's."""
        count = stacked.log_weights.shape[1]
        mode = modes.vector().to(stacked.log_weights.dtype).reshape(count, 7)
        dist = FinalPoseDistribution(stacked.means, stacked.log_weights, stacked.density_bandwidth,
                                     stacked.trial_rounds, stacked.exponent, mode, method, centres, validate_args,
                                     normaliser_samples=normaliser_samples, normaliser_keys=normaliser_keys)
        if stacked.density_bandwidth != stacked.bandwidth:
            dist = dist._widened_to_mode(stacked.bandwidth)
        return dist

    @staticmethod
    def from_predictions(predictions, method: Evaluation | str | None = None,
                         validate_args: bool | None = None) -> FinalPoseDistribution:
        """One distribution of ``batch_shape (B,)`` over a batch of predictions (``predict_many``'s list);
        ``method``: default the first prediction's."""
        predictions = list(predictions)
        return FinalPoseDistribution.from_motion_densities(
            [p.motion_density for p in predictions], se3.Pose.stack([p.final_pose for p in predictions]),
            [p.candidates for p in predictions], method or predictions[0].density.method, validate_args)

    def _widened_to_mode(self, annealed: KernelBandwidth) -> FinalPoseDistribution:
        """This distribution with trial rounds added where its annealed mode lies beyond the cut-offs: the mode
        was annealed under the wider ``annealed`` kernels at the same rounds, so as many rounds as make these
        kernels that wide put it back inside (docs/method.md, "Two widths: the mode and the density")."""
        ratio = max(annealed.p_std / self.bandwidth.p_std, annealed.rot_std / self.bandwidth.rot_std, 1.0)
        dist = self
        for _ in range(math.ceil(math.log(ratio) / math.log(self.bandwidth.alpha_t)) + 1):
            outside = ~torch.isfinite(dist.unnormalised_log_prob(dist._mode))  # (*B,)
            if not bool(outside.any()):
                break
            rounds = dist.trial_rounds.clone()
            rounds[..., :2] += outside.unsqueeze(-1).to(rounds.dtype)
            dist = dist._replace(trial_rounds=rounds)
        return dist

    def __getitem__(self, index: int) -> FinalPoseDistribution:
        """The distribution of one prediction of a batch (``batch_shape (B,)`` → ``()``)."""
        if len(self.batch_shape) != 1:
            raise InvalidParameterError("only a distribution with batch_shape (B,) is indexed")
        centres = None if self.normaliser_centres is None else self.normaliser_centres.take(index)
        return self._replace(means=self.means.take(index), log_weights=self.log_weights[:, index],
                             trial_rounds=self.trial_rounds[index], exponent=self.exponent[:, index],
                             mode=self._mode[index], normaliser_centres=centres,
                             normaliser_keys=None if self.normaliser_keys is None else self.normaliser_keys[index],
                             log_z=None if self._log_z is None else self._log_z[index])

    def _replace(self, log_z: Tensor | None = None, **changes) -> FinalPoseDistribution:
        """This distribution with some constructor arguments changed, and the normaliser ``log_z`` if known."""
        arguments = dict(means=self.means, log_weights=self.log_weights, bandwidth=self.bandwidth,
                         trial_rounds=self.trial_rounds, exponent=self.exponent, mode=self._mode,
                         method=self.method, normaliser_centres=self.normaliser_centres,
                         validate_args=self._validate_args, kernels=self.kernels, frame=self.frame,
                         normaliser_samples=self.normaliser_samples, normaliser_keys=self.normaliser_keys)
        return FinalPoseDistribution(**(arguments | changes), log_z=log_z)

    # ------------------------------------------------------------------------------------------ properties

    @property
    def mode(self) -> Tensor:
        """``(*B, 7)`` the annealed prediction (``Prediction.final_pose`` as ``[p, q_wxyz]``).

        Raises:
            NotImplementedError: a density built without one (a baseline's scoring density).
        """
        if self._mode is None:
            raise NotImplementedError("this density was built without an annealed mode")
        return self._mode

    @property
    def num_experts(self) -> int:
        return int(self.log_weights.shape[0])

    def experts(self) -> PoseKDE:
        """The experts as one :class:`PoseKDE` of batch ``(E, *B)`` (the dense method; built once)."""
        if self._experts is None:
            e, shape = self.num_experts, self.means.batch_shape
            means = se3.Pose.unchecked(self.means.p.expand(e, *shape, 3), self.means.q.expand(e, *shape, 4))
            self._experts = PoseKDE(means, self.bandwidth, self.log_weights,
                                    trial_rounds=self.trial_rounds.expand(e, *self.batch_shape, 3))
        return self._experts

    def log_normaliser(self) -> Tensor:
        """``(*B,)`` float64 ``log Z``: each expert normalised with its cut-off kernels' integrals, the
        product by importance sampling (seeded with DEFAULT_SEED; with ``normaliser_keys``, all at once, each from
        its key's draws; computed on first use)."""
        if self._log_z is None and self.normaliser_keys is not None:  # all at once, each from its own keyed draws
            flat_batch = max(1, self.batch_shape.numel())
            centres = None if self.normaliser_centres is None else self.normaliser_centres.reshape(flat_batch, -1)
            keys = self.normaliser_keys.reshape(-1).to(self.means.p.device)
            values = log_normalisers(self.means.reshape(flat_batch, -1),
                                     self.log_weights.reshape(self.num_experts, flat_batch, -1), self.bandwidth,
                                     self.trial_rounds.reshape(flat_batch, 3),
                                     self.exponent.reshape(self.num_experts, flat_batch), centres,
                                     KeyedStream(DEFAULT_SEED, keys), self.normaliser_samples)
            self._log_z = values.reshape(self.batch_shape)
        if self._log_z is None:
            flat_batch = max(1, self.batch_shape.numel())
            log_w = self.log_weights.reshape(self.num_experts, flat_batch, -1)
            exponent = self.exponent.reshape(self.num_experts, flat_batch)
            means = self.means.reshape(flat_batch, -1)
            rounds = self.trial_rounds.reshape(flat_batch, 3)
            values = []
            for b in range(flat_batch):  # once per prediction: the estimator draws per expert
                counted = exponent[:, b] > 0
                kept = torch.isfinite(log_w[counted, b]).any(0)
                e = int(counted.sum())
                kde = PoseKDE(se3.Pose.unchecked(means.p[b, kept].expand(e, -1, 3), means.q[b, kept].expand(e, -1, 4)),
                              self.bandwidth, log_w[counted, b][:, kept], trial_rounds=rounds[b].expand(e, 3))
                centres = None if self.normaliser_centres is None else \
                    self.normaliser_centres.reshape(flat_batch, -1).take(b)
                # seeded per prediction: its normaliser is the same alone and in any batch
                generator = as_generator(None, self.means.p.device)
                values.append(log_normaliser(kde, generator, self.normaliser_samples, centres, exponent[counted, b]))
            self._log_z = torch.stack(values).reshape(self.batch_shape)
        return self._log_z

    def log_kernel_integral(self) -> Tensor:
        """``(*B,)`` float64 log of one cut-off kernel's integral (every kernel of a prediction shares its
        bandwidth and trial rounds; computed once)."""
        if self._log_kernel is None:
            self._log_kernel = log_kernel_normaliser(self.experts())[0]
        return self._log_kernel

    # ------------------------------------------------------------------------------------------ evaluation

    def _validate_sample(self, value: Tensor) -> None:
        if not isinstance(value, Tensor) or value.shape[-1:] != (7,):
            raise InvalidPoseError(f"values must be tensors (..., 7) as [p, q_wxyz], got "
                                   f"{tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__}")
        try:
            torch.broadcast_shapes(value.shape[:-1], self.batch_shape)
        except RuntimeError as exc:
            raise InvalidPoseError(f"values {tuple(value.shape)} do not broadcast with the batch shape "
                                   f"{tuple(self.batch_shape)} (values are (..., *batch_shape, 7))") from exc
        se3.check_pose(se3.Pose.from_vector(value), "values")

    def _as_queries(self, value: Tensor) -> tuple[Tensor, torch.Size]:
        """Values ``(..., *B, 7)`` as queries ``(*B, M, 7)`` and the sample shape ``(...)``."""
        nb = len(self.batch_shape)
        value = value.to(self.means.p.dtype)
        shape = torch.broadcast_shapes(value.shape[:-1], self.batch_shape)
        sample_shape = shape[: len(shape) - nb]
        flat = value.expand(*shape, 7).reshape(-1, *self.batch_shape, 7)
        return flat.movedim(0, nb), sample_shape

    def _unnormalised(self, queries: Tensor) -> Tensor:
        """``Σ_e γ_e log P_e`` (normalised weights, kernels 1 at their means) at ``(*B, M, 7)`` → ``(*B, M)``."""
        pose = se3.Pose.from_vector(queries)
        if self.method is Evaluation.FAST:
            if self._product is None:
                self._product = SharedKernelProduct(self.means, self.log_weights, self.bandwidth, self.trial_rounds,
                                                    expert_exponent=self.exponent, validate_args=False)
            return self._product.log_prob(pose)
        per_expert = self.experts().log_prob(pose)  # (E, *B, M)
        gamma = self.exponent.unsqueeze(-1)
        return torch.where(gamma > 0, gamma * per_expert, torch.zeros_like(per_expert)).sum(0)

    def _full_log_prob(self, value: Tensor) -> Tensor:
        """``log_prob`` with the full (uncut) kernels: poses moved out of ``frame`` and the experts' logs summed
        in float64, the kernels evaluated densely in the model's dtype (there is no cut-off to prune)."""
        nb = len(self.batch_shape)
        shape = torch.broadcast_shapes(value.shape[:-1], self.batch_shape)
        sample_shape = shape[: len(shape) - nb]
        flat = value.double().expand(*shape, 7).reshape(-1, *self.batch_shape, 7).movedim(0, nb)  # (*B, M, 7)
        y = se3.Pose.from_vector(flat)
        if self.frame is not None:
            left, right = self.frame
            y = se3.compose(se3.compose(se3.inverse(left), y), se3.inverse(right))
        gamma = self.exponent.double().unsqueeze(-1)  # (E, *B, 1)
        per_expert = expert_log_probs(self.experts(), y)  # (E, *B, M), each expert normalised
        weighted = torch.where(gamma > 0, gamma * per_expert, torch.zeros_like(per_expert))
        out = weighted.sum(0) - self.log_normaliser().unsqueeze(-1)
        return out.movedim(-1, 0).reshape(torch.Size([*sample_shape, *self.batch_shape]))

    def log_prob(self, value: Tensor) -> Tensor:
        """Normalised log density (nats; module docstring) at poses ``(..., *B, 7)`` → ``(..., *B)``;
        −inf outside the kernels' cut-offs. Differentiable with respect to ``value``."""
        if self._validate_args:
            self._validate_sample(value)
        if self.kernels == "full":
            return self._full_log_prob(value)
        queries, sample_shape = self._as_queries(value)
        constant = (self.exponent.double().sum(0) * self.log_kernel_integral() + self.log_normaliser()
                    ).to(queries.dtype)
        out = self._unnormalised(queries) - constant.unsqueeze(-1)  # (*B, M)
        return out.movedim(-1, 0).reshape(torch.Size([*sample_shape, *self.batch_shape]))

    def unnormalised_log_prob(self, value: Tensor) -> Tensor:
        """:meth:`log_prob` up to a constant of each batch element (the normaliser is not estimated): enough to
        order poses by density or colour them, at a fraction of the cost. The full kernels' form
        (``kernels="full"``) is :meth:`log_prob` itself."""
        if self.kernels == "full":
            return self.log_prob(value)
        if self._validate_args:
            self._validate_sample(value)
        queries, sample_shape = self._as_queries(value)
        out = self._unnormalised(queries)  # (*B, M)
        return out.movedim(-1, 0).reshape(torch.Size([*sample_shape, *self.batch_shape]))

    def sample(self, sample_shape: torch.Size | tuple = (), generator: torch.Generator | None = None) -> Tensor:
        """Poses ``(*sample_shape, *B, 7)`` drawn by importance resampling (module docstring); without a
        ``generator`` one seeded with DEFAULT_SEED (the same draws every call).

        As torch's distributions: a ``sample_shape`` with a 0 gives an empty tensor of that shape, a
        negative size is a ``ValueError``. The draws are not reparameterised (``has_rsample`` is False, so
        ``rsample`` raises ``NotImplementedError``): gradients reach ``log_prob``'s queries, not samples.

        Raises:
            ValueError: a negative size in ``sample_shape``.
        """
        try:
            sample_shape = torch.Size(sample_shape)
        except TypeError as exc:
            raise ValueError(f"sample_shape must be a tuple of sizes, got {sample_shape!r}") from exc
        if any(size < 0 for size in sample_shape):
            raise ValueError(f"sample_shape must not hold a negative size, got {tuple(sample_shape)}")
        if sample_shape.numel() == 0:
            return self.means.p.new_empty(*sample_shape, *self.batch_shape, 7)
        n = sample_shape.numel()
        generator = as_generator(generator, self.means.p.device)
        with torch.no_grad():
            experts = self.experts()
            per_expert_draws = max(MIN_POOL_PER_EXPERT, math.ceil(4 * n / self.num_experts))
            pool, _ = experts.sample(per_expert_draws, generator)  # (E, *B, m)
            nb = len(self.batch_shape)
            pool = se3.Pose.unchecked(pool.p.movedim(0, nb).reshape(*self.batch_shape, -1, 3),
                            pool.q.movedim(0, nb).reshape(*self.batch_shape, -1, 4))  # (*B, E·m)
            log_p = experts.log_prob(pool).double() - self.log_kernel_integral().unsqueeze(-1)  # (E, *B, M)
            gamma = self.exponent.double().unsqueeze(-1)
            target = torch.where(gamma > 0, gamma * log_p, torch.zeros_like(log_p)).sum(0)
            mixture = torch.logsumexp(log_p, 0)
            if not torch.isfinite(target).any(-1).all():
                raise ModelError("no proposal has non-zero density under the product of experts")
            # a draw on a cut-off's boundary may round outside every kernel: it weighs nothing
            log_ratio = torch.where(torch.isfinite(mixture), target - mixture, torch.full_like(mixture, -math.inf))
            weights = torch.softmax(log_ratio.reshape(-1, pool.p.shape[-2]), -1)  # (prod B, M)
            index = se3.multinomial(weights, n, generator)
            flat = pool.vector().reshape(-1, pool.p.shape[-2], 7)
            drawn = torch.gather(flat, 1, index.unsqueeze(-1).expand(-1, n, 7))  # (prod B, n, 7)
        drawn = drawn.reshape(*self.batch_shape, n, 7).movedim(nb, 0)
        if self.frame is not None:
            left, right = self.frame
            moved = se3.compose(se3.compose(left, se3.Pose.from_vector(drawn.double())), right)
            drawn = moved.vector().to(drawn.dtype)
        return drawn.reshape(*sample_shape, *self.batch_shape, 7)

    def to(self, device=None, dtype=None) -> FinalPoseDistribution:
        """This distribution on another device and/or floating dtype (the normaliser is kept)."""
        def move(t: Tensor) -> Tensor:
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        centres = None if self.normaliser_centres is None else self.normaliser_centres.to(device=device, dtype=dtype)
        frame = None if self.frame is None else tuple(f.to(device=device) for f in self.frame)
        return self._replace(means=self.means.to(device=device, dtype=dtype), log_weights=move(self.log_weights),
                             trial_rounds=self.trial_rounds.to(device), exponent=move(self.exponent),
                             mode=None if self._mode is None else move(self._mode), normaliser_centres=centres,
                             frame=frame, log_z=None if self._log_z is None else self._log_z.to(device),
                             normaliser_keys=None if self.normaliser_keys is None else self.normaliser_keys.to(device))

    def with_method(self, method: Evaluation | str) -> FinalPoseDistribution:
        """The same distribution evaluated by ``method`` (an :class:`~pushtorch.kde.Evaluation` or its string)."""
        return self._replace(method=Evaluation.of(method), log_z=self._log_z)

    def with_kernels(self, kernels: str) -> FinalPoseDistribution:
        """The same prediction with ``kernels="cut"`` (the model's cut-off kernels: 0 beyond their reach) or
        ``"full"`` (the Gaussian × folded vMF kernels the cut-offs approximate: finite everywhere, as a
        planner's gradients or a likelihood score need); normalised anew."""
        if kernels == self.kernels:
            return self
        return self._replace(kernels=kernels)

    def __repr__(self) -> str:
        return (f"FinalPoseDistribution(batch_shape={tuple(self.batch_shape)}, experts={self.num_experts}, "
                f"kernels={self.means.p.shape[-2]} {self.kernels}, method={self.method.value!r})")


class DefensiveMixture(Distribution):
    """``(1 − ε) · narrow + ε · wide``: a density with a defensive component (Hesterberg 1995), what the residual
    model predicts where its corrections may not hold (:mod:`pushtorch.prediction.residual`; docs/method.md, "The
    residual model"): the same kernels wider, or its rollouts uncorrected. Both parts are normalised, of one batch
    shape: :class:`FinalPoseDistribution`, or mixtures of them in turn; the mode is the narrow part's.

    Raises:
        InvalidParameterError: a share outside ``(0, 1)`` or parts of different batch shapes.
    """

    arg_constraints: dict = {}
    support = constraints.independent(constraints.real, 1)
    has_rsample = False

    def __init__(self, narrow: FinalPoseDistribution, wide: FinalPoseDistribution, share: float,
                 validate_args: bool | None = None) -> None:
        if not 0.0 < float(share) < 1.0:
            raise InvalidParameterError(f"a defensive share lies in (0, 1), got {share!r}")
        if narrow.batch_shape != wide.batch_shape:
            raise InvalidParameterError(f"the parts' batch shapes differ: {tuple(narrow.batch_shape)} and "
                                        f"{tuple(wide.batch_shape)}")
        self.narrow, self.wide, self.share = narrow, wide, float(share)
        super().__init__(batch_shape=narrow.batch_shape, event_shape=torch.Size([7]),
                         validate_args=narrow._validate_args if validate_args is None else validate_args)

    @property
    def mode(self) -> Tensor:
        """``(*B, 7)`` the narrow part's mode."""
        return self.narrow.mode

    def log_prob(self, value: Tensor) -> Tensor:
        """Normalised log density (nats) at poses ``(..., *B, 7)`` → ``(..., *B)``, as the parts'."""
        return torch.logaddexp(self.narrow.log_prob(value) + math.log1p(-self.share),
                               self.wide.log_prob(value) + math.log(self.share))

    def unnormalised_log_prob(self, value: Tensor) -> Tensor:
        """:meth:`log_prob` (the parts' constants differ, so the mixture is scored whole)."""
        return self.log_prob(value)

    def sample(self, sample_shape: torch.Size | tuple = (), generator: torch.Generator | None = None) -> Tensor:
        """Poses ``(*sample_shape, *B, 7)``: each draw from the wide part with probability ``ε``, else the narrow
        (without a ``generator`` one seeded with DEFAULT_SEED: the same draws every call). Sizes as
        :meth:`FinalPoseDistribution.sample`."""
        sample_shape = torch.Size(sample_shape)
        generator = as_generator(generator, _device(self.narrow))
        narrow = self.narrow.sample(sample_shape, generator)
        wide = self.wide.sample(sample_shape, generator)
        pick = torch.rand(narrow.shape[:-1], generator=generator, device=narrow.device) < self.share
        return torch.where(pick.unsqueeze(-1), wide, narrow)

    def to(self, device=None, dtype=None) -> DefensiveMixture:
        """This mixture on another device and/or floating dtype."""
        return DefensiveMixture(self.narrow.to(device, dtype), self.wide.to(device, dtype), self.share,
                                self._validate_args)

    def with_kernels(self, kernels: str) -> DefensiveMixture:
        """Both parts with ``kernels`` (:meth:`FinalPoseDistribution.with_kernels`)."""
        return DefensiveMixture(self.narrow.with_kernels(kernels), self.wide.with_kernels(kernels), self.share,
                                self._validate_args)

    def __repr__(self) -> str:
        return f"DefensiveMixture(share={self.share:g}, narrow={self.narrow!r}, wide={self.wide!r})"


def _device(density) -> torch.device:
    """The device of a :class:`FinalPoseDistribution`, or of a :class:`DefensiveMixture`'s innermost narrow part."""
    return density.means.p.device if isinstance(density, FinalPoseDistribution) else _device(density.narrow)
