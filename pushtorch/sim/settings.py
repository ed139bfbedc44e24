"""What a simulated world is made of before any engine builds it: the simulator's settings and the pushed object.

Paper, Experimental Setup: the authors simulated a Pioneer 3-DX with a bumper pushing objects in
Gazebo/ODE; pybullet (or MuJoCo) replaces that engine here. :class:`SimSettings` holds the physics and
controller settings of the ``sim`` config group and the engine of ``world.engine`` / ``physics.engine``
(:func:`settings_from_config`); :class:`ObjectSpec` holds what a worker needs to build an object in either
engine (its convex pieces and its inertia per kg, :func:`object_spec`). :data:`WORLD_VERSION` names the
simulated world in every run manifest.

Numpy only: specs and settings are sent to worker processes. The worlds that use them are
:mod:`pushtorch.sim.pybullet_world` and :mod:`pushtorch.sim.mujoco_world`, built by
:func:`pushtorch.sim.engines.make_world`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pushtorch.errors import InvalidParameterError
from pushtorch.sim.drive import DRIVES, DriveSettings

__all__ = [
    "ENGINES",
    "ObjectSpec",
    "SimSettings",
    "WORLD_VERSION",
    "object_spec",
    "settings_from_config",
]

#: Version of the simulated world, written into every run manifest: records of another version are refused
#: (pushtorch.sim.runner), never mixed. 2: a fresh object collision shape per push (1 let a convex hull's
#: state carry over between the pushes of one worker). 3: mirror-symmetric pushes (a compliant floor, hulls
#: on support spheres, no early solver exit, every push simulated in the robot's start frame).
WORLD_VERSION = 3

#: The engines a world runs in (``world.engine``; pushtorch.sim.mujoco_world for MuJoCo). Part of the world's
#: identity: pushes, models and caches of one engine are never mixed with another's.
ENGINES = ("pybullet", "mujoco")


@dataclass(frozen=True)
class SimSettings:
    """Physics and controller settings of the push simulator (the ``sim`` config group).

    Attributes:
        engine: ``pybullet`` (default) or ``mujoco``, the engine the world runs in
            (:func:`pushtorch.sim.engines.make_world`).
        time_step: physics step in s. 1/240 s keeps 0.1 m/s pushes quasi-static and stable.
        solver_iterations: constraint-solver iterations per step.
        control_every: physics steps between two updates of the robot's velocity targets.
        record_rate: Hz of the recorded object and robot trajectories (t = 0 included).
        settle_time: s the world keeps running after the push with the robot commanded to stop; the final
            object pose is read after it, at rest.
        bumper_friction: effective bumper-object friction coefficient.
        object_friction: the object's own pybullet friction coefficient (see :mod:`pushtorch.sim.pybullet_world`).
        max_force: N, bound of each planar drive axis of the robot (wheel traction of a 9 kg base, ~0.7 g).
        max_torque: N m, bound of the yaw drive.
        tip_angle_deg: an object whose up axis tilts more than this during the push has "tipped".
        lift_tolerance: m; an object whose centre rises or sinks more than this "left the ground".
        ground_half_extent: m, half side of the square ground box.
        robot: ``p3dx`` (default: the Pioneer's wheels, traction and motors, :mod:`pushtorch.sim.drive`) or
            ``ideal`` (the planar joints' velocity motors bounded by ``max_force`` and ``max_torque``, the
            robot before issue 16).
        drive: the ``p3dx`` drive's parameters (a :class:`~pushtorch.sim.drive.DriveSettings` or a mapping).
    """

    time_step: float = 1.0 / 240.0
    engine: str = "pybullet"
    solver_iterations: int = 50
    control_every: int = 4
    record_rate: float = 10.0
    settle_time: float = 0.25
    bumper_friction: float = 0.5
    object_friction: float = 1.0
    max_force: float = 60.0
    max_torque: float = 10.0
    tip_angle_deg: float = 10.0
    lift_tolerance: float = 0.01
    ground_half_extent: float = 50.0
    robot: str = "p3dx"
    drive: DriveSettings = field(default_factory=DriveSettings)

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise InvalidParameterError(f"world.engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")
        if self.robot not in DRIVES:
            raise InvalidParameterError(f"sim.robot must be one of {', '.join(DRIVES)}, got {self.robot!r}")
        if not isinstance(self.drive, DriveSettings):
            try:
                object.__setattr__(self, "drive", DriveSettings(**dict(self.drive)))
            except TypeError as exc:
                raise InvalidParameterError(f"sim.drive: {exc}") from exc
        positive = {
            "time_step": self.time_step,
            "record_rate": self.record_rate,
            "object_friction": self.object_friction,
            "max_force": self.max_force,
            "max_torque": self.max_torque,
            "tip_angle_deg": self.tip_angle_deg,
            "lift_tolerance": self.lift_tolerance,
            "ground_half_extent": self.ground_half_extent,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise InvalidParameterError(f"sim.{name} must be a positive finite number, got {value!r}")
        if not (np.isfinite(self.bumper_friction) and self.bumper_friction >= 0):
            raise InvalidParameterError(f"sim.bumper_friction must be >= 0, got {self.bumper_friction!r}")
        if not (np.isfinite(self.settle_time) and self.settle_time >= 0):
            raise InvalidParameterError(f"sim.settle_time must be >= 0, got {self.settle_time!r}")
        if int(self.solver_iterations) < 1 or int(self.control_every) < 1:
            raise InvalidParameterError("sim.solver_iterations and sim.control_every must be >= 1")
        if self.record_rate * self.time_step > 1.0:
            raise InvalidParameterError("sim.record_rate must not exceed the physics rate 1/time_step")


@dataclass(frozen=True)
class ObjectSpec:
    """What a worker needs to build an object in pybullet: plain arrays, cheap to send to a process.

    Attributes:
        name: object name (catalogue name or mesh file stem).
        parts: convex pieces as ``(V_i, 3)`` vertex arrays in the object frame (origin at the centre of
            mass, metres).
        part_faces: ``(F_i, 3)`` triangle vertex indices of each piece.
        rest_height: height of the origin above the ground when upright.
        inertia_per_kg: ``(3,)`` principal moments of inertia of a 1 kg object of this shape (kg m²/kg).
        principal_rotation: ``(4,)`` wxyz rotation of the principal inertia frame in the object frame.
    """

    name: str
    parts: tuple[np.ndarray, ...]
    part_faces: tuple[np.ndarray, ...]
    rest_height: float
    inertia_per_kg: np.ndarray
    principal_rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))


def object_spec(model) -> ObjectSpec:
    """The :class:`ObjectSpec` of an :class:`pushtorch.objects.ObjectModel` (uniform density).

    Raises:
        InvalidParameterError: the model has no collision part or a degenerate mass distribution.
    """
    mesh = model.mesh
    if not model.collision_parts:
        raise InvalidParameterError(f"object {model.name!r} has no collision parts")
    volume = float(mesh.volume)
    if not (np.isfinite(volume) and volume > 0):
        raise InvalidParameterError(f"object {model.name!r} encloses no volume")
    # trimesh's moment_inertia is about the centre of mass at density 1; divide by the volume for 1 kg.
    tensor = np.asarray(mesh.moment_inertia, dtype=np.float64) / volume
    off_diagonal = np.abs(tensor - np.diag(np.diag(tensor))).max()
    if off_diagonal <= 1e-9 * np.abs(tensor).max():
        moments, rotation = np.diag(tensor).copy(), np.array([1.0, 0.0, 0.0, 0.0])
    else:
        moments, axes = np.linalg.eigh(tensor)
        if np.linalg.det(axes) < 0:
            axes[:, 2] = -axes[:, 2]
        rotation = _matrix_to_wxyz(axes)
    if (moments <= 0).any():
        raise InvalidParameterError(f"object {model.name!r} has a non-positive principal moment of inertia")
    parts = tuple(np.array(p.vertices, dtype=np.float64) for p in model.collision_parts)
    faces = tuple(np.array(p.faces, dtype=np.int64) for p in model.collision_parts)
    return ObjectSpec(model.name, parts, faces, float(model.rest_height), moments, rotation)


def _matrix_to_wxyz(m: np.ndarray) -> np.ndarray:
    """A proper rotation matrix (3, 3) → unit wxyz quaternion with w >= 0 (Shepperd's method)."""
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.empty(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def settings_from_config(config: Mapping, which: str = "world") -> SimSettings:
    """The :class:`SimSettings` of a composed config: its ``sim`` group in the engine of ``world.engine``
    (``which="world"``: training pushes and ground truth) or ``physics.engine`` (``which="physics"``: the
    physics peers); pybullet where the config names none.

    Raises:
        InvalidParameterError: an unknown engine or simulator setting.
    """
    engine = (config.get(which) or {}).get("engine", "pybullet")
    try:
        return SimSettings(**{**(config.get("sim") or {}), "engine": engine})
    except TypeError as exc:
        raise InvalidParameterError(f"sim: {exc}") from exc

