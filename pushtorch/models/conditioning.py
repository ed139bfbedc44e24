"""Online adaptation: a posterior over the ground friction and the mass from observed pushes, and a model whose
kernels are re-weighted by it (paper, §Conclusions and future work: "carrying out several sample pushes in an
online fashion … by comparing observed movements of the pushed object with the PDRs already available in the
system"; the "unintentionally biased" general models).

Every motion kernel keeps the friction ``μ`` and mass ``m`` its training push was simulated with
(:attr:`~pushtorch.models.motion.MotionKernels.physics`). The kernels are samples of the training prior: their
parameters ``θ_j = (μ_j, log m_j)`` are the particles of the posterior, each weighted by how well the kernels of
its neighbourhood in ``θ`` explain the observed outcomes (self-normalised importance weights).

*Cells.* The parameters are binned on a grid of up to :data:`CELLS` centres per parameter over the kernels' range,
no closer than :data:`CELL_WIDTH` (one centre where the range is narrower); a kernel belongs to the cells by a
Gaussian membership of one grid spacing, normalised over the cells: ``b_jg``.

*The likelihood of one observation* (:func:`cell_log_likelihood`, evaluated by
:func:`pushtorch.models.evidence.observation_evidence`): the observed push's contacts are placed as a
prediction places them at its robot start, and each expert ``e`` of the product (the manipulator frame and the
environment frames) weighs kernel ``j`` by its contact weight ``w_ej = K^c(c_e | c_j)``. The observed outcome
``y`` (the observed world motion applied at the observed cloud's centroid) has, in cell ``g``, the likelihood
``L_e(g) = Σ_j b_jg w_ej K(y | f_j) / Σ_j b_jg w_ej`` under the kernels ``f_j`` the prediction would use, with
the motion kernel ``K`` uncut and normalised (so no observation has likelihood 0, and models of other bandwidths
compare), the kernels' world motions applied at the same centroid. The experts pool as the prediction does,
``log L(g) = Σ_e γ_e log L_e(g)`` with the exponents ``γ_e`` (:func:`~pushtorch.models.motion.expert_exponents`);
an expert whose contacts reach no kernel of a cell says nothing about it (its own marginal likelihood stands in).
Where the observation has the robot's own final pose, its motion adds :func:`odometry_log_likelihood`.

*The posterior.* ``ℓ_g = Σ_o log L(o | g)`` over the observations, in float64 and in their order, so conditioning
on one push at a time gives the sum conditioning on all at once gives. Each kernel's weight is
``ρ_j = Σ_g b_jg exp(τ ℓ_g) π_g / q_g``, where ``q_g = mean_j b_jg`` is where the kernels crowd and ``π_g`` the
prior: ``q`` itself (the default; then ``ρ_j = 1`` without observations), or the training prior's density
(de-biasing: ``condition_on([], prior=(friction, mass))``). The tempering ``τ ∈ (0, 1]`` is 1 unless the
weights' effective sample size would fall below :func:`ess_floor` kernels; then it is the largest ``τ`` that
keeps the floor (the posterior never collapses onto one push). The posterior's summary is the weighted mean and
spread of the kernels' ``μ`` and ``log m``.

*An observation no kernel explains* (no contact-weighted kernel within :data:`OUTLIER_DISTANCE` and
:data:`OUTLIER_ANGLE` of the observed outcome: a thrown object, a pose a metre away) is left out with a warning
and counted (``rejected``); it never moves the weights.

*A library* (:class:`ConditionedLibrary`): every model is conditioned, and the models are weighed by their
evidence ``log p_M(O) = log Σ_g π_g exp(ℓ_g)`` (untempered): prediction uses the model of highest evidence, or
``H_r`` without observations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.models.motion import MotionKernels

Tensor = torch.Tensor

__all__ = [
    "CELLS",
    "CELL_WIDTH",
    "ODOMETRY_STD",
    "OUTLIER_ANGLE",
    "OUTLIER_DISTANCE",
    "Observation",
    "PhysicsPosterior",
    "PosteriorSummary",
    "cell_log_likelihood",
    "conditioned_model",
    "ess_floor",
    "kernel_physics",
    "log_membership",
    "new_posterior",
    "observation_seed",
    "observations_from_table",
    "odometry_log_likelihood",
    "summarise",
]

#: Grid centres per parameter (μ and log m) of the posterior's cells.
CELLS = 16
#: The robot's odometry noise (m, rad) its own final pose is compared with the kernels' under.
ODOMETRY_STD = (0.005, 0.01)
#: The narrowest cell per parameter: 0.05 in μ, 0.25 in log m (a mass 28 % apart).
CELL_WIDTH = (0.05, 0.25)
#: An observed outcome farther than this (m) from every kernel its contacts reach is not explained.
OUTLIER_DISTANCE = 0.10
#: … or turned farther than this (rad) from every such kernel (a tipped or thrown object).
OUTLIER_ANGLE = math.radians(30.0)
#: The posterior's kernel weights keep an effective sample size of at least this share of the kernels …
ESS_FRACTION = 0.02
#: … and at least this many kernels.
ESS_MINIMUM = 10


def ess_floor(n_kernels: int) -> float:
    """The effective sample size the kernel weights keep: ``max(ESS_FRACTION · N, ESS_MINIMUM)``, at most N."""
    return float(min(n_kernels, max(ESS_FRACTION * n_kernels, ESS_MINIMUM)))


def observation_seed(seed: int, index: int) -> int:
    """The seed of the ``index``-th observation's evidence (its push condition): the same whether the
    observation comes alone or in a batch."""
    return (int(seed) * 1_000_003 + int(index)) % (2**63 - 1)


@dataclass(frozen=True)
class Observation:
    """One observed push.

    Attributes:
        cloud: the object's single-shot cloud before the push (a :class:`~pushtorch.perception.PointCloud`,
            points ``(P, 3)`` or its :class:`~pushtorch.features.SurfaceFeatures`), world frame.
        action: ``(2,)`` the action pushed (ẋ m/s, θ̇ rad/s), one the model was trained for.
        initial_pose, final_pose: the object's observed poses before and after the push (world; any frame
            attached to the object, the same for both: the observed displacement between them is the evidence).
        robot_start: the robot's start pose, or None when the robot pushed from where the model places it.
        robot_final: the robot's own final pose from its odometry (world), or None: evidence about the mass and
            friction the push met (:func:`odometry_log_likelihood`).
    """

    cloud: object
    action: object
    initial_pose: se3.Pose
    final_pose: se3.Pose
    robot_start: se3.Pose | None = None
    robot_final: se3.Pose | None = None

    def __post_init__(self) -> None:
        for name in ("initial_pose", "final_pose", "robot_start", "robot_final"):
            pose = getattr(self, name)
            if pose is None and name in ("robot_start", "robot_final"):
                continue
            if not isinstance(pose, se3.Pose):
                raise InvalidParameterError(f"an observation's {name} must be a pushtorch.se3.Pose, got "
                                            f"{type(pose).__name__}")
            if pose.batch_shape.numel() != 1:
                raise InvalidParameterError(f"an observation's {name} must be one pose, got batch shape "
                                            f"{tuple(pose.batch_shape)}")
            se3.check_pose(pose, f"the observation's {name}")

    @property
    def displacement(self) -> se3.Pose:
        """The observed world motion ``W = B1 ∘ B0⁻¹`` ``()``, float64."""
        b0 = se3.Pose.unchecked(self.initial_pose.p.reshape(3).double(), self.initial_pose.q.reshape(4).double())
        b1 = se3.Pose.unchecked(self.final_pose.p.reshape(3).double(), self.final_pose.q.reshape(4).double())
        return se3.compose(b1, se3.inverse(b0))


def observations_from_table(table, rows: Sequence[int] | None = None) -> list[Observation]:
    """The observed pushes of a push table (:func:`pushtorch.sim.tables.read_push_table`), in row order: each
    row's cloud, action, object poses, robot start and the robot's final pose (its odometry's evidence).

    Args:
        rows: the rows to observe (default: every row).

    Raises:
        RecordFormatError: a row without a cloud.
    """
    records = table.records
    rows = range(len(records)) if rows is None else [int(r) for r in rows]
    return [Observation(table.cloud(i), records.action[i], records.object_initial.take(i),
                        records.object_final.take(i), records.robot_start.take(i),
                        records.robot_trajectory.take((i, -1))) for i in rows]


def kernel_physics(kernels: Sequence[MotionKernels]) -> Tensor:
    """``(N, 2)`` float64 ``(μ, log m)`` of the kernels, concatenated in order.

    Raises:
        ModelError: kernels that do not know their physics (a model trained before kernels kept it).
    """
    parts = []
    for k in kernels:
        if k.physics is None:
            raise ModelError("this model's kernels do not know the ground friction and mass of their pushes, which "
                             "conditioning weighs: train it on pushes that record them (a push table's 'mass' and "
                             "'ground_friction' columns; a model file from before kernels kept them: retrain it)")
        phys = k.physics.detach().double().cpu()
        parts.append(torch.stack([phys[:, 0], phys[:, 1].clamp_min(1e-9).log()], -1))
    return torch.cat(parts)


def _grid(theta: Tensor) -> tuple[Tensor, Tensor]:
    """Cell centres ``(G, 2)`` and membership scales ``(2,)`` over the kernels' ``θ (N, 2)``: per parameter, up to
    :data:`CELLS` centres over the kernels' range, no closer than :data:`CELL_WIDTH` (one centre where the range
    is narrower: a biased model's kernels share one cell)."""
    axes, scales = [], []
    for d in range(theta.shape[1]):
        lo, hi = float(theta[:, d].min()), float(theta[:, d].max())
        count = min(CELLS, int((hi - lo) / CELL_WIDTH[d]) + 1)
        if count < 2:
            axes.append(torch.tensor([0.5 * (lo + hi)], dtype=torch.float64))
            scales.append(max(hi - lo, CELL_WIDTH[d]))
        else:
            axes.append(torch.linspace(lo, hi, count, dtype=torch.float64))
            scales.append((hi - lo) / (count - 1))
    grid = torch.cartesian_prod(*axes).reshape(-1, theta.shape[1])
    return grid, torch.tensor(scales, dtype=torch.float64)


def log_membership(theta: Tensor, centres: Tensor, scale: Tensor) -> Tensor:
    """``(N, G)`` log ``b_jg``: each kernel's Gaussian membership of the cells, normalised over the cells."""
    d2 = (((theta.unsqueeze(1) - centres.unsqueeze(0)) / scale) ** 2).sum(-1)
    return torch.log_softmax(-0.5 * d2, -1)


def _prior_log_density(prior, values: Tensor, log_scale: bool) -> Tensor:
    """The training prior's log density at ``values`` (of ``log m`` when ``log_scale``); a fixed prior is flat."""
    x = values.exp() if log_scale else values
    jacobian = values if log_scale else torch.zeros_like(values)  # p(log m) = p(m) · m
    kind = type(prior).__name__
    if kind == "Uniform":
        inside = (x >= prior.low - 1e-9) & (x <= prior.high + 1e-9)
        base = torch.where(inside, torch.full_like(x, -math.log(prior.high - prior.low)), torch.full_like(x, -60.0))
    elif kind == "Normal":
        base = -0.5 * ((x - prior.loc) / prior.std) ** 2 - math.log(prior.std * math.sqrt(2 * math.pi))
    elif kind == "Fixed":
        return torch.zeros_like(values)
    else:
        raise InvalidParameterError(f"de-biasing needs a Fixed, Uniform or Normal prior, got {prior!r}")
    return base + jacobian


@dataclass
class PhysicsPosterior:
    """A posterior over ``(μ, log m)`` on the cells of a model's kernels (module docstring).

    Attributes:
        centres: ``(G, 2)`` cell centres ``(μ, log m)``; scale: ``(2,)`` the membership's std per parameter.
        log_crowding: ``(G,)`` log ``q_g``, where the model's kernels lie; log_prior: ``(G,)`` log ``π_g``.
        log_likelihood: ``(G,)`` ``ℓ_g``, the sum over the accepted observations (float64).
        observed, rejected: observations accepted and left out as unexplained.
        seed: the seed of the observations' evidence (:func:`observation_seed`).
        debiased: whether ``π`` is the training prior (else the kernels' own crowding).
    """

    centres: Tensor
    scale: Tensor
    log_crowding: Tensor
    log_prior: Tensor
    log_likelihood: Tensor
    observed: int = 0
    rejected: int = 0
    seed: int = 0
    debiased: bool = False

    def with_evidence(self, cells: Tensor | None) -> PhysicsPosterior:
        """This posterior after one more observation (``cells``: its ``(G,)`` log-likelihood; None: rejected)."""
        if cells is None:
            return replace(self, rejected=self.rejected + 1)
        cells = cells.double().cpu()
        if cells.shape != self.log_likelihood.shape or not torch.isfinite(cells).all():
            raise ModelError(f"an observation's cell log-likelihood must be {tuple(self.log_likelihood.shape)} "
                             "finite values")
        return replace(self, log_likelihood=self.log_likelihood + cells, observed=self.observed + 1)

    def log_evidence(self) -> float:
        """``log Σ_g π_g exp(ℓ_g)``: how well the model explains every accepted observation (untempered)."""
        log_pi = torch.log_softmax(self.log_prior, 0)
        return float(torch.logsumexp(log_pi + self.log_likelihood, 0))

    def kernel_log_weights(self, theta: Tensor) -> tuple[Tensor, float]:
        """``(N,)`` log ``ρ_j`` of kernels with parameters ``θ (N, 2)`` (max 0, finite) and the tempering ``τ``
        that keeps their effective sample size above :func:`ess_floor`."""
        log_b = log_membership(theta, self.centres, self.scale)
        ratio = self.log_prior - self.log_crowding

        def weights(tau: float) -> Tensor:
            w = torch.logsumexp(log_b + (tau * self.log_likelihood + ratio).unsqueeze(0), -1)
            return (w - w.max()).clamp_min(-60.0)

        def ess(w: Tensor) -> float:
            e = (w - w.max()).exp()
            return float(e.sum() ** 2 / (e**2).sum())

        floor = ess_floor(len(theta))
        full = weights(1.0)
        if ess(full) >= floor or self.observed == 0:
            return full, 1.0
        lo, hi = 0.0, 1.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ess(weights(mid)) >= floor else (lo, mid)
        return weights(lo), lo

    # -- files ---------------------------------------------------------------------------------

    def arrays(self) -> dict[str, Tensor]:
        return {"posterior.centres": self.centres, "posterior.scale": self.scale,
                "posterior.log_crowding": self.log_crowding, "posterior.log_prior": self.log_prior,
                "posterior.log_likelihood": self.log_likelihood}

    def header(self) -> dict:
        return {"observed": self.observed, "rejected": self.rejected, "seed": self.seed, "debiased": self.debiased}

    @staticmethod
    def from_file(header: dict, arrays: dict[str, Tensor]) -> PhysicsPosterior:
        for key in ("observed", "rejected", "seed"):
            if not isinstance(header[key], int) or isinstance(header[key], bool) or header[key] < 0:
                raise TypeError(f"posterior field {key!r} must be an integer >= 0, got {header[key]!r}")
        if not isinstance(header["debiased"], bool):
            raise TypeError(f"posterior field 'debiased' must be a boolean, got {header['debiased']!r}")
        t = {k.split(".", 1)[1]: v.double() for k, v in arrays.items() if k.startswith("posterior.")}
        return PhysicsPosterior(t["centres"], t["scale"], t["log_crowding"], t["log_prior"], t["log_likelihood"],
                                header["observed"], header["rejected"], header["seed"], header["debiased"])


def new_posterior(kernels: Sequence[MotionKernels], seed: int = 0, prior: tuple | None = None) -> PhysicsPosterior:
    """The prior posterior of a model with these kernels (every action's, both kinds): its cells, where the
    kernels crowd and, with ``prior`` ``(friction prior, mass prior)``, the training prior to de-bias towards."""
    theta = kernel_physics(kernels)
    centres, scale = _grid(theta)
    log_crowding = torch.logsumexp(log_membership(theta, centres, scale), 0) - math.log(len(theta))
    if prior is None:
        log_prior = log_crowding.clone()
    else:
        friction, mass = prior
        log_prior = torch.log_softmax(_prior_log_density(friction, centres[:, 0], False)
                                      + _prior_log_density(mass, centres[:, 1], True), 0)
    return PhysicsPosterior(centres, scale, log_crowding, log_prior, torch.zeros(len(centres), dtype=torch.float64),
                            seed=int(seed), debiased=prior is not None)


def cell_log_likelihood(log_membership: Sequence[Tensor], contact_log_weights: Sequence[Tensor],
                        log_kernels: Sequence[Tensor], exponents: Tensor) -> Tensor:
    """``(G,)`` ``log L(g)`` of one observation (module docstring).

    Args:
        log_membership: per contact kind, ``(N_k, G)`` log ``b_jg`` of its kernels.
        contact_log_weights: per kind, ``(F_k, N_k)`` the experts' contact log weights (``-inf``: cut off).
        log_kernels: per kind, ``(N_k,)`` log ``K(y | f_j)`` of the observed outcome under each kernel.
        exponents: ``(Σ F_k,)`` the experts' exponents ``γ_e``, kinds in order.
    """
    rows = []
    for log_b, log_w, log_k in zip(log_membership, contact_log_weights, log_kernels, strict=True):
        # the posterior lives on the CPU in float64, whatever device the model predicts on
        log_b, log_w, log_k = log_b.double().cpu(), log_w.double().cpu(), log_k.double().cpu()
        num = torch.logsumexp(log_w.unsqueeze(-1) + (log_k.unsqueeze(-1) + log_b).unsqueeze(0), 1)  # (F, G)
        den = torch.logsumexp(log_w.unsqueeze(-1) + log_b.unsqueeze(0), 1)
        marginal = torch.logsumexp(log_w + log_k, -1) - torch.logsumexp(log_w, -1)  # (F,)
        supported = torch.isfinite(den) & torch.isfinite(num)
        rows.append(torch.where(supported, num - den, marginal.unsqueeze(-1)))
    per_expert = torch.cat(rows)  # (E, G)
    per_expert = torch.where(torch.isfinite(per_expert), per_expert, torch.zeros_like(per_expert))
    return (exponents.double().cpu().unsqueeze(-1) * per_expert).sum(0)


def odometry_log_likelihood(log_membership: Tensor, robot_motion: Tensor, observed: Tensor) -> Tensor:
    """``(G,)`` log-likelihood per cell of the robot's own observed motion ``(3,)`` (x, y, yaw in its start frame)
    under the kernels' ``robot_motion (N, 3)``: ``log Σ_j b_jg N(r | r_j, ODOMETRY_STD²) − log Σ_j b_jg``.

    A loaded robot falls behind its command, and the motion it makes barely depends on where the object sat, so
    every kernel of the action takes part (one per push: the manipulator kernels)."""
    std = torch.tensor([ODOMETRY_STD[0], ODOMETRY_STD[0], ODOMETRY_STD[1]], dtype=torch.float64)
    diff = robot_motion.double().cpu() - observed.double().cpu().reshape(1, 3)
    diff[:, 2] = torch.atan2(torch.sin(diff[:, 2]), torch.cos(diff[:, 2]))
    log_n = (-0.5 * (diff / std) ** 2 - torch.log(std * math.sqrt(2 * math.pi))).sum(-1)  # (N,)
    log_b = log_membership.double().cpu()
    return torch.logsumexp(log_b + log_n.unsqueeze(-1), 0) - torch.logsumexp(log_b, 0)


@dataclass
class PosteriorSummary:
    """What :meth:`~pushtorch.models.model.PushModel.posterior` returns.

    Attributes:
        samples: ``(n, 2)`` draws of ``(μ, m kg)`` from the posterior (kernels' parameters by weight).
        mu_mean, mu_std: the friction coefficient's posterior mean and spread.
        log_mass_mean, log_mass_std: the same of the natural log of the mass in kg.
        observed, rejected: observations used and left out.
        ess: the effective sample size of the kernel weights; tempering: ``τ``.
        model_weights: a library's posterior over its models (name → probability), else None.
    """

    samples: Tensor
    mu_mean: float
    mu_std: float
    log_mass_mean: float
    log_mass_std: float
    observed: int
    rejected: int
    ess: float
    tempering: float = 1.0
    model_weights: dict[str, float] | None = field(default=None)

    def as_record(self) -> dict[str, float]:
        return {"mu_mean": self.mu_mean, "mu_std": self.mu_std, "log_mass_mean": self.log_mass_mean,
                "log_mass_std": self.log_mass_std}


def summarise(theta: Tensor, log_weights: Tensor, n: int, generator: torch.Generator | None, observed: int,
              rejected: int, tempering: float = 1.0, model_weights: dict[str, float] | None = None) -> PosteriorSummary:
    """The weighted moments of kernel parameters ``θ (N, 2)`` under ``log_weights (N,)`` and ``n`` draws."""
    w = torch.softmax(log_weights.double(), 0)
    mean = (w.unsqueeze(-1) * theta).sum(0)
    std = (w.unsqueeze(-1) * (theta - mean) ** 2).sum(0).clamp_min(0).sqrt()
    draws = theta[torch.multinomial(w, n, replacement=True, generator=generator)] if n > 0 else theta[:0]
    samples = torch.stack([draws[:, 0], draws[:, 1].exp()], -1)
    ess = float(1.0 / (w**2).sum())
    return PosteriorSummary(samples, float(mean[0]), float(std[0]), float(mean[1]), float(std[1]), observed,
                            rejected, ess, tempering, model_weights)


def conditioned_model(model, posterior: PhysicsPosterior):
    """A copy of ``model`` (a :class:`~pushtorch.models.model.PushModel`) whose kernels carry the posterior's
    weights (every action, both kinds) and which keeps ``posterior``."""
    theta = kernel_physics(model.motion_kernels)
    log_w, _ = posterior.kernel_log_weights(theta)
    motions, start = [], 0
    for m in model.motions:
        parts = []
        for k in (m.manipulator, m.environment):
            w = log_w[start: start + len(k)].to(dtype=k.r.dtype, device=k.r.device)
            start += len(k)
            unchanged = posterior.observed == 0 and not posterior.debiased
            parts.append(replace(k, log_weight=None if unchanged else w))
        motions.append(replace(m, manipulator=parts[0], environment=parts[1]))
    return replace(model, motions=motions, physics_posterior=posterior, meta=dict(model.meta))
