"""Densities that anneal themselves: the fast path's annealing steps as the densities run them.

Paper, Query Density and Motion Model: "perform simulated annealing based optimisation upon the candidates
aiming to maximise the likelihood approximated by KDE". :func:`pushtorch.anneal.anneal` owns the
annealing — the schedule, the random stream (which proposals and acceptance uniforms are drawn, in which
order), the dense reference loop, the checks of a caller's values and the result. On its fast path it hands
the density the steps it drew (:class:`AnnealInputs`); a density that can run them fused with its own
evaluation offers :class:`FusedAnnealing` and is called duck-typed (``getattr(density, "fused_anneal",
None)``), so the annealer never looks inside a density:

* :class:`~pushtorch.kde.SharedKernelProduct` (the motion model's product of experts) runs each step —
  proposal, the product's log-likelihood and the Metropolis test — as one fused call per chunk of problems;
* :class:`~pushtorch.kde.PoseKDE` (a query density) runs, on pruned leaf blocks and compiled, two fused
  calls per step around its list of (query, block) pairs, and otherwise the generic loop
  (:func:`anneal_chains`) on its own fast evaluation.

What a step computes from the drawn offsets is defined here, once, as pure tensor functions —
:func:`propose_from_offsets` and :func:`metropolis_update` — which the annealer imports for its generic
loop and the densities call inside their fused steps. The alternative, the annealer passing them in as
callables, was not taken: the fused steps call them *inside* one torch.compile'd function together with
the density's kernels, and a compiled function is shared per name by every caller
(:func:`~pushtorch.kde.fused_function`), so it would be traced against whichever callables came first and
guard on their identity; pure functions of tensors belong in the layer below the annealer and are the same
in every trace. The annealer still passes what is its own as data: the pre-drawn steps (an iterator, drawn
lazily: a density that declines has drawn nothing, and the stream's order is the annealer's alone), the
energy scale and whether a history is recorded.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch.kde.fused import fused_function
from pushtorch.se3 import Pose

Tensor = torch.Tensor

__all__ = [
    "AnnealInputs",
    "AnnealOutcome",
    "DrawnSteps",
    "FusedAnnealing",
    "anneal_chains",
    "chain_state",
    "metropolis_update",
    "propose_from_offsets",
]


class DrawnSteps(NamedTuple):
    """Several consecutive steps' random parts, drawn at once by the annealer.

    Attributes:
        temperatures: each step's temperature ``S`` floats.
        step_p: translation offsets ``(S, *B, C, 3)``.
        left, right: rotation offsets ``(S, *B, C, 4)``; a proposal is ``normalise(left ⊗ q ⊗ right)``.
        accept_u: the Metropolis test's uniforms ``(S, *B, C)``.
    """

    temperatures: list[float]
    step_p: Tensor
    left: Tensor
    right: Tensor
    accept_u: Tensor


@dataclass(frozen=True)
class AnnealInputs:
    """What the annealer hands a density that anneals itself.

    Attributes:
        start: the chains' start poses ``(*B, C)``, unit quaternions.
        steps: the steps in order, drawn lazily chunk by chunk (:class:`DrawnSteps`). A density that
            declines (returns None) must not have advanced it: the annealer's own loop then consumes it.
        energy_scale: E of the acceptance test ``exp(Δ log L / (E T)) > U(0, 1)``.
        record_history: the chains' poses and log-likelihoods are wanted after every step.
    """

    start: Pose
    steps: Iterator[DrawnSteps]
    energy_scale: float
    record_history: bool = False

    def inverse_energy(self, temperature: float) -> Tensor:
        """``1 / (E T)`` as a tensor of the start poses' dtype and device (one per step)."""
        return torch.tensor(1.0 / (self.energy_scale * temperature), dtype=self.start.p.dtype,
                            device=self.start.p.device)


class AnnealOutcome(NamedTuple):
    """What annealing the chains gave.

    Attributes:
        start_log_prob: the start poses' log-likelihoods ``(*B, C)`` (the annealer checks them).
        best: the best pose each chain visited ``(*B, C)``; best_log_prob: its log-likelihood ``(*B, C)``.
        saw_nan: bool ``()``, whether a proposal's log-likelihood was NaN (never accepted).
        history: with ``record_history``, the chains' poses and log-likelihoods before the first step and
            after every step, as lists ``([p], [q], [log L])``; else None.
    """

    start_log_prob: Tensor
    best: Pose
    best_log_prob: Tensor
    saw_nan: Tensor
    history: tuple[list[Tensor], list[Tensor], list[Tensor]] | None = None


