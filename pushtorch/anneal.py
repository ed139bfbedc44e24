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
proposal and Metropolis test as one fused (compiled when possible) call each
(:func:`pushtorch.kde.annealing.anneal_chains`), and lets planar and free problems share one batch (a
per-problem ``planar`` mask), which the fast prediction path uses to anneal the robot's and the object's
query densities together. A density that anneals itself (:class:`pushtorch.kde.FusedAnnealing`: a
:class:`~pushtorch.kde.PoseKDE`, a :class:`~pushtorch.kde.SharedKernelProduct`) is handed the drawn
steps and runs them fused with its own evaluation; this module never looks inside a density. It owns the
schedule, the random stream (:func:`_drawn_steps`: which draws, in which order, whoever runs the steps),
the dense reference loop and the checks of a caller's values; the steps' pure tensor functions are kde's
(:mod:`pushtorch.kde.annealing` says why).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import Evaluation, PoseKDE
from pushtorch.kde.annealing import AnnealInputs, DrawnSteps, anneal_chains
from pushtorch.se3 import (
    Pose,
    check_unit_quaternion,
    perturb,
    random_normal,
    random_uniform,
    vmf_offsets,
    yaw_quaternion,
)
from pushtorch.streams import is_keyed

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

    def take(self, index) -> AnnealResult:
        """The result of the problems at ``index`` of the first problem dim (an int: one problem, its dim dropped;
        a tensor of indices: a subset or reordering), the history's step dim kept first."""
        def pose(p: Pose, lead: bool = False) -> Pose:
            return Pose.unchecked(p.p[:, index], p.q[:, index]) if lead else Pose.unchecked(p.p[index], p.q[index])

        return AnnealResult(
            best=pose(self.best), best_log_prob=self.best_log_prob[index], candidates=pose(self.candidates),
            log_prob=self.log_prob[index], history=None if self.history is None else pose(self.history, True),
            history_log_prob=None if self.history_log_prob is None else self.history_log_prob[:, index],
        )


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
    if is_keyed(generator) and generator.dim is not None:  # the problems' dim moves behind the steps'
        generator = generator.along(generator.dim + 1)
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


def _drawn_steps(schedule: AnnealSchedule, shape: torch.Size, generator, planar: Tensor | None, dtype, device
                 ) -> Iterator[DrawnSteps]:
    """The fast path's steps in chunks of :data:`_DRAW_STEPS`: yields each chunk's temperatures and its
    pre-drawn proposals and acceptance uniforms (:func:`_draw_fast_proposals`), drawn when the chunk is
    reached, in the one order every fast loop (the generic one, a density's fused one) consumes them, so they
    share the seed's random stream."""
    temperatures = schedule.temperatures()
    for start in range(0, len(temperatures), _DRAW_STEPS):
        chunk = temperatures[start : start + _DRAW_STEPS]
        yield DrawnSteps(chunk, *_draw_fast_proposals(chunk, shape, schedule, generator, planar, dtype, device))


_Z_AXIS = torch.tensor([False, False, True])


def _evaluate(log_prob_fn: Callable[[Pose], Tensor], pose: Pose, shape: torch.Size) -> Tensor:
    with torch.no_grad():
        return _checked(log_prob_fn(pose), shape)


def _checked(value: Tensor, shape: torch.Size) -> Tensor:
    """``log_prob_fn``'s values, refused if misshaped, NaN or +inf."""
    if not isinstance(value, Tensor) or value.shape != shape:
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ModelError(f"log_prob_fn must return a tensor of shape {tuple(shape)} (*B, C), got {got}")
    if torch.isnan(value).any():
        raise ModelError("log_prob_fn returned NaN log-likelihoods (use -inf for zero density)")
    if (value == math.inf).any():
        raise ModelError("log_prob_fn returned +inf log-likelihoods")
    return value


def _raise_on_bad_values(saw_nan: Tensor, best_lp: Tensor) -> None:
    """The fast path's one check of the steps' values, after the steps (one sync, not one per step)."""
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
    method: Evaluation | str = Evaluation.DENSE,
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
        method: an :class:`~pushtorch.kde.Evaluation` or its string: ``"dense"``, the reference proposals
            (one step's draws at a time, :func:`pushtorch.se3.perturb`), or ``"fast"``: the same proposal
            distributions, several steps drawn at once and applied in fused calls. Both draw rotations
            with :func:`pushtorch.se3.vmf_offsets`; the seed's random stream differs between the two.
            With ``"fast"``, a ``log_prob_fn`` that anneals itself (:class:`~pushtorch.kde.FusedAnnealing`)
            is handed the drawn steps: a :class:`PoseKDE` is then evaluated by its own fast path
            (``log_prob(..., method="fast")``: the same values up to float rounding), a pruned one or a
            :class:`~pushtorch.kde.SharedKernelProduct` in steps fused with their evaluation; the same
            draws, so the same random stream, either way.

    Returns:
        :class:`AnnealResult`. A candidate at ``-inf`` accepts any finite proposal; if its proposal is
        also ``-inf`` it keeps its pose.

    Raises:
        InvalidPoseError: ``init`` without a candidate dim or with non-unit quaternions.
        ModelError: ``log_prob_fn`` returns the wrong shape, NaN or +inf.
    """
    schedule = AnnealSchedule() if schedule is None else schedule
    method = Evaluation.of(method)
    shape = init.batch_shape
    if planar is not None:
        if method != Evaluation.FAST:
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
    dtype, device = current.p.dtype, current.p.device
    if method == Evaluation.FAST:
        inputs = AnnealInputs(current, _drawn_steps(schedule, shape, generator, planar, dtype, device),
                              schedule.energy_scale, record_history)
        anneal_itself = getattr(log_prob_fn, "fused_anneal", None)
        outcome = anneal_itself(inputs) if callable(anneal_itself) else None
        if outcome is None:  # nothing drawn yet: the generic loop over log_prob_fn
            outcome = anneal_chains(log_prob_fn, inputs, _evaluate(log_prob_fn, current, shape))
        else:
            _checked(outcome.start_log_prob, shape)
        _raise_on_bad_values(outcome.saw_nan, outcome.best_log_prob)
        best, best_lp = outcome.best, outcome.best_log_prob
        if record_history:
            history_p, history_q, history_lp = outcome.history
    else:
        current_lp = _evaluate(log_prob_fn, current, shape)
        best, best_lp = current, current_lp
        history_p, history_q, history_lp = [current.p], [current.q], [current_lp]
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
