"""Bodies from observed clouds and their batched rollouts: the physics every cloud-based predictor shares
(beyond the paper, whose predictor is learned alone; its §Conclusions and future work ask for transfer to
shapes unlike the training ones, where a simulator on the observed shape knows what local contact cannot).

* :func:`cloud_body`: the rigid body a single-shot cloud builds (the visible surface's convex hull swept down
  to the ground) and its pose.
* :func:`rollout_ensemble`: one push of that body rolled out for an ensemble of ``(μ, m)``, in one call to the
  configured engine. ``physics_from_cloud``, ``physics_ensemble``
  (:mod:`pushtorch.evaluation.baselines`) and the residual model (:mod:`pushtorch.models.residual`) roll out
  through it, so they are compared like for like.
* :class:`RolloutPool`: worker processes that take a body per task. Inside ``with RolloutPool(workers):``
  every :func:`rollout_ensemble` of this process splits its ensemble over the workers (each rollout is
  independent of the others: the same outcomes, bit for bit, as one after another). Neither engine can batch
  the robot's drive itself: the Pioneer's wheel loops (:func:`~pushtorch.sim.drive.wheel_forces`, a PI loop
  with conditional integration and a friction circle shared with the sideways holding force) run in Python
  every step, which MuJoCo's built-in actuators cannot express, so ``mujoco.rollout`` cannot run it.

It sits in ``sim``, below ``models``, so a model can roll out; nothing here learns.
"""

from __future__ import annotations

import contextvars
import dataclasses
import multiprocessing as mp
import sys

import numpy as np
import torch
import trimesh

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.objects import ObjectModel, Symmetry
from pushtorch.sim.settings import SimSettings

__all__ = ["RolloutPool", "active_rollout_pool", "cloud_body", "rollout_ensemble"]

#: The pool that :func:`rollout_ensemble` splits ensembles over in this context (None: one after another here).
_ACTIVE: contextvars.ContextVar[RolloutPool | None] = contextvars.ContextVar("pushtorch_rollout_pool", default=None)


def cloud_body(points: torch.Tensor, initial_estimate: se3.Pose,
               name: str = "cloud_hull") -> tuple[ObjectModel, se3.Pose]:
    """A rigid body reconstructed from an observed cloud, and its pose: the convex hull of the points and of
    their projections onto the ground (z = 0), i.e. the visible surface swept down to the floor.

    The body frame sits at the hull's centre of mass with the estimate's heading (the frame only names the
    body: the displacement a push gives does not depend on it). Hidden parts the camera could not see and
    concavities are filled or missing exactly as the sweep makes them.

    Raises:
        ModelError: the cloud spans no volume (fewer than 4 points off one plane), or has non-finite points.
    """
    world = points.detach().double().cpu().numpy().reshape(-1, 3)
    if not np.isfinite(world).all():
        raise ModelError("the observed cloud has non-finite points: no body to simulate")
    ground = world.copy()
    ground[:, 2] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by a flat hull's zero volume
        try:
            hull = trimesh.convex.convex_hull(np.concatenate([world, ground]))
        except Exception as exc:  # scipy's QhullError on flat or degenerate point sets
            raise ModelError(f"the observed cloud ({len(world)} points) spans no volume to simulate") from exc
        volume = hull.volume
    if not volume > 0:
        raise ModelError(f"the observed cloud ({len(world)} points) spans no volume to simulate")
    centre = np.asarray(hull.center_mass)
    yaw = float(se3.yaw_of(initial_estimate.q.reshape(4)))
    pose = se3.from_xy_yaw(float(centre[0]), float(centre[1]), yaw, z=float(centre[2])).to(torch.float64)
    to_body = np.linalg.inv(se3.to_matrix(pose).numpy())
    body = hull.copy()
    body.apply_transform(to_body)
    identity = Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    return ObjectModel(name, body, identity), pose


