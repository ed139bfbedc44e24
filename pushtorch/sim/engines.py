"""Which engine a push world runs in: the factory that builds the pybullet or the MuJoCo world.

Paper, Experimental Setup and Future Work: the authors' ground truth was Gazebo/ODE; pushtorch's default is
pybullet (:mod:`pushtorch.sim.pybullet_world`), and MuJoCo (:mod:`pushtorch.sim.mujoco_world`) lets the
world (training pushes, ground truth) differ from the simulator the physics peers roll out in
(``world.engine`` and ``physics.engine``, docs/method.md "Two engines"). :func:`make_world` is the only place
that knows both worlds: every caller that builds a world asks it, by :attr:`SimSettings.engine`.
"""

from __future__ import annotations

from pushtorch.sim.pybullet_world import PushWorld
from pushtorch.sim.settings import ObjectSpec, SimSettings

__all__ = ["engine_version", "make_world"]


def make_world(spec: ObjectSpec, settings: SimSettings | None = None):
    """The world of ``settings.engine`` for ``spec``: a :class:`PushWorld` (pybullet) or a
    :class:`pushtorch.sim.mujoco_world.MujocoWorld`; both run :func:`pushtorch.sim.push.execute_push`.

    Raises:
        MissingDependencyError: the engine's package is not installed.
        SimulationError: the engine cannot build the world.
    """
    settings = settings or SimSettings()
    if settings.engine == "mujoco":
        try:
            import mujoco  # noqa: F401
        except ImportError as exc:
            from pushtorch.errors import MissingDependencyError

            raise MissingDependencyError(f"world.engine=mujoco needs MuJoCo: pip install mujoco ({exc})") from exc
        from pushtorch.sim.mujoco_world import MujocoWorld

        return MujocoWorld(spec, settings)
    return PushWorld(spec, settings)



def engine_version(engine: str) -> str:
    """The installed version of ``engine`` (``pybullet`` or ``mujoco``): what a model file records."""
    if engine == "mujoco":
        import mujoco

        return f"mujoco {mujoco.__version__}"
    import importlib.metadata

    return f"pybullet {importlib.metadata.version('pybullet')}"
