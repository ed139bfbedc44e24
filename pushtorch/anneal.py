"""Simulated annealing over SE(3), batched over candidates and problems.

Paper, Query Density (and Motion Model, which reuses it): "sample from a discrete distribution over the
mean points of the kernels … using the weights", then "perform simulated annealing based optimisation
upon the candidates aiming to maximise the likelihood approximated by KDE", and keep the candidate with
the highest likelihood. The paper gives no schedule; this one follows the method's lineage (see
docs/method.md and the shared lineage notes):

* temperature falls linearly from ``t_start`` (1) to ``t_end`` (0.1) over ``steps`` steps;
* a proposal perturbs each candidate with a translation of per-axis std ``step_p_std · T`` and a
  rotation of per-axis std ``step_rot_std · T`` (a vMF of concentration κ = 4 / (step_rot_std · T)²,
  i.e. the lineage's "concentration ∝ 1/(δT)²");
* it is accepted if better, or if ``exp(Δ log L / (E · T)) > U(0, 1)`` with energy scale ``E``;
* ``planar=True`` perturbs only x, y and the yaw about the world z axis (a push on a table is planar):
  z, roll and pitch stay exactly as initialised.

Every candidate of every problem moves at once: the only Python loop is over steps. ``method="fast"``
draws the same proposals with cheaper exact samplers, 20 steps' worth at a time, runs each step's
proposal and Metropolis test as one fused (compiled when possible) call — against a
:class:`~pushtorch.kde.SharedKernelProduct` (the motion model's product of experts) the density's
evaluation too, so a step is one call — and lets planar and free problems share one batch (a
per-problem ``planar`` mask), which the fast prediction path uses to anneal the robot's and the object's
query densities together.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import PoseKDE, SharedKernelProduct, fast_path_compiled, fused_function
from pushtorch.kde.fused import _block_sums, _reachable_blocks
from pushtorch.kde.products import _shared_kernel_product
from pushtorch.se3 import (
    Pose,
    check_unit_quaternion,
    perturb,
    random_normal,
    random_uniform,
    vmf_offsets,
    yaw_quaternion,
)

Tensor = torch.Tensor

__all__ = ["AnnealResult", "AnnealSchedule", "anneal", "initial_candidates", "polish_candidates"]


@dataclass(frozen=True)
class AnnealSchedule:
    """Steps, temperatures and perturbation sizes of :func:`anneal`.

    Attributes:
        steps: number of annealing steps (default 100; the lineage runs about 500).
        t_start, t_end: temperature of the first and last step, linear in between (lineage: 1 → 0.1).
        step_p_std: translation std per axis (m) of a proposal at T = 1; scaled by T (lineage: 2–3 mm).
        step_rot_std: rotation std per axis (rad) of a proposal at T = 1; scaled by T. Default 0.06 rad
            matches the lineage's vMF concentration 1000 / (δT)² (std 2/√κ per axis).
        energy_scale: E in the acceptance test exp(Δ log L / (E T)) > U(0, 1) (lineage: 0.05–0.5).
        planar: perturb only x, y and yaw about the world z axis.
    """

    steps: int = 100
    t_start: float = 1.0
    t_end: float = 0.1
    step_p_std: float = 0.003
    step_rot_std: float = 0.06
    energy_scale: float = 0.1
    planar: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.steps, bool) or int(self.steps) != self.steps or self.steps < 0:
            raise InvalidParameterError(f"steps must be an integer >= 0, got {self.steps!r}")
        object.__setattr__(self, "steps", int(self.steps))
        for name in ("t_start", "t_end", "energy_scale"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value <= 0:
                raise InvalidParameterError(f"{name} must be finite and > 0, got {value}")
            object.__setattr__(self, name, value)
        for name in ("step_p_std", "step_rot_std"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise InvalidParameterError(f"{name} must be finite and >= 0, got {value}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "planar", bool(self.planar))

    def temperatures(self) -> list[float]:
        """The temperature of each step, linear from ``t_start`` to ``t_end`` (both included)."""
        if self.steps == 1:
            return [self.t_start]
        span = self.t_end - self.t_start
        return [self.t_start + span * k / (self.steps - 1) for k in range(self.steps)]


@dataclass
class AnnealResult:
    """What :func:`anneal` returns.

    Attributes:
        best: the best pose found per problem, Pose ``(*B,)``.
        best_log_prob: its log-likelihood ``(*B,)``.
        candidates: the best pose each candidate's chain visited, Pose ``(*B, C)`` (the paper's "several
            candidates with associated likelihoods").
        log_prob: their log-likelihoods ``(*B, C)``.
        history: the chains' current poses before step 1 and after every step, Pose ``(steps+1, *B, C)``,
            if recorded (for Rerun); else None. After :func:`polish_candidates` the polished candidates
            are one more step.
        history_log_prob: their log-likelihoods ``(steps+1, *B, C)``, if recorded.
    """

    best: Pose
    best_log_prob: Tensor
    candidates: Pose
    log_prob: Tensor
    history: Pose | None = None
    history_log_prob: Tensor | None = None


def initial_candidates(kde: PoseKDE, n: int, generator: torch.Generator | None = None) -> Pose:
    """Annealing start points: kernel means drawn with probability equal to their weights.

    Paper (Query Density): "sample from a discrete distribution over the mean points of the kernels …
    using the weights associated with each kernel to determine their likelihood of being selected".

    Args:
        kde: the density; n: candidates per batch element; generator: seeded torch.Generator.

    Returns:
        Pose ``(*B, n)`` (``kde.batch_shape``).
    """
    return kde.kernel_means(kde.sample_kernels(n, generator))


def _propose(pose: Pose, temperature: float, schedule: AnnealSchedule, generator) -> Pose:
    p_std = schedule.step_p_std * temperature
    rot_std = schedule.step_rot_std * temperature
    if schedule.planar:
        noise = random_normal(pose.p.shape[:-1] + (2,), generator, pose.p.dtype, pose.p.device)
        p = pose.p.clone()
        p[..., :2] += p_std * noise
        yaw = rot_std * random_normal(pose.q.shape[:-1], generator, pose.q.dtype, pose.q.device)
        # A world-frame rotation about z (left product) changes the heading only: roll and pitch are kept.
        q = pkt.quaternion_raw_multiply(yaw_quaternion(yaw), pose.q)
    else:
        # vMF on S^3 has per-axis rotation-vector std 2/√κ for large κ; rot_std = 0 means no rotation.
        kappa = 4.0 / rot_std**2 if rot_std > 0 else 1e12
        p, q = perturb(pose, p_std, kappa, generator)
    return Pose.unchecked(p, q / q.norm(dim=-1, keepdim=True))


# Steps whose proposals the fast path draws at once: few generator calls, bounded memory
# (20 steps × 32 conditions × 1,000 chains × 12 floats ≈ 31 MB).
_DRAW_STEPS = 20


def _draw_fast_proposals(
    temperatures: list[float], shape: torch.Size, schedule: AnnealSchedule, generator, planar: Tensor | None,
    dtype, device,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The random parts of several steps' proposals and acceptance tests, drawn in a few calls.

    Returns translation offsets ``(S, *shape, 3)``, left (world yaw, planar chains) and right (body
    vMF, free chains) rotation offsets ``(S, *shape, 4)`` — the proposal is ``left ⊗ q ⊗ right`` — and
    the acceptance uniforms ``(S, *shape)``. The same distributions as :func:`_propose`: a planar chain
    moves in x, y and the yaw about world z, a free chain by an isotropic translation and a vMF rotation.
    """
    steps = len(temperatures)
    full = torch.Size([steps, *shape])
    t = torch.tensor(temperatures, dtype=dtype, device=device).reshape(steps, *([1] * len(shape)))
    if planar is None and schedule.planar:
        planar = torch.ones((), dtype=torch.bool, device=device)
    noise = random_normal((*full, 3), generator, dtype, device)
    if planar is not None:
        noise = torch.where(planar.unsqueeze(-1) & _Z_AXIS.to(device), torch.zeros_like(noise), noise)
    step_p = noise * (schedule.step_p_std * t).unsqueeze(-1)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device).expand(*full, 4)
    left = right = identity
    if schedule.step_rot_std > 0:
        rot_std = schedule.step_rot_std * t
        right = vmf_offsets(4.0 / rot_std**2, full, generator, dtype, device)
        if planar is not None:
            yaw = rot_std * random_normal(full, generator, dtype, device)
            left = torch.where(planar.unsqueeze(-1), yaw_quaternion(yaw), identity)
            right = torch.where(planar.unsqueeze(-1), identity, right)
    accept_u = random_uniform(full, generator, dtype, device)
    return step_p, left.contiguous(), right.contiguous(), accept_u


