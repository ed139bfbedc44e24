"""Push plans: the inputs of a batch of pushes (start poses, actions, physical parameters), fixed up front.

Paper, Experimental Setup ("The robot is placed with the desired contact between the robot's bumper and
the object ... Once the physical critical parameters are sampled from the desired distributions, a push
action is generated and a PDR is recorded") and the parameter tables (Samples Per Action).

A plan is a pure function of its configuration and seed: every random quantity of every push (mass,
ground friction, placement jitter) is drawn here, batched, from one ``torch.Generator`` seeded with the
run's seed, in a fixed order (mass, friction, lateral jitter, heading jitter). Push ``i`` therefore gets
the same inputs whichever worker runs it and whenever, which is what makes runs reproducible and
resumable. Pushes are numbered action-major: push ``i`` performs action ``i // samples_per_action``.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.sim.priors import Prior

__all__ = ["Placement", "PushPlan", "plan_training_pushes"]


@dataclass(frozen=True)
class Placement:
    """How training places the robot against the object (the ``placement`` config entry).

    The object stands upright at the origin with yaw ``object_yaw_deg``; the robot approaches along +x
    (heading 0 plus a uniform jitter of ±``yaw_jitter_deg``), its bumper centred on the object's side
    facing it (plus a uniform lateral jitter of ±``lateral_jitter`` m), ``gap`` m short of touching.
    """

    gap: float = 0.002
    lateral_jitter: float = 0.0
    yaw_jitter_deg: float = 0.0
    object_yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("gap", "lateral_jitter", "yaw_jitter_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidParameterError(f"placement.{name} must be a finite number >= 0, got {value!r}")
        if not math.isfinite(self.object_yaw_deg):
            raise InvalidParameterError("placement.object_yaw_deg must be finite")


def _as_f64(x, shape: tuple[int, ...], name: str) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=torch.float64).detach().cpu()
    try:
        t = t.expand(*shape).clone()
    except RuntimeError as exc:
        raise InvalidParameterError(
            f"plan field {name} of shape {tuple(t.shape)} does not fit {shape}"
        ) from exc
    if not torch.isfinite(t).all():
        raise InvalidParameterError(f"plan field {name} has NaN or infinite entries")
    return t


@dataclass
class PushPlan:
    """The inputs of N pushes of one object (float64, CPU; built directly or by a planner).

    Attributes:
        object_name: the object pushed.
        robot_start: base poses ``(N,)`` on the ground, world frame.
        object_initial: object poses ``(N,)``, world frame.
        action: ``(N, 2)`` (ẋ m/s, θ̇ rad/s).
        mass: ``(N,)`` kg; ground_friction: ``(N,)`` effective object-ground coefficient.
        action_index: ``(N,)`` int64 (default 0).
        index: ``(N,)`` int64 push numbers (default 0..N-1).
        seed: the run seed recorded with every push.
        duration: s of every push.
    """

    object_name: str
    robot_start: se3.Pose
    object_initial: se3.Pose
    action: torch.Tensor
    mass: torch.Tensor
    ground_friction: torch.Tensor
    action_index: torch.Tensor | None = None
    index: torch.Tensor | None = None
    seed: int = 0
    duration: float = 4.0
    _fingerprint: str | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = int(torch.as_tensor(self.mass).reshape(-1).shape[0])
        self.mass = _as_f64(self.mass, (n,), "mass")
        self.ground_friction = _as_f64(self.ground_friction, (n,), "ground_friction")
        self.action = _as_f64(self.action, (n, 2), "action")
        self.robot_start = se3.Pose.unchecked(
            _as_f64(self.robot_start.p, (n, 3), "robot_start.p"),
            _as_f64(self.robot_start.q, (n, 4), "robot_start.q"),
        )
        self.object_initial = se3.Pose.unchecked(
            _as_f64(self.object_initial.p, (n, 3), "object_initial.p"),
            _as_f64(self.object_initial.q, (n, 4), "object_initial.q"),
        )
        se3.check_unit_quaternion(self.object_initial.q, name="object_initial.q")
        from pushtorch.robot import base_pose_to_joints

        base_pose_to_joints(self.robot_start)  # raises unless every start pose lies on the ground
        if (self.mass <= 0).any() or (self.ground_friction <= 0).any():
            raise InvalidParameterError("every mass and ground friction of a plan must be positive")
        if not (math.isfinite(self.duration) and self.duration > 0):
            raise InvalidParameterError(f"the push duration must be positive, got {self.duration!r}")
        self.action_index = (
            torch.zeros(n, dtype=torch.int64)
            if self.action_index is None
            else torch.as_tensor(self.action_index, dtype=torch.int64).expand(n).clone()
        )
        self.index = (
            torch.arange(n, dtype=torch.int64)
            if self.index is None
            else torch.as_tensor(self.index, dtype=torch.int64).expand(n).clone()
        )
        self.seed = int(self.seed)

    def __len__(self) -> int:
        return int(self.mass.shape[0])

    def arrays(self, start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
        """Pushes ``start:stop`` as plain numpy arrays (what a worker process receives)."""
        sl = slice(start, stop)
        return {
            "index": self.index[sl].numpy(),
            "action_index": self.action_index[sl].numpy(),
            "action": self.action[sl].numpy(),
            "robot_start_p": self.robot_start.p[sl].numpy(),
            "robot_start_q": self.robot_start.q[sl].numpy(),
            "object_initial_p": self.object_initial.p[sl].numpy(),
            "object_initial_q": self.object_initial.q[sl].numpy(),
            "mass": self.mass[sl].numpy(),
            "ground_friction": self.ground_friction[sl].numpy(),
        }

    def fingerprint(self) -> str:
        """SHA-256 of everything that determines the pushes (guards a resumed run against a changed plan)."""
        if self._fingerprint is None:
            h = hashlib.sha256()
            h.update(f"{self.object_name}|{self.seed}|{self.duration!r}".encode())
            for name, array in sorted(self.arrays().items()):
                h.update(name.encode())
                h.update(np.ascontiguousarray(array).tobytes())
            self._fingerprint = h.hexdigest()
        return self._fingerprint


def plan_training_pushes(
    model,
    actions: torch.Tensor,
    samples_per_action: int,
    mass_prior: Prior,
    friction_prior: Prior,
    seed: int = 0,
    duration: float = 4.0,
    placement: Placement | None = None,
) -> PushPlan:
    """The paper's training pushes: ``samples_per_action`` pushes of each action from a fresh placement.

    Args:
        model: the :class:`pushtorch.objects.ObjectModel` to push.
        actions: ``(A, 2)`` actions (ẋ m/s, θ̇ rad/s), e.g. from :func:`pushtorch.sim.push.make_actions`.
        samples_per_action: pushes per action (the paper's Samples Per Action, 500 for training).
        mass_prior, friction_prior: where each push's mass and ground friction are drawn from.
        seed: the run seed; the plan is a pure function of the arguments and the seed.
        duration: s per push (the paper's 4).
        placement: robot placement and jitter.

    Returns:
        A :class:`PushPlan` of ``A * samples_per_action`` pushes, action-major.

    Raises:
        InvalidParameterError: bad counts or actions, or a jittered bumper that misses the object.
    """
    from pushtorch.sim.push import place_robot_against

    placement = placement or Placement()
    actions = torch.as_tensor(actions, dtype=torch.float64)
    if actions.ndim != 2 or actions.shape[-1] != 2 or actions.shape[0] < 1:
        raise InvalidParameterError(f"actions must have shape (A, 2), got {tuple(actions.shape)}")
    if int(samples_per_action) != samples_per_action or samples_per_action < 1:
        raise InvalidParameterError(
            f"samples_per_action must be a positive integer, got {samples_per_action!r}"
        )
    per_action = int(samples_per_action)
    n = actions.shape[0] * per_action
    generator = torch.Generator().manual_seed(int(seed))
    mass = mass_prior.sample((n,), generator)
    friction = friction_prior.sample((n,), generator)
    lateral = (2 * torch.rand(n, generator=generator, dtype=torch.float64) - 1) * placement.lateral_jitter
    heading = (2 * torch.rand(n, generator=generator, dtype=torch.float64) - 1) * math.radians(
        placement.yaw_jitter_deg
    )
    object_pose = model.resting_pose(0.0, 0.0, math.radians(placement.object_yaw_deg))
    if placement.lateral_jitter == 0 and placement.yaw_jitter_deg == 0:
        start = place_robot_against(model.mesh, object_pose, 0.0, 0.0, placement.gap).to(torch.float64)
        robot_start = start.expand(n)
    else:
        starts = [
            place_robot_against(model.mesh, object_pose, float(h), float(y), placement.gap)
            for h, y in zip(heading.tolist(), lateral.tolist(), strict=True)
        ]
        robot_start = se3.Pose.stack(starts).to(torch.float64)
    action_index = torch.arange(actions.shape[0]).repeat_interleave(per_action)
    return PushPlan(
        object_name=model.name,
        robot_start=robot_start,
        object_initial=object_pose.to(torch.float64).expand(n),
        action=actions[action_index],
        mass=mass,
        ground_friction=friction,
        action_index=action_index,
        seed=int(seed),
        duration=float(duration),
    )
