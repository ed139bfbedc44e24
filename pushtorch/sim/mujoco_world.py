"""The MuJoCo world of a push: the same ground, robot, bumper, drive and object as the pybullet world.

Paper, Experimental Setup and Future Work: the authors' ground truth was Gazebo/ODE; pushtorch's default is
pybullet. A second engine lets the *world* (training pushes, ground truth) differ from the simulator the
physics peers roll out in, as a lab's simulator differs from its floor (``world.engine`` and
``physics.engine``, docs/method.md "Two engines").

:class:`MujocoWorld` has :class:`pushtorch.sim.pybullet_world.PushWorld`'s interface (``spawn_object``,
``object_pose``, ``place_robot``, ``drive``, ``robot_joints``, ``touching``, ``step``, ``close``), so
:func:`pushtorch.sim.push.execute_push` runs a push in either engine unchanged.

Design (decisions, see docs/method.md "Two engines"):
    * One source of truth for the robot: its MJCF is written here from the shipped URDF's boxes and mount
      (:func:`pushtorch.robot.bumper_geometry`), with the same three planar joints (x, y, yaw) in the push's
      start frame and the same drive (:func:`pushtorch.sim.drive.wheel_forces`, applied as generalised
      forces on the planar joints every physics step, as in pybullet). ``ideal`` uses velocity actuators
      bounded by ``max_force`` / ``max_torque``.
    * Objects are bodies of the same collision pieces as in pybullet (:func:`pushtorch.sim.geometry.object_pieces`):
      axis-aligned boxes as box geoms, the other parts as mesh geoms (MuJoCo collides a mesh as its convex
      hull) standing on the same support spheres. Without them MuJoCo's plane collider picks a few of a flat
      bottom's equally deep vertices in their stored order, and mirrored pushes of the hybrid ended 8 mm apart.
    * Friction: MuJoCo combines two geoms' coefficients by the maximum, unless one geom has the higher
      ``priority``, whose coefficient then holds. The ground and the bumper have priority 1 and the object 0,
      so the object-ground coefficient is exactly the sampled μ and the object-bumper one ``bumper_friction``,
      as in the pybullet world (``tests/test_mujoco_world.py`` measures μ from a sliding block's deceleration).
      The bumper's friction is isotropic in MuJoCo (pybullet's world keeps it horizontal): part of the gap.
    * Contacts are soft: the solver's time constant is two physics steps (the shortest MuJoCo allows), so a
      resting object sinks under a millimetre; ``multiccd`` gives flat convex faces several contact points.
    * Mass and inertia are set per push on the compiled model and its constants recomputed
      (``mj_setConst``); ``mj_resetData`` clears every trace of the previous push.

Numpy only (workers run it); quaternions are wxyz, MuJoCo's own order, so none is converted.
"""

from __future__ import annotations

import math

import numpy as np

from pushtorch.errors import InvalidParameterError, SimulationError
from pushtorch.sim.drive import DriveState, wheel_forces
from pushtorch.sim.geometry import object_pieces
from pushtorch.sim.settings import ObjectSpec, SimSettings

__all__ = ["MujocoWorld", "world_xml"]

#: ``contype`` / ``conaffinity`` bits: the ground collides with the object only, the robot with the object only.
_GROUND, _OBJECT, _ROBOT = (2, 0), (1, 3), (1, 0)
#: Gain (N per m/s, N m per rad/s) of the ``ideal`` robot's velocity actuators.
IDEAL_GAIN = 2000.0


def _floats(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.asarray(values, dtype=np.float64).reshape(-1))