def rollout_ensemble(body: ObjectModel, start: se3.Pose, robot_start: se3.Pose, action: torch.Tensor,
                     friction: torch.Tensor, mass: torch.Tensor, settings=None):
    """One push of ``body`` from ``start`` rolled out for every ``(friction[i], mass[i])`` in one call to the
    engine of ``settings`` (a :class:`~pushtorch.sim.settings.SimSettings`; default pybullet's): in this process,
    one after another in one world, or split over the workers of the active :class:`RolloutPool`.

    Args:
        start, robot_start: ``()`` the body's and the robot's start poses (world).
        action: ``(2,)`` (ẋ m/s, θ̇ rad/s); friction, mass: ``(N,)``.

    Returns:
        :class:`~pushtorch.sim.records.PushRecords` of the ``N`` rollouts (float64), in order.

    Raises:
        InvalidParameterError: an empty or misshaped ensemble.
    """
    from pushtorch.sim.runner import simulate_pushes

    friction = torch.as_tensor(friction, dtype=torch.float64).reshape(-1)
    mass = torch.as_tensor(mass, dtype=torch.float64).reshape(-1)
    n = int(friction.shape[0])
    if n < 1 or mass.shape[0] != n:
        raise InvalidParameterError(f"an ensemble needs as many masses as frictions, at least one: got "
                                    f"{n} and {int(mass.shape[0])}")
    offset = _local_offset(start, robot_start, settings)
    if offset is not None:  # the same push about the origin, moved back
        start = se3.Pose.unchecked(start.p.double() - offset, start.q)
        robot_start = se3.Pose.unchecked(robot_start.p.double() - offset, robot_start.q)
        return _moved(rollout_ensemble(body, start, robot_start, action, friction, mass, settings), offset)
    pool = _ACTIVE.get()
    if pool is not None and n > 1:
        return pool.rollout(body, start, robot_start, action, friction, mass, settings)
    robot = se3.Pose.unchecked(robot_start.p.double().reshape(1, 3).expand(n, 3),
                               robot_start.q.double().reshape(1, 4).expand(n, 4))
    initial = se3.Pose.unchecked(start.p.double().reshape(1, 3).expand(n, 3),
                                 start.q.double().reshape(1, 4).expand(n, 4))
    act = torch.as_tensor(action, dtype=torch.float64).reshape(1, 2).expand(n, 2)
    return simulate_pushes(body, robot, initial, act, mass, friction, settings=settings)


def _local_offset(start: se3.Pose, robot_start: se3.Pose, settings) -> torch.Tensor | None:
    """``(3,)`` float64 the body's start on the ground plane where it or the robot starts more than a quarter of the
    simulated ground's width from its centre (a map's frame): the push is then rolled out about the origin (the
    ground is flat and alike everywhere) and moved back; None nearer, where it is rolled out where it is."""
    half = (settings or SimSettings()).ground_half_extent
    body, robot = start.p.detach().double().reshape(3), robot_start.p.detach().double().reshape(3)
    if max(float(body[:2].abs().max()), float(robot[:2].abs().max())) <= half / 2:
        return None
    return torch.cat([body[:2], body.new_zeros(1)])


def _moved(records, offset: torch.Tensor):
    """``records`` with every pose translated by ``offset (3,)``."""
    moved = {f.name: se3.Pose.unchecked(value.p + offset.to(value.p), value.q)
             for f in dataclasses.fields(records) if isinstance(value := getattr(records, f.name), se3.Pose)}
    return dataclasses.replace(records, **moved)


def active_rollout_pool() -> RolloutPool | None:
    """The :class:`RolloutPool` this context's ensembles are split over, or None."""
    return _ACTIVE.get()


