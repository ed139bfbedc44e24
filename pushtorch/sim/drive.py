"""How the simulated robot moves: a Pioneer 3-DX differential drive with traction and motor limits (issue 16).

Paper, Experimental Setup: a Pioneer 3-DX with a bumper pushes the objects, under the actions "0.1 m/s
forward while turning at −10, 0 or +10 °/s for 4 s". The actions are *commands*: a real robot tracks them
with its wheels, and a load it cannot carry slows it down. The paper finds mass to matter more than friction
("a high mass object … moves little"), which a stiff pusher cannot reproduce: quasi-static pushing does not
depend on mass.

``sim.robot`` chooses the drive (:class:`pushtorch.sim.pybullet_world.PushWorld` applies it every physics step):

* ``p3dx``: the planar base of :mod:`pushtorch.robot` driven by the forces of two wheels. Each wheel's motor
  runs a PI loop on the wheel's ground speed (the robot's firmware servoes wheel speed), bounded by the motor
  torque at the wheel (``wheel_torque / wheel_radius``) and by traction: a wheel pushes the ground with at
  most ``wheel_friction`` times its share of the robot's weight; forward and sideways forces share that
  friction circle, and the sideways force holds the base against sliding (a wheel does not slip sideways
  until the circle is used up). The body wrench is ``F = F_l + F_r`` forward, ``τ = (F_r − F_l) s / 2`` in
  yaw (``s`` the wheel separation), and the sideways force at the axle. Wheel speeds are bounded by
  ``max_wheel_speed``.
* ``ideal``: the planar joints' velocity motors, bounded per axis (``max_force``, ``max_torque`` of
  :class:`~pushtorch.sim.settings.SimSettings`): a stiff pusher, kept for comparison with earlier runs.

Parameters and their sources are in docs/method.md ("The robot's drive"); :func:`wheel_forces` is the
whole controller (pure numpy, unit-tested on its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from pushtorch.errors import InvalidParameterError

__all__ = ["DRIVES", "DriveSettings", "DriveState", "wheel_forces"]

#: The drives ``sim.robot`` may name.
DRIVES = ("p3dx", "ideal")
GRAVITY = 9.81


@dataclass(frozen=True)
class DriveSettings:
    """The Pioneer 3-DX drive (``sim.drive``; docs/method.md gives each value's source).

    Attributes:
        robot_mass: kg, the whole robot (the URDF's base carries it).
        wheel_radius: m.
        wheel_separation: m between the two drive wheels' contact lines.
        wheel_friction: tyre–floor friction coefficient.
        drive_load_share: share of the robot's weight on the two drive wheels (the rest on the caster).
        wheel_torque: N m, the most a motor applies at its wheel.
        max_wheel_speed: m/s, a wheel's top ground speed.
        speed_gain: N per m/s of wheel-speed error (proportional term of each wheel's loop).
        integral_gain: N per m of accumulated wheel-speed error (integral term).
    """

    robot_mass: float = 9.0
    wheel_radius: float = 0.0975
    wheel_separation: float = 0.33
    wheel_friction: float = 0.5
    drive_load_share: float = 0.9
    wheel_torque: float = 5.0
    max_wheel_speed: float = 1.2
    speed_gain: float = 400.0
    integral_gain: float = 4000.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidParameterError(f"sim.drive.{f.name} must be a positive finite number, got {value!r}")
        if self.drive_load_share > 1.0:
            raise InvalidParameterError(f"sim.drive.drive_load_share must be at most 1, got {self.drive_load_share}")

    @property
    def wheel_force_limit(self) -> float:
        """N, the largest forward force one wheel can apply: the smaller of motor and traction."""
        return min(self.wheel_torque / self.wheel_radius, self.traction_limit)

    @property
    def traction_limit(self) -> float:
        """N, the friction force one drive wheel's share of the weight allows."""
        return self.wheel_friction * self.drive_load_share * self.robot_mass * GRAVITY / 2.0


@dataclass
class DriveState:
    """The wheel loops' integrals (m of accumulated speed error, left and right); reset per push."""

    left: float = 0.0
    right: float = 0.0


def _clip(value: float, limit: float) -> float:
    return -limit if value < -limit else (limit if value > limit else value)


def wheel_forces(drive: DriveSettings, command: tuple[float, float], velocity: tuple[float, float, float],
                 state: DriveState, time_step: float) -> tuple[float, float, float]:
    """One control step of the two wheel loops: the wheels' forward forces and the sideways holding force.

    Scalar Python on purpose: it runs every physics step of every push (numpy's per-call overhead tripled
    a push's cost).

    Args:
        drive: the drive's parameters.
        command: the commanded body twist (forward speed m/s, yaw rate rad/s).
        velocity: the base's current body velocity (forward m/s, sideways m/s, yaw rate rad/s).
        state: the loops' integrals, updated in place (conditional integration: a saturated wheel stops
            integrating in the direction that saturates it, so it does not wind up).
        time_step: s since the last step.

    Returns:
        ``(left, right, sideways)``: forward forces of the left and right wheel (N, each within its motor
        and traction limits), and the sideways force at the axle (N) that the wheels' remaining friction
        circles allow.
    """
    half = drive.wheel_separation / 2.0
    speed, yaw_rate = command
    forward, sideways, spin = velocity
    limit = drive.wheel_force_limit
    forces = []
    for side, sign in (("left", -1.0), ("right", 1.0)):
        target = _clip(speed + sign * yaw_rate * half, drive.max_wheel_speed)
        error = target - (forward + sign * spin * half)
        integral = getattr(state, side) + error * time_step
        wanted = drive.speed_gain * error + drive.integral_gain * integral
        force = _clip(wanted, limit)
        if not (abs(wanted) > limit and (error > 0) == (wanted > 0)):  # no wind-up while saturated
            setattr(state, side, integral)
        forces.append(force)
    # the rest of each wheel's friction circle holds the base sideways (a wheel slides only beyond it)
    circle = drive.traction_limit
    room = sum(math.sqrt(max(circle * circle - f * f, 0.0)) for f in forces)
    hold = -drive.robot_mass * sideways / time_step
    return forces[0], forces[1], _clip(hold, room)