def world_xml(spec: ObjectSpec, settings: SimSettings) -> str:
    """The MJCF of one push world: ground plane, the robot of the shipped URDF, and ``spec``'s object.

    Raises:
        SimulationError: an object part that MuJoCo cannot hold (fewer than 4 vertices off a plane).
    """
    from pushtorch.robot import BASE_LINK, BUMPER_LINK, bumper_geometry, link_inertial

    s = settings
    geometry = bumper_geometry()
    mount = geometry.mount
    mount_p = mount.p.double().numpy()
    mount_q = mount.q.double().numpy()
    chassis_half = np.asarray(geometry.chassis_size, dtype=np.float64) / 2
    bumper_half = np.asarray(geometry.size, dtype=np.float64) / 2
    robot_mass = s.drive.robot_mass if s.robot == "p3dx" else link_inertial(BASE_LINK)[0]
    bumper_mass, bumper_com, bumper_moments = link_inertial(BUMPER_LINK)
    # the URDF's chassis inertia scaled to the robot's mass (a uniform box)
    cx, cy, cz = np.asarray(geometry.chassis_size, dtype=np.float64)
    chassis_inertia = robot_mass / 12.0 * np.array([cy**2 + cz**2, cx**2 + cz**2, cx**2 + cy**2])
    assets, geoms = [], []
    common = f'contype="{_OBJECT[0]}" conaffinity="{_OBJECT[1]}" priority="0" friction="0 0 0" condim="3"'
    for i, piece in enumerate(object_pieces(spec)):
        if piece.kind == "box":
            geoms.append(f'<geom name="part{i}" type="box" pos="{_floats(piece.centre)}" size="{_floats(piece.size)}"'
                         f' {common}/>')
        elif piece.kind == "hull":
            assets.append(f'<mesh name="part{i}" vertex="{_floats(piece.vertices)}" inertia="convex"/>')
            geoms.append(f'<geom name="part{i}" type="mesh" mesh="part{i}" {common}/>')
        else:
            geoms.append(f'<geom name="part{i}" type="sphere" pos="{_floats(piece.centre)}" '
                         f'size="{float(piece.size[0])!r}" {common}/>')
    half = s.ground_half_extent
    actuators = ""
    if s.robot == "ideal":
        actuators = (
            "<actuator>"
            f'<velocity name="vx" joint="base_x" kv="{IDEAL_GAIN}" forcelimited="true" '
            f'forcerange="{-s.max_force} {s.max_force}"/>'
            f'<velocity name="vy" joint="base_y" kv="{IDEAL_GAIN}" forcelimited="true" '
            f'forcerange="{-s.max_force} {s.max_force}"/>'
            f'<velocity name="vyaw" joint="base_yaw" kv="{IDEAL_GAIN}" forcelimited="true" '
            f'forcerange="{-s.max_torque} {s.max_torque}"/>'
            "</actuator>"
        )
    timeconst = 2.0 * s.time_step
    return f"""<mujoco model="pushtorch_{spec.name}">
  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>
  <option timestep="{s.time_step!r}" gravity="0 0 -9.81" integrator="implicitfast" cone="elliptic"
          iterations="{int(s.solver_iterations)}" tolerance="1e-10">
    <flag multiccd="enable" warmstart="enable"/>
  </option>
  <default><geom solref="{timeconst!r} 1" solimp="0.95 0.99 0.001"/></default>
  <asset>{''.join(assets)}</asset>
  <worldbody>
    <geom name="ground" type="plane" size="{half} {half} 0.1" contype="{_GROUND[0]}" conaffinity="{_GROUND[1]}"
          priority="1" friction="1 0 0" condim="3"/>
    <body name="base" pos="0 0 0">
      <joint name="base_x" type="slide" axis="1 0 0" damping="0" armature="0"/>
      <joint name="base_y" type="slide" axis="0 1 0" damping="0" armature="0"/>
      <joint name="base_yaw" type="hinge" axis="0 0 1" damping="0" armature="0"/>
      <inertial pos="{_floats(geometry.chassis_centre)}" mass="{robot_mass!r}"
                diaginertia="{_floats(chassis_inertia)}"/>
      <geom name="chassis" type="box" pos="{_floats(geometry.chassis_centre)}" size="{_floats(chassis_half)}"
            contype="{_ROBOT[0]}" conaffinity="{_ROBOT[1]}" priority="1" friction="{s.bumper_friction!r} 0 0"
            condim="3"/>
      <body name="bumper" pos="{_floats(mount_p)}" quat="{_floats(mount_q)}">
        <inertial pos="{_floats(bumper_com)}" mass="{bumper_mass!r}" diaginertia="{_floats(bumper_moments)}"/>
        <geom name="bumper" type="box" pos="{_floats(geometry.box_centre)}" size="{_floats(bumper_half)}"
              contype="{_ROBOT[0]}" conaffinity="{_ROBOT[1]}" priority="1" friction="{s.bumper_friction!r} 0 0"
              condim="3"/>
      </body>
    </body>
    <body name="object" pos="0 0 1">
      <freejoint name="object"/>
      <inertial pos="0 0 0" quat="{_floats(spec.principal_rotation)}" mass="1"
                diaginertia="{_floats(spec.inertia_per_kg)}"/>
      {''.join(geoms)}
    </body>
  </worldbody>
  {actuators}
</mujoco>
"""