def _drawn_steps(schedule: AnnealSchedule, shape: torch.Size, generator, planar: Tensor | None, dtype, device):
    """The fast path's steps in chunks of :data:`_DRAW_STEPS`: yields each chunk's temperatures and its
    pre-drawn proposals and acceptance uniforms (:func:`_draw_fast_proposals`), in the one order every
    fast loop draws them, so they share the seed's random stream."""
    temperatures = schedule.temperatures()
    for start in range(0, len(temperatures), _DRAW_STEPS):
        chunk = temperatures[start : start + _DRAW_STEPS]
        yield chunk, *_draw_fast_proposals(chunk, shape, schedule, generator, planar, dtype, device)


def _fast_proposal(p: Tensor, q: Tensor, step_p: Tensor, left: Tensor, right: Tensor, component_dim: int = -1
                   ) -> tuple[Tensor, Tensor]:
    """One step's proposals from pre-drawn offsets (fused): ``p + Δp``, ``normalise(left ⊗ q ⊗ right)``, with
    the pose components along ``component_dim``."""
    rows = [t.movedim(component_dim, -1) for t in (left, q, right)]
    turned = pkt.quaternion_raw_multiply(pkt.quaternion_raw_multiply(rows[0], rows[1]), rows[2])
    turned = turned.movedim(-1, component_dim)
    return p + step_p, turned / turned.norm(dim=component_dim, keepdim=True)