class FusedAnnealing(Protocol):
    """A density that runs the annealer's fast steps itself, fused with its own evaluation."""

    def fused_anneal(self, inputs: AnnealInputs) -> AnnealOutcome | None:
        """Anneal ``inputs.start`` through ``inputs.steps``, the same proposals and acceptance tests as
        :func:`anneal_chains` over the density's log-likelihood, or None — before drawing a step — where it
        cannot (e.g. a history is wanted, or the poses are not its own batch of problems)."""
        ...


def propose_from_offsets(p: Tensor, q: Tensor, step_p: Tensor, left: Tensor, right: Tensor,
                         component_dim: int = -1) -> tuple[Tensor, Tensor]:
    """One step's proposals from drawn offsets (fused): ``p + Δp``, ``normalise(left ⊗ q ⊗ right)``, with
    the pose components along ``component_dim``."""
    rows = [t.movedim(component_dim, -1) for t in (left, q, right)]
    turned = pkt.quaternion_raw_multiply(pkt.quaternion_raw_multiply(rows[0], rows[1]), rows[2])
    turned = turned.movedim(-1, component_dim)
    return p + step_p, turned / turned.norm(dim=component_dim, keepdim=True)


def metropolis_update(
    p: Tensor, q: Tensor, lp: Tensor, best_p: Tensor, best_q: Tensor, best_lp: Tensor,
    prop_p: Tensor, prop_q: Tensor, prop_lp: Tensor, u: Tensor, inverse_energy: Tensor, saw_nan: Tensor,
    component_dim: int = -1,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The Metropolis test and the best-so-far update of one step (fused): a proposal is accepted if better
    or if ``exp(Δ log L · inverse_energy) > u``. ``saw_nan`` accumulates whether any proposal's
    log-likelihood was NaN (never accepted). Poses hold their components along ``component_dim`` (-1, or
    -2 for rows ``(…, 3|4, C)``)."""
    accept = (prop_lp > lp) | (torch.exp((prop_lp - lp) * inverse_energy) > u)
    p = torch.where(accept.unsqueeze(component_dim), prop_p, p)
    q = torch.where(accept.unsqueeze(component_dim), prop_q, q)
    lp = torch.where(accept, prop_lp, lp)
    improved = lp > best_lp
    best_p = torch.where(improved.unsqueeze(component_dim), p, best_p)
    best_q = torch.where(improved.unsqueeze(component_dim), q, best_q)
    best_lp = torch.where(improved, lp, best_lp)
    return p, q, lp, best_p, best_q, best_lp, saw_nan | torch.isnan(prop_lp).any()


def chain_state(p: Tensor, q: Tensor, lp: Tensor) -> tuple[Tensor, ...]:
    """The fused steps' state at the start: current and best poses and log-likelihoods, and the NaN flag.
    Distinct tensors: aliased inputs would make torch.compile guard on the aliasing and recompile."""
    return (p.clone(), q.clone(), lp.clone(), p.clone(), q.clone(), lp.clone(),
            torch.zeros((), dtype=torch.bool, device=p.device))


def anneal_chains(log_prob: Callable[[Pose], Tensor], inputs: AnnealInputs, start_log_prob: Tensor
                  ) -> AnnealOutcome:
    """The generic fast loop: each step's proposal and Metropolis test one fused (compiled when possible)
    call each, ``log_prob`` (under no_grad) between them. Values are not checked here: a NaN is never
    accepted and sets ``saw_nan``, for the caller to check once at the end."""
    device = inputs.start.p.device
    propose = fused_function("anneal_proposal", propose_from_offsets, device)
    accept = fused_function("anneal_acceptance", metropolis_update, device)
    p, q, lp = inputs.start.p, inputs.start.q, start_log_prob
    # distinct tensors: aliased inputs would make torch.compile guard on the aliasing and recompile
    best_p, best_q, best_lp = p.clone(), q.clone(), lp.clone()
    history: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([p], [q], [lp])
    saw_nan = torch.zeros((), dtype=torch.bool, device=device)
    for chunk, step_p, left, right, accept_u in inputs.steps:
        for k, temperature in enumerate(chunk):
            prop_p, prop_q = propose(p, q, step_p[k], left[k], right[k])
            with torch.no_grad():
                prop_lp = log_prob(Pose.unchecked(prop_p, prop_q))
            p, q, lp, best_p, best_q, best_lp, saw_nan = accept(
                p, q, lp, best_p, best_q, best_lp, prop_p, prop_q, prop_lp, accept_u[k],
                inputs.inverse_energy(temperature), saw_nan)
            if inputs.record_history:
                history[0].append(p)
                history[1].append(q)
                history[2].append(lp)
    return AnnealOutcome(start_log_prob, Pose.unchecked(best_p, best_q), best_lp, saw_nan,
                         history if inputs.record_history else None)