class MujocoWorld:
    """One MuJoCo model and data holding the ground, the robot and one object (see the module notes).

    Built once per object; every push resets the data and sets the object's mass, inertia and the ground's
    friction on the model. Same interface as :class:`pushtorch.sim.pybullet_world.PushWorld`.

    Raises:
        SimulationError: MuJoCo cannot compile the world (e.g. a degenerate object part).
    """

    def __init__(self, spec: ObjectSpec, settings: SimSettings | None = None):
        import mujoco

        self.mj = mujoco
        self.spec = spec
        self.settings = settings or SimSettings(engine="mujoco")
        try:
            self.model = mujoco.MjModel.from_xml_string(world_xml(spec, self.settings))
        except ValueError as exc:
            raise SimulationError(f"MuJoCo cannot build the world of {spec.name!r}: {exc}") from exc
        self.data = mujoco.MjData(self.model)
        m = self.model
        name = mujoco.mjtObj
        self._object_body = mujoco.mj_name2id(m, name.mjOBJ_BODY, "object")
        self._ground = mujoco.mj_name2id(m, name.mjOBJ_GEOM, "ground")
        robot_bodies = {mujoco.mj_name2id(m, name.mjOBJ_BODY, n) for n in ("base", "bumper")}
        self._robot_geom = np.isin(m.geom_bodyid, sorted(robot_bodies))
        self._is_object_geom = m.geom_bodyid == self._object_body
        joint = m.jnt_qposadr[mujoco.mj_name2id(m, name.mjOBJ_JOINT, "object")]
        self._object_q = slice(int(joint), int(joint) + 7)
        self._drive_state = DriveState()
        self._closed = False

    def spawn_object(self, position: np.ndarray, q_object: np.ndarray, mass: float, ground_friction: float) -> None:
        """Reset the world with the object at a pose (object frame, wxyz), its mass and the ground friction.

        Raises:
            InvalidParameterError: mass or friction not positive and finite.
        """
        if not (np.isfinite(mass) and mass > 0):
            raise InvalidParameterError(f"object mass must be positive and finite, got {mass!r}")
        if not (np.isfinite(ground_friction) and ground_friction > 0):
            raise InvalidParameterError(f"ground friction must be positive and finite, got {ground_friction!r}")
        mj, m, d = self.mj, self.model, self.data
        m.body_mass[self._object_body] = float(mass)
        m.body_inertia[self._object_body] = float(mass) * np.asarray(self.spec.inertia_per_kg, dtype=np.float64)
        m.geom_friction[self._ground, 0] = float(ground_friction)
        mj.mj_setConst(m, d)  # the mass-dependent constants (the contacts' softness scales with them)
        mj.mj_resetData(m, d)  # after mj_setConst, which leaves the data at the model's reference pose
        q = np.asarray(q_object, dtype=np.float64)
        d.qpos[self._object_q] = np.concatenate([np.asarray(position, dtype=np.float64), q / np.linalg.norm(q)])
        mj.mj_forward(m, d)

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's current pose: position ``(3,)`` and wxyz quaternion ``(4,)`` of the object frame."""
        qpos = self.data.qpos[self._object_q]
        q = np.array(qpos[3:], dtype=np.float64)
        return np.array(qpos[:3], dtype=np.float64), q / np.linalg.norm(q)

    def place_robot(self, position: np.ndarray, q_base: np.ndarray) -> None:
        """The robot's planar joints at rest at the start (pushes run in the robot's start frame: only the
        identity start is simulated)."""
        if np.abs(np.asarray(position, dtype=np.float64)).max() > 0 or abs(float(q_base[0]) - 1.0) > 1e-12:
            raise InvalidParameterError("the MuJoCo world simulates every push in the robot's start frame")
        self.data.qpos[:3] = 0.0
        self.data.qvel[:3] = 0.0
        self._drive_state = DriveState()
        self.drive(0.0, 0.0)

    @property
    def control_every(self) -> int:
        """Physics steps between two calls of :meth:`drive` (the wheels' forces act for one step only)."""
        return 1 if self.settings.robot == "p3dx" else int(self.settings.control_every)

    def drive(self, speed: float, yaw_rate: float) -> None:
        """Command the body twist through the robot's drive (see :meth:`PushWorld.drive`)."""
        d, s = self.data, self.settings
        heading = float(d.qpos[2])
        cos, sin = math.cos(heading), math.sin(heading)
        if s.robot != "p3dx":
            d.ctrl[:] = (speed * cos, speed * sin, yaw_rate)
            return
        vx, vy, spin = (float(v) for v in d.qvel[:3])
        left, right, sideways = wheel_forces(s.drive, (speed, yaw_rate),
                                             (vx * cos + vy * sin, -vx * sin + vy * cos, spin), self._drive_state,
                                             s.time_step)
        forward = left + right
        d.qfrc_applied[:3] = (forward * cos - sideways * sin, forward * sin + sideways * cos,
                              (right - left) * s.drive.wheel_separation / 2.0)

    def robot_joints(self) -> np.ndarray:
        """Joint positions ``(3,)``: x, y (m) and yaw (rad) of the base in the start frame."""
        return np.array(self.data.qpos[:3], dtype=np.float64)

    def touching(self) -> bool:
        """Whether the robot (bumper or chassis) is in contact with the object now."""
        n = self.data.ncon
        if n == 0:
            return False
        geoms = self.data.contact.geom[:n]
        a, b = geoms[:, 0], geoms[:, 1]
        hit = (self._robot_geom[a] & self._is_object_geom[b]) | (self._robot_geom[b] & self._is_object_geom[a])
        return bool(hit.any())

    def step(self) -> None:
        self.mj.mj_step(self.model, self.data)

    def close(self) -> None:
        """Nothing to release (MuJoCo's model and data are freed with the object); idempotent."""
        self._closed = True

    def __enter__(self) -> MujocoWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