def _fast_acceptance(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor,
    prop_p: Tensor, prop_q: Tensor, prop_lp: Tensor, u: Tensor, inverse_energy: Tensor, saw_nan: Tensor,
    component_dim: int = -1,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The Metropolis test and the best-so-far update of one step (fused); see :func:`anneal`.
    ``saw_nan`` accumulates whether any proposal's log-likelihood was NaN (never accepted). Poses hold
    their components along ``component_dim`` (-1, or -2 for rows ``(…, 3|4, C)``)."""
    accept = (prop_lp > lp) | (torch.exp((prop_lp - lp) * inverse_energy) > u)
    p = torch.where(accept.unsqueeze(component_dim), prop_p, p)
    q = torch.where(accept.unsqueeze(component_dim), prop_q, q)
    lp = torch.where(accept, prop_lp, lp)
    improved = lp > best_lp
    best_p = torch.where(improved.unsqueeze(component_dim), p, best_p)
    best_q = torch.where(improved.unsqueeze(component_dim), q, best_q)
    best_lp = torch.where(improved, lp, best_lp)
    return p, q, lp, best_p, best_q, best_lp, saw_nan | torch.isnan(prop_lp).any()


def _chain_state(p: Tensor, q: Tensor, lp: Tensor) -> tuple[Tensor, ...]:
    """The fused steps' state at the start: current and best poses and log-likelihoods, and the NaN flag.
    Distinct tensors: aliased inputs would make torch.compile guard on the aliasing and recompile."""
    return (p.clone(), q.clone(), lp.clone(), p.clone(), q.clone(), lp.clone(),
            torch.zeros((), dtype=torch.bool, device=p.device))


def _shared_product_step(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor, saw_nan: Tensor,
    step_p: Tensor, left: Tensor, right: Tensor, u: Tensor, inverse_energy: Tensor,
    table: Tensor, weights: Tensor, scale: Tensor, offset: Tensor, exponent: Tensor, delta_p: float, delta_q: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A whole annealing step against a :class:`~pushtorch.kde.SharedKernelProduct`'s problems: proposal,
    the product's log-likelihood and the Metropolis test in one fused call (issue 18: one compiled call
    per step instead of three, and none of the eager glue between them).

    Poses and offsets are rows, ``p (D, 3, C)``, ``q``, ``left``, ``right (D, 4, C)``; ``lp``, ``u (D, C)``:
    the compiled kernel loop then reads every query component at unit stride and vectorises (laid out
    ``(D, C, 7)`` it ran scalar and the fused step was 2.7x slower than three calls, measured). Other
    arguments as :func:`_fast_acceptance` and ``products._shared_kernel_product``.
    """
    prop_p, prop_q = _fast_proposal(p, q, step_p, left, right, component_dim=-2)
    prop_lp = _shared_kernel_product(torch.cat([prop_p, prop_q], 1), table, weights, scale, offset, exponent,
                                     delta_p, delta_q)
    p, q, lp, best_p, best_q, best_lp, saw_nan = _fast_acceptance(
        p, q, lp, best_p, best_q, best_lp, prop_p, prop_q, prop_lp, u, inverse_energy, saw_nan, component_dim=-2)
    # rows out as rows in: an input laid out otherwise fails the compiled step's stride guard and recompiles
    return p.contiguous(), q.contiguous(), lp, best_p.contiguous(), best_q.contiguous(), best_lp, saw_nan


def _anneal_shared_product(
    product: SharedKernelProduct, current: Pose, current_lp: Tensor, schedule: AnnealSchedule, generator,
    planar: Tensor | None,
) -> tuple[Pose, Tensor, Tensor]:
    """The fast path's steps against a shared-kernel product: the same draws as the generic loop (so the
    same random stream), each step one fused call per cache-sized chunk of problems. Returns the best
    poses, their log-likelihoods and whether a proposal's log-likelihood was NaN."""
    shape = current.batch_shape
    d, c = product.table.shape[0], shape[-1]
    dtype, device = current.p.dtype, current.p.device
    step = fused_function("anneal_shared_product_step", _shared_product_step, device)
    chunks = product.problem_chunks(c)
    layouts = [product.chunk_layout(a, b) for a, b in chunks]

    def rows(t: Tensor, width: int) -> Tensor:  # (…, D·C, width) → (…, D, width, C), contiguous
        return t.reshape(*t.shape[: t.dim() - len(shape) - 1], d, c, width).transpose(-1, -2).contiguous()

    states = []
    for a, b in chunks:
        p, q, lp = rows(current.p, 3)[a:b], rows(current.q, 4)[a:b], current_lp.reshape(d, c)[a:b]
        states.append(_chain_state(p, q, lp))
    for chunk, step_p, left, right, accept_u in _drawn_steps(schedule, shape, generator, planar, dtype, device):
        step_p, left, right = rows(step_p, 3), rows(left, 4), rows(right, 4)
        accept_u = accept_u.reshape(len(chunk), d, c)
        inverse_energy = [torch.tensor(1.0 / (schedule.energy_scale * t), dtype=dtype, device=device) for t in chunk]
        for i, (a, b) in enumerate(chunks):
            state = states[i]
            for k in range(len(chunk)):
                state = step(*state, step_p[k, a:b], left[k, a:b], right[k, a:b], accept_u[k, a:b],
                             inverse_energy[k], *layouts[i], product.delta_p, product.delta_q)
            states[i] = state
    best_p = torch.cat([s[3] for s in states]).transpose(1, 2).reshape(*shape, 3)
    best_q = torch.cat([s[4] for s in states]).transpose(1, 2).reshape(*shape, 4)
    best_lp = torch.cat([s[5] for s in states]).reshape(shape)
    saw_nan = torch.stack([s[6] for s in states]).any()
    return Pose.unchecked(best_p, best_q), best_lp, saw_nan


def _propose_and_reach(
    p: Tensor, q: Tensor, step_p: Tensor, left: Tensor, right: Tensor,
    lo: Tensor, hi: Tensor, centre: Tensor, cos_reach: Tensor, r2: Tensor,
) -> tuple[Tensor, Tensor]:
    """A step's proposals against a block-pruned density (fused): the proposals as query rows
    ``(D, C, 7)`` and which leaf blocks each may touch ``(D, C, nb)`` (see ``kde.fused._reachable_blocks``)."""
    prop_p, prop_q = _fast_proposal(p, q, step_p, left, right)
    x = torch.cat([prop_p, prop_q], -1)
    return x, _reachable_blocks(x.transpose(1, 2), lo, hi, centre, cos_reach, r2)


def _block_step_acceptance(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor, saw_nan: Tensor,
    x: Tensor, u: Tensor, inverse_energy: Tensor, table: Tensor, scale: Tensor, query_density: Tensor,
    pair_query: Tensor, pair_block: Tensor, num_blocks: int, log_w_max: Tensor, delta_p: float, delta_q: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The rest of that step (fused): the proposals' log densities over their (query, block) pairs and the
    Metropolis test. ``log_w_max (D, 1)`` is each density's largest log weight (the table's are relative)."""
    total = _block_sums(x.reshape(-1, 7), table, scale, query_density, pair_query, pair_block, num_blocks,
                        delta_p, delta_q)
    prop_lp = torch.log(total.reshape(lp.shape)) + log_w_max
    return _fast_acceptance(p, q, lp, best_p, best_q, best_lp, x[..., :3], x[..., 3:], prop_lp, u, inverse_energy,
                            saw_nan)


def _anneal_pruned_kde(
    kde: PoseKDE, current: Pose, current_lp: Tensor, schedule: AnnealSchedule, generator, planar: Tensor | None,
) -> tuple[Pose, Tensor, Tensor]:
    """The fast path's steps against a density on pruned leaf blocks: the same draws as the generic loop,
    each step two fused calls — proposal with block reach, then the pair sums with the Metropolis test —
    around the one data-dependent step, the list of (query, block) pairs, instead of four calls and the
    glue of :meth:`PoseKDE.log_prob`. Returns as :func:`_anneal_shared_product`."""
    index = kde.fast_index()
    shape = current.batch_shape
    d, c = max(1, kde.batch_shape.numel()), shape[-1]
    dtype, device = current.p.dtype, current.p.device
    propose = fused_function("anneal_propose_and_reach", _propose_and_reach, device)
    accept = fused_function("anneal_block_step_acceptance", _block_step_acceptance, device)
    p, q, lp = current.p.reshape(d, c, 3), current.q.reshape(d, c, 4), current_lp.reshape(d, c)
    state = _chain_state(p, q, lp)
    query_density = torch.arange(d, device=device).repeat_interleave(c)
    log_w_max = index.log_w_max.reshape(d, 1)
    bounds = (index.lo, index.hi, index.centre, index.cos_reach, index.r2)
    for chunk, step_p, left, right, accept_u in _drawn_steps(schedule, shape, generator, planar, dtype, device):
        step_p, accept_u = step_p.reshape(len(chunk), d, c, 3), accept_u.reshape(len(chunk), d, c)
        left, right = left.reshape(len(chunk), d, c, 4), right.reshape(len(chunk), d, c, 4)
        for k, temperature in enumerate(chunk):
            x, reach = propose(state[0], state[1], step_p[k], left[k], right[k], *bounds)
            pair_query, pair_block = (reach.reshape(d * c, index.num_blocks) > 0).nonzero(as_tuple=True)
            inverse_energy = torch.tensor(1.0 / (schedule.energy_scale * temperature), dtype=dtype, device=device)
            state = accept(*state, x, accept_u[k], inverse_energy, index.table, index.scale, query_density,
                           pair_query, pair_block, index.num_blocks, log_w_max, index.delta_p, index.delta_q)
    return Pose.unchecked(state[3].reshape(*shape, 3), state[4].reshape(*shape, 4)), state[5].reshape(shape), state[6]


_Z_AXIS = torch.tensor([False, False, True])


def _evaluate(log_prob_fn: Callable[[Pose], Tensor], pose: Pose, shape: torch.Size) -> Tensor:
    with torch.no_grad():
        value = log_prob_fn(pose)
    if not isinstance(value, Tensor) or value.shape != shape:
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ModelError(f"log_prob_fn must return a tensor of shape {tuple(shape)} (*B, C), got {got}")
    if torch.isnan(value).any():
        raise ModelError("log_prob_fn returned NaN log-likelihoods (use -inf for zero density)")
    if (value == math.inf).any():
        raise ModelError("log_prob_fn returned +inf log-likelihoods")
    return value


def _anneal_fast_steps(
    log_prob_fn: Callable[[Pose], Tensor], current: Pose, current_lp: Tensor, schedule: AnnealSchedule,
    generator, planar: Tensor | None, record_history: bool,
) -> tuple[Pose, Tensor, tuple[list[Tensor], list[Tensor], list[Tensor]]]:
    """The fast path's steps: proposals pre-drawn for :data:`_DRAW_STEPS` steps at a time, proposal and
    acceptance each one fused (compiled when possible) call, ``log_prob_fn``'s values checked once at
    the end instead of at every step (a NaN is never accepted, so a flag records it without a sync;
    the shape was checked on the initial evaluation)."""
    shape = current.batch_shape
    dtype, device = current.p.dtype, current.p.device
    own_problems = shape[:-1] == getattr(log_prob_fn, "batch_shape", None)
    if isinstance(log_prob_fn, SharedKernelProduct) and own_problems and not record_history:
        best, best_lp, saw_nan = _anneal_shared_product(log_prob_fn, current, current_lp, schedule, generator, planar)
        _raise_on_bad_values(saw_nan, best_lp)
        return best, best_lp, ([], [], [])
    if isinstance(log_prob_fn, PoseKDE):
        index = log_prob_fn.fast_index()
        # eagerly the generic loop's pair sums are chunked in memory; the fused step streams them compiled
        if index.blocks and index.linear and own_problems and not record_history and fast_path_compiled(device):
            best, best_lp, saw_nan = _anneal_pruned_kde(log_prob_fn, current, current_lp, schedule, generator,
                                                        planar)
            _raise_on_bad_values(saw_nan, best_lp)
            return best, best_lp, ([], [], [])
        log_prob_fn = partial(log_prob_fn.log_prob, method="fast")
    propose = fused_function("anneal_proposal", _fast_proposal, device)
    accept = fused_function("anneal_acceptance", _fast_acceptance, device)
    p, q, lp = current.p, current.q, current_lp
    # distinct tensors: aliased inputs would make torch.compile guard on the aliasing and recompile
    best_p, best_q, best_lp = p.clone(), q.clone(), lp.clone()
    history: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([p], [q], [lp])
    saw_nan = torch.zeros((), dtype=torch.bool, device=device)
    for chunk, step_p, left, right, accept_u in _drawn_steps(schedule, shape, generator, planar, dtype, device):
        for k, temperature in enumerate(chunk):
            prop_p, prop_q = propose(p, q, step_p[k], left[k], right[k])
            with torch.no_grad():
                prop_lp = log_prob_fn(Pose.unchecked(prop_p, prop_q))
            inverse_energy = torch.tensor(1.0 / (schedule.energy_scale * temperature), dtype=dtype, device=device)
            p, q, lp, best_p, best_q, best_lp, saw_nan = accept(
                p, q, lp, best_p, best_q, best_lp, prop_p, prop_q, prop_lp, accept_u[k], inverse_energy, saw_nan)
            if record_history:
                history[0].append(p)
                history[1].append(q)
                history[2].append(lp)
    _raise_on_bad_values(saw_nan, best_lp)
    return Pose.unchecked(best_p, best_q), best_lp, history


def _raise_on_bad_values(saw_nan: Tensor, best_lp: Tensor) -> None:
    """The fast path's one check of ``log_prob_fn``'s values, after the steps (one sync, not one per step)."""
    if bool(saw_nan):
        raise ModelError("log_prob_fn returned NaN log-likelihoods (use -inf for zero density)")
    if bool((best_lp == math.inf).any()):
        raise ModelError("log_prob_fn returned +inf log-likelihoods")


def anneal(
    log_prob_fn: Callable[[Pose], Tensor],
    init: Pose,
    schedule: AnnealSchedule | None = None,
    generator: torch.Generator | None = None,
    record_history: bool = False,
    planar: Tensor | None = None,
    method: str = "dense",
) -> AnnealResult:
    """Maximise ``log_prob_fn`` over SE(3) by simulated annealing from every candidate of ``init``.

    Args:
        log_prob_fn: maps Pose ``(*B, C)`` to log-likelihoods ``(*B, C)`` (e.g. a :class:`PoseKDE` or a
            :class:`~pushtorch.kde.ProductOfExperts` of batch shape ``*B``); evaluated under no_grad.
            ``-inf`` is allowed (zero density); NaN is not.
        init: start poses ``p (*B, C, 3)``, ``q (*B, C, 4)`` (unit, w,x,y,z), e.g. from
            :func:`initial_candidates`.
        schedule: the :class:`AnnealSchedule`; default AnnealSchedule().
        generator: seeded torch.Generator for reproducible runs.
        record_history: keep every step's chain poses and log-likelihoods (memory ``steps × B × C``).
        planar: optional bool ``(*B,)`` per problem: planar moves (x, y, yaw) where True, full SE(3)
            moves where False, so planar and free problems anneal in one batch; None uses
            ``schedule.planar`` for all. Needs ``method="fast"``.
        method: ``"dense"``, the reference proposals (one step's draws at a time, :func:`pushtorch.se3.perturb`),
            or ``"fast"``: the same proposal distributions, several steps drawn at once and applied in fused
            calls. Both draw rotations with :func:`pushtorch.se3.vmf_offsets`; the seed's random stream
            differs between the two. With ``"fast"``, a :class:`PoseKDE` given as ``log_prob_fn`` is
            evaluated by its own fast path (``log_prob(..., method="fast")``: the same values up to
            float rounding), and a pruned one or a :class:`~pushtorch.kde.SharedKernelProduct` anneals in
            steps fused with their evaluation.

    Returns:
        :class:`AnnealResult`. A candidate at ``-inf`` accepts any finite proposal; if its proposal is
        also ``-inf`` it keeps its pose.

    Raises:
        InvalidPoseError: ``init`` without a candidate dim or with non-unit quaternions.
        ModelError: ``log_prob_fn`` returns the wrong shape, NaN or +inf.
    """
    schedule = AnnealSchedule() if schedule is None else schedule
    if method not in ("dense", "fast"):
        raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}")
    fast_kde = method == "fast" and isinstance(log_prob_fn, PoseKDE)
    shape = init.batch_shape
    if planar is not None:
        if method != "fast":
            raise InvalidParameterError("a per-problem planar mask needs method='fast'")
        planar = torch.as_tensor(planar, device=init.p.device)
        if planar.dtype != torch.bool:
            raise InvalidParameterError(f"planar must be a bool tensor, got {planar.dtype}")
        try:
            torch.broadcast_shapes(planar.shape, shape[:-1])
        except RuntimeError as exc:
            raise InvalidParameterError(
                f"planar {tuple(planar.shape)} does not broadcast to the problems {tuple(shape[:-1])}"
            ) from exc
        planar = planar.unsqueeze(-1)  # over candidates
    if len(shape) == 0 or shape[-1] == 0:
        raise InvalidPoseError(
            f"init must have a candidate dim, Pose (*B, C) with C >= 1; got {tuple(shape)}"
        )
    if not torch.isfinite(init.p).all():
        raise InvalidPoseError("init positions hold NaN or infinite values")
    check_unit_quaternion(init.q, name="init.q")
    current = Pose.unchecked(init.p.expand(*shape, 3).clone(), init.q.expand(*shape, 4).clone())
    current = Pose.unchecked(current.p, current.q / current.q.norm(dim=-1, keepdim=True))
    evaluate = partial(log_prob_fn.log_prob, method="fast") if fast_kde else log_prob_fn
    current_lp = _evaluate(evaluate, current, shape)
    best, best_lp = current, current_lp
    history_p, history_q, history_lp = [current.p], [current.q], [current_lp]
    dtype, device = current.p.dtype, current.p.device
    if method == "fast":
        best, best_lp, (history_p, history_q, history_lp) = _anneal_fast_steps(
            log_prob_fn, current, current_lp, schedule, generator, planar, record_history)
    else:
        for temperature in schedule.temperatures():
            proposal = _propose(current, temperature, schedule, generator)
            proposal_lp = _evaluate(log_prob_fn, proposal, shape)
            u = random_uniform(shape, generator, dtype, device)
            # -inf - -inf is NaN: such a candidate compares False everywhere and keeps its pose.
            delta = proposal_lp - current_lp
            accept = (proposal_lp > current_lp) | (torch.exp(delta / (schedule.energy_scale * temperature)) > u)
            current = Pose.unchecked(
                torch.where(accept.unsqueeze(-1), proposal.p, current.p),
                torch.where(accept.unsqueeze(-1), proposal.q, current.q),
            )
            current_lp = torch.where(accept, proposal_lp, current_lp)
            improved = current_lp > best_lp
            best = Pose.unchecked(
                torch.where(improved.unsqueeze(-1), current.p, best.p),
                torch.where(improved.unsqueeze(-1), current.q, best.q),
            )
            best_lp = torch.where(improved, current_lp, best_lp)
            if record_history:
                history_p.append(current.p)
                history_q.append(current.q)
                history_lp.append(current_lp)
    result = _best_of(best, best_lp)
    if record_history:
        result.history = Pose.unchecked(torch.stack(history_p), torch.stack(history_q))
        result.history_log_prob = torch.stack(history_lp)
    return result


def polish_candidates(
    result: AnnealResult,
    shift_fn: Callable[[Pose], Pose],
    log_prob_fn: Callable[[Pose], Tensor],
    steps: int,
) -> AnnealResult:
    """Move every annealed candidate up to its local mode: ``steps`` mean-shift moves (``shift_fn``, e.g.
    :meth:`pushtorch.kde.PoseKDE.mean_shift`), each kept only where it raises the log-likelihood.

    The fast path's "better proposals" (docs/method.md): annealing explores with fewer steps and the
    mean-shift fixed point, where a mode is, replaces the last steps' small random moves. The best
    candidate is chosen again; a recorded history gains the polished candidates as its last step.
    """
    if isinstance(steps, bool) or int(steps) != steps or steps < 0:
        raise InvalidParameterError(f"polish steps must be an integer >= 0, got {steps!r}")
    if steps == 0:
        return result
    p, q, lp = result.candidates.p, result.candidates.q, result.log_prob
    for _ in range(int(steps)):
        with torch.no_grad():
            moved = shift_fn(Pose.unchecked(p, q))
            moved_lp = log_prob_fn(moved)
        better = moved_lp > lp  # NaN never is
        p = torch.where(better.unsqueeze(-1), moved.p, p)
        q = torch.where(better.unsqueeze(-1), moved.q, q)
        lp = torch.where(better, moved_lp, lp)
    polished = _best_of(Pose.unchecked(p, q), lp)
    if result.history is not None:  # the polished candidates as one more step, for review
        polished.history = Pose.unchecked(torch.cat([result.history.p, p.unsqueeze(0)]),
                                torch.cat([result.history.q, q.unsqueeze(0)]))
        polished.history_log_prob = torch.cat([result.history_log_prob, lp.unsqueeze(0)])
    return polished


def _best_of(candidates: Pose, log_prob: Tensor) -> AnnealResult:
    """The result whose best is each problem's highest candidate (an all -inf problem: its first)."""
    winner = log_prob.argmax(-1, keepdim=True)  # (*B, 1)
    return AnnealResult(
        best=Pose.unchecked(torch.gather(candidates.p, -2, winner.unsqueeze(-1).expand(*winner.shape, 3)).squeeze(-2),
                  torch.gather(candidates.q, -2, winner.unsqueeze(-1).expand(*winner.shape, 4)).squeeze(-2)),
        best_log_prob=torch.gather(log_prob, -1, winner).squeeze(-1),
        candidates=candidates,
        log_prob=log_prob,
    )
