"""The pybullet world of a push: ground, robot with bumper, one object; created once, reset per push.

Paper, Experimental Setup: the authors simulated a Pioneer 3-DX with a bumper pushing objects in
Gazebo/ODE; pybullet replaces that engine here and is the ground truth of every push.

Design (decisions the paper leaves open, see docs/method.md):
    * The ground is a large static box whose top face is z = 0 (a box gives the objects a full contact
      manifold at once; a pybullet plane starts with one point and lets a resting object rock).
    * Objects are compounds of the :attr:`ObjectModel.collision_parts` convex pieces (pieces that are
      axis-aligned boxes become exact box primitives, the others convex hulls standing on support spheres:
      :func:`pushtorch.sim.geometry.object_pieces`, the same in MuJoCo), free rigid bodies
      (maximal coordinates), with the collision margin set to 0 so an object rests exactly at its
      ``rest_height`` (the default 1 mm margin lifts it). Mass and friction are set per push; the inertia is
      the mesh's (uniform density) scaled to the sampled mass, in the principal frame of the mesh.
    * The bumper's friction acts in the robot's horizontal plane only (anisotropic friction): vertical
      static friction between plate and object is indeterminate for a rigid solver and pressed the object
      into the ground or lifted it, which made the effective ground friction erratic.
    * Friction: pybullet multiplies the coefficients of the two bodies in contact. The object's own
      coefficient is fixed to ``object_friction`` (1.0 by default); the ground gets
      ``ground_friction / object_friction`` and the bumper ``bumper_friction / object_friction``, so the
      effective object-ground and object-bumper coefficients are exactly the sampled / configured ones.
    * The world ends at the ground's edge (``ground_half_extent``, 50 m): an object beyond it would fall
      for ever. :func:`pushtorch.sim.geometry.check_inside_world` refuses push inputs whose object or robot
      could leave the ground during the push (start position plus the distance the push can travel), or
      whose object starts below the ground; an object that still ends below the ground box is an error,
      never a record.
    * The robot is the package's URDF with a fixed world link placed at the push's start pose; its planar
      joints (x, y, yaw) start at 0, so joint x points along the start heading (see pushtorch.robot). Their
      velocity motors track the commanded body twist; each planar axis is bounded by ``max_force`` and yaw
      by ``max_torque`` (a box bound in the start frame: within the ±40° of a push the forward force
      available lies between ``max_force`` and 1.3 ``max_force``).

The simulation itself runs on numpy and pybullet (no torch on the workers' hot path).
Poses at this level are numpy ``(position (3,), quaternion (4,) wxyz)`` pairs; conversions to pybullet's
x,y,z,w (:func:`pushtorch.sim.geometry.xyzw` and :func:`~pushtorch.sim.geometry.wxyz`) happen here and
nowhere else in the simulator. :func:`pushtorch.sim.engines.make_world` builds this world or MuJoCo's.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile

import numpy as np

from pushtorch.errors import InvalidParameterError, SimulationError
from pushtorch.sim.drive import DriveState, wheel_forces
from pushtorch.sim.geometry import object_pieces, quat_conjugate, quat_multiply, wxyz, xyzw
from pushtorch.sim.settings import ObjectSpec, SimSettings

__all__ = ["PushWorld"]

#: Joint indices of pushtorch/assets/pioneer_bumper.urdf as pybullet numbers them.
JOINT_X, JOINT_Y, JOINT_YAW = 0, 1, 2
BASE_LINK_INDEX, BUMPER_LINK_INDEX = 2, 3
#: Thickness of the ground box (m); its top face is z = 0.
GROUND_THICKNESS = 0.1
#: pybullet keeps only this many children of a compound collision shape.
MAX_COMPOUND_CHILDREN = 16
#: Ground contact stiffness and damping per kg of the object (N/m, N s/m): ERP 0.5 at 240 Hz, so the support
#: forces under an object are the unique ones of a compliant floor, not whichever of the statically
#: indeterminate solutions the solver's order settles on.
GROUND_STIFFNESS_PER_KG, GROUND_DAMPING_PER_KG = 19200.0, 80.0


def _hull_file(text: str) -> str:
    """The path of an OBJ file holding ``text``, written once per content (``PushWorld._shape_arguments``)."""
    folder = os.path.join(tempfile.gettempdir(), "pushtorch-shapes")
    path = os.path.join(folder, hashlib.sha256(text.encode()).hexdigest()[:32] + ".obj")
    if not os.path.isfile(path):
        os.makedirs(folder, exist_ok=True)
        fd, partial = tempfile.mkstemp(dir=folder, suffix=".part")
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(partial, path)  # another process writing the same content at once writes the same bytes
    return path


class PushWorld:
    """One pybullet DIRECT client holding the ground, the robot and one object.

    The world is built once; every push resets it (poses, joint states, mass, friction) instead of
    rebuilding it. A push's outcome depends only on its own inputs: the object's collision shape and body
    are re-created before every push, so neither a contact cache nor a shape's internal state survives
    from the previous push (tests/test_sim_physics.py checks a push after another against a fresh world).

    Args:
        spec: the object to push.
        settings: physics and controller settings.
        urdf_path: robot URDF (default: the package's Pioneer with bumper).

    Raises:
        SimulationError: pybullet cannot connect or load a body.
    """

    def __init__(self, spec: ObjectSpec, settings: SimSettings | None = None, urdf_path: str | None = None):
        import pybullet as pb

        from pushtorch.robot import URDF_PATH

        self.pb = pb
        self.spec = spec
        self.settings = settings or SimSettings()
        if self.settings.engine != "pybullet":
            raise InvalidParameterError(f"PushWorld is the pybullet world; make_world builds a {self.settings.engine}"
                                        " one")
        self.client = pb.connect(pb.DIRECT)
        if self.client < 0:
            raise SimulationError("pybullet could not start a DIRECT physics client")
        self._closed = False
        s = self.settings
        cid = self.client
        pb.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=s.time_step,
            numSolverIterations=int(s.solver_iterations),
            numSubSteps=0,
            deterministicOverlappingPairs=1,
            # the solver's early exit (default 1e-7) stopped its iterations at an order-dependent point
            solverResidualThreshold=1e-9,
            physicsClientId=cid,
        )
        half = s.ground_half_extent
        ground_shape = pb.createCollisionShape(
            pb.GEOM_BOX, halfExtents=[half, half, GROUND_THICKNESS / 2], physicsClientId=cid
        )
        self.ground = pb.createMultiBody(
            0.0, ground_shape, basePosition=[0.0, 0.0, -GROUND_THICKNESS / 2], physicsClientId=cid
        )
        self.robot = pb.loadURDF(str(urdf_path or URDF_PATH), useFixedBase=True, physicsClientId=cid)
        if self.robot < 0:
            raise SimulationError(f"pybullet could not load the robot URDF {urdf_path or URDF_PATH}")
        # The chassis floats above the ground by design; skipping those pairs saves collision work.
        for link in range(-1, pb.getNumJoints(self.robot, physicsClientId=cid)):
            pb.setCollisionFilterPair(self.ground, self.robot, -1, link, 0, physicsClientId=cid)
            pb.changeDynamics(
                self.robot,
                link,
                lateralFriction=s.bumper_friction / s.object_friction,
                # Friction acts in the robot's horizontal plane only: vertical static friction between
                # the plate and the object is indeterminate for a rigid solver, which then pressed the
                # object into the ground or lifted it (ground normal force 0.8-1.5 m g, erratic pushes).
                anisotropicFriction=[1.0, 1.0, 0.0],
                physicsClientId=cid,
            )
        for joint in (JOINT_X, JOINT_Y, JOINT_YAW):
            pb.changeDynamics(self.robot, joint, jointDamping=0.0, linearDamping=0.0, angularDamping=0.0,
                              physicsClientId=cid)
        if s.robot == "p3dx":  # the base carries the robot's mass, which the wheels' traction depends on
            pb.changeDynamics(self.robot, BASE_LINK_INDEX, mass=s.drive.robot_mass, physicsClientId=cid)
        self._shape_args = self._shape_arguments()
        self._object_shape = -1
        self.object = -1
        # rotation of the principal (inertial) frame in the object frame, and its inverse
        self._q_principal = np.asarray(spec.principal_rotation, dtype=np.float64)

    # --- object ---------------------------------------------------------------------------------

    def _shape_arguments(self) -> dict:
        """The arguments of ``createCollisionShapeArray`` for the object: one compound collision shape, exact
        boxes as box primitives, other pieces as convex hulls standing on a ring of small spheres
        (:func:`object_pieces`). Made once per world; :meth:`_create_object_shape` builds a fresh shape from
        them for every push. pybullet reads a hull from an OBJ file: each is written once per content, under
        ``<temp>/pushtorch-shapes/`` by the hash of its text (atomically), and shared by every world and process
        that meets the same piece, so that no world leaves a folder behind when its process ends unclosed (a
        pool or cluster worker that is killed).
        """
        pb = self.pb
        types, half_extents, files, positions, radii = [], [], [], [], []
        geom = {"box": pb.GEOM_BOX, "hull": pb.GEOM_MESH, "sphere": pb.GEOM_SPHERE}
        for piece in object_pieces(self.spec, MAX_COMPOUND_CHILDREN):
            path = ""
            if piece.kind == "hull":
                # pybullet builds a dynamic mesh's convex hull from the vertices its faces reference
                path = _hull_file("".join(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in piece.vertices)
                                  + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in piece.faces))
            types.append(geom[piece.kind])
            half_extents.append([float(v) for v in piece.size] if piece.kind == "box" else [0.0, 0.0, 0.0])
            files.append(path)
            positions.append([float(v) for v in piece.centre])
            radii.append(float(piece.size[0]) if piece.kind == "sphere" else 0.0)
        return {"shapeTypes": types, "halfExtents": half_extents, "fileNames": files, "radii": radii,
                "meshScales": [[1.0, 1.0, 1.0]] * len(types), "collisionFramePositions": positions,
                "collisionFrameOrientations": [[0.0, 0.0, 0.0, 1.0]] * len(types)}

    def _create_object_shape(self) -> int:
        """A fresh compound collision shape of the object (:meth:`_shape_arguments`)."""
        shape = self.pb.createCollisionShapeArray(**self._shape_args, physicsClientId=self.client)
        if shape < 0:
            raise SimulationError(f"pybullet could not create the collision shape of {self.spec.name!r}")
        return shape

    def _principal_pose(self, position: np.ndarray, q_object: np.ndarray) -> tuple[list[float], list[float]]:
        """Object-frame pose → pose of the principal inertial frame that pybullet stores as the base."""
        return [float(v) for v in position], xyzw(quat_multiply(q_object, self._q_principal))

    def spawn_object(
        self, position: np.ndarray, q_object: np.ndarray, mass: float, ground_friction: float
    ) -> None:
        """(Re-)create the object body at a pose (object frame, wxyz) with its mass and the ground friction.

        Raises:
            InvalidParameterError: mass or friction not positive and finite.
        """
        if not (np.isfinite(mass) and mass > 0):
            raise InvalidParameterError(f"object mass must be positive and finite, got {mass!r}")
        if not (np.isfinite(ground_friction) and ground_friction > 0):
            raise InvalidParameterError(
                f"ground friction must be positive and finite, got {ground_friction!r}"
            )
        pb, cid, s = self.pb, self.client, self.settings
        if self.object >= 0:
            pb.removeBody(self.object, physicsClientId=cid)
        # A fresh collision shape for every push: a convex-hull shape keeps state from the pushes it took
        # part in (a cylinder pushed after another push ended 27 mm from where it ends in a fresh world);
        # rebuilt, every push is a function of its own inputs alone (2-3 ms). pybullet refuses to remove a
        # shape a removed body used, so the old ones stay (a few kB each).
        self._object_shape = self._create_object_shape()
        pos, orn = self._principal_pose(position, q_object)
        self.object = pb.createMultiBody(
            baseMass=float(mass),
            baseCollisionShapeIndex=self._object_shape,
            basePosition=pos,
            baseOrientation=orn,
            baseInertialFramePosition=[0.0, 0.0, 0.0],
            baseInertialFrameOrientation=xyzw(self._q_principal),
            # a free rigid body (not a 0-link multibody) collides and solves markedly faster
            useMaximalCoordinates=True,
            physicsClientId=cid,
        )
        if self.object < 0:
            raise SimulationError(f"pybullet could not create the body of {self.spec.name!r}")
        pb.resetBasePositionAndOrientation(self.object, pos, orn, physicsClientId=cid)
        pb.changeDynamics(
            self.object,
            -1,
            mass=float(mass),
            localInertiaDiagonal=[float(v) for v in mass * np.asarray(self.spec.inertia_per_kg)],
            lateralFriction=s.object_friction,
            spinningFriction=0.0,
            rollingFriction=0.0,
            restitution=0.0,
            linearDamping=0.0,
            angularDamping=0.0,
            collisionMargin=0.0,
            activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=cid,
        )
        pb.changeDynamics(self.ground, -1, lateralFriction=float(ground_friction) / s.object_friction,
                          restitution=0.0, contactStiffness=GROUND_STIFFNESS_PER_KG * float(mass),
                          contactDamping=GROUND_DAMPING_PER_KG * float(mass), physicsClientId=cid)

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's current pose: position ``(3,)`` and wxyz quaternion ``(4,)`` of the object frame."""
        pos, orn = self.pb.getBasePositionAndOrientation(self.object, physicsClientId=self.client)
        q = quat_multiply(wxyz(orn), quat_conjugate(self._q_principal))
        return np.asarray(pos, dtype=np.float64), q / np.linalg.norm(q)

    # --- robot ----------------------------------------------------------------------------------

    def place_robot(self, position: np.ndarray, q_base: np.ndarray) -> None:
        """Put the robot's world link at the start pose (base frame, wxyz) with its joints at rest."""
        pb, cid = self.pb, self.client
        pb.resetBasePositionAndOrientation(
            self.robot, [float(v) for v in position], xyzw(q_base), physicsClientId=cid
        )
        for joint in (JOINT_X, JOINT_Y, JOINT_YAW):
            pb.resetJointState(self.robot, joint, 0.0, 0.0, physicsClientId=cid)
        self._drive_state = DriveState()
        if self.settings.robot == "p3dx":
            # the wheels' forces replace the joints' velocity motors (which would otherwise hold the joints)
            pb.setJointMotorControlArray(self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], pb.VELOCITY_CONTROL,
                                         targetVelocities=[0.0, 0.0, 0.0], forces=[0.0, 0.0, 0.0],
                                         physicsClientId=cid)
        self.drive(0.0, 0.0)

    @property
    def control_every(self) -> int:
        """Physics steps between two calls of :meth:`drive`: the wheels' forces act for one step only."""
        return 1 if self.settings.robot == "p3dx" else int(self.settings.control_every)

    def drive(self, speed: float, yaw_rate: float) -> None:
        """Command the body twist (forward speed m/s, yaw rate rad/s) through the robot's drive.

        ``p3dx``: the wheels' forces of :func:`pushtorch.sim.drive.wheel_forces` for the next physics step.
        ``ideal``: the planar joints live in the start frame, so the forward speed is split along the current
        heading; each drive axis is bounded by ``max_force`` (yaw by ``max_torque``).
        """
        if self.settings.robot == "p3dx":
            self._drive_wheels(speed, yaw_rate)
            return
        pb, cid, s = self.pb, self.client, self.settings
        heading = pb.getJointState(self.robot, JOINT_YAW, physicsClientId=cid)[0]
        pb.setJointMotorControlArray(
            self.robot,
            [JOINT_X, JOINT_Y, JOINT_YAW],
            pb.VELOCITY_CONTROL,
            targetVelocities=[speed * np.cos(heading), speed * np.sin(heading), yaw_rate],
            forces=[s.max_force, s.max_force, s.max_torque],
            physicsClientId=cid,
        )

    def _drive_wheels(self, speed: float, yaw_rate: float) -> None:
        pb, cid, s = self.pb, self.client, self.settings
        states = pb.getJointStates(self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], physicsClientId=cid)
        heading, (vx, vy, spin) = states[2][0], (st[1] for st in states)
        cos, sin = math.cos(heading), math.sin(heading)
        left, right, sideways = wheel_forces(s.drive, (speed, yaw_rate),
                                             (vx * cos + vy * sin, -vx * sin + vy * cos, spin), self._drive_state,
                                             s.time_step)
        forward = left + right
        torque = (right - left) * s.drive.wheel_separation / 2.0
        pb.setJointMotorControlArray(
            self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], pb.TORQUE_CONTROL,
            forces=[forward * cos - sideways * sin, forward * sin + sideways * cos, torque], physicsClientId=cid,
        )

    def robot_joints(self) -> np.ndarray:
        """Joint positions ``(3,)``: x, y (m) and yaw (rad) of the base in the start frame."""
        states = self.pb.getJointStates(
            self.robot, [JOINT_X, JOINT_Y, JOINT_YAW], physicsClientId=self.client
        )
        return np.array([st[0] for st in states], dtype=np.float64)

    def touching(self) -> bool:
        """Whether the robot (bumper or chassis) is in contact with the object now."""
        return bool(self.pb.getContactPoints(self.robot, self.object, physicsClientId=self.client))

    def step(self) -> None:
        self.pb.stepSimulation(physicsClientId=self.client)

    def close(self) -> None:
        """Disconnect the pybullet client (idempotent)."""
        if not self._closed:
            try:
                self.pb.disconnect(physicsClientId=self.client)
            finally:
                self._closed = True

    def __enter__(self) -> PushWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort at interpreter shutdown
        try:
            self.close()
        except Exception:
            pass