class RolloutPool:
    """Worker processes that roll ensembles out in parallel, a body per task (module docstring).

    Use as a context manager: inside it, every :func:`rollout_ensemble` of this thread splits its ensemble into
    one contiguous chunk per worker (no more chunks than rollouts) and gathers them in order. Outside it, or for
    an ensemble of one, rollouts run here. The pool is worth its transfers where rollouts are many and cores
    free (``tools/bench_residual.py`` prints a rollout's and a world's cost on this host, and the pool's gain).

    Args:
        workers: processes (0: this job's share of the cores, :func:`pushtorch.parallel.core_share`).
        start_method: as :class:`~pushtorch.sim.runner.PushPool`'s (default ``fork`` on Linux).

    Raises:
        InvalidParameterError: fewer than one worker, or a start method this platform lacks.
    """

    def __init__(self, workers: int = 0, start_method: str | None = None) -> None:
        from pushtorch.parallel import core_share

        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise InvalidParameterError(f"workers must be a whole number >= 1 (or 0 for this job's cores), got "
                                        f"{workers!r}")
        self.workers = int(workers) or core_share()
        methods = mp.get_all_start_methods()
        method = start_method or ("fork" if "fork" in methods and sys.platform.startswith("linux") else "spawn")
        if method not in methods:
            raise InvalidParameterError(f"start method {method!r} is not available here ({', '.join(methods)})")
        self._pool = mp.get_context(method).Pool(self.workers, initializer=_init_rollout_worker)
        self._tokens: list[contextvars.Token] = []

    def rollout(self, body: ObjectModel, start: se3.Pose, robot_start: se3.Pose, action: torch.Tensor,
                friction: torch.Tensor, mass: torch.Tensor, settings=None):
        """:func:`rollout_ensemble` split over the workers: the same records, in the same order."""
        from pushtorch.sim.records import PushRecords

        friction = torch.as_tensor(friction, dtype=torch.float64).reshape(-1)
        mass = torch.as_tensor(mass, dtype=torch.float64).reshape(-1)
        chunks = [c for c in np.array_split(np.arange(len(friction)), min(self.workers, len(friction))) if len(c)]
        mesh = (np.asarray(body.mesh.vertices), np.asarray(body.mesh.faces), body.name)
        poses = tuple(t.detach().double().cpu().numpy() for t in (start.p, start.q, robot_start.p, robot_start.q,
                                                                   torch.as_tensor(action)))
        tasks = [(mesh, poses, friction[c].numpy(), mass[c].numpy(), settings) for c in chunks]
        return PushRecords.cat([_from_plain(r) for r in self._pool.map(_rollout_chunk, tasks)])

    def close(self) -> None:
        self._pool.close()
        self._pool.join()

    def __enter__(self) -> RolloutPool:
        self._tokens.append(_ACTIVE.set(self))
        return self

    def __exit__(self, *exc) -> None:
        _ACTIVE.reset(self._tokens.pop())
        if not self._tokens:
            self.close()


def _init_rollout_worker() -> None:
    torch.set_num_threads(1)  # a rollout is the engine's; torch only keeps its records
    _ACTIVE.set(None)  # a worker forked inside another pool's context rolls out itself


def _to_plain(records) -> dict:
    """Records as numpy arrays (what crosses between processes without torch's shared-memory handles)."""
    out = {}
    for f in dataclasses.fields(records):
        value = getattr(records, f.name)
        if isinstance(value, se3.Pose):
            out[f.name] = ("pose", value.p.numpy(), value.q.numpy())
        elif isinstance(value, torch.Tensor):
            out[f.name] = ("tensor", value.numpy())
        else:
            out[f.name] = ("value", value)
    return out


def _from_plain(plain: dict):
    from pushtorch.sim.records import PushRecords

    def back(kind, *values):
        if kind == "pose":
            return se3.Pose.unchecked(torch.from_numpy(values[0]), torch.from_numpy(values[1]))
        return torch.from_numpy(values[0]) if kind == "tensor" else values[0]

    return PushRecords(**{name: back(*value) for name, value in plain.items()})


def _rollout_chunk(task):
    """One worker's share of an ensemble: the body built again from its mesh, its rollouts one after another."""
    (vertices, faces, name), (sp, sq, rp, rq, action), friction, mass, settings = task
    identity = Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    body = ObjectModel(name, trimesh.Trimesh(vertices, faces, process=False), identity)
    start = se3.Pose.unchecked(torch.from_numpy(sp), torch.from_numpy(sq))
    robot = se3.Pose.unchecked(torch.from_numpy(rp), torch.from_numpy(rq))
    return _to_plain(rollout_ensemble(body, start, robot, torch.from_numpy(action), torch.from_numpy(friction),
                                      torch.from_numpy(mass), settings))
