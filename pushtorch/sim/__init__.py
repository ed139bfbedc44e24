"""Push simulation in pybullet or MuJoCo: worlds, actions, priors, plans, records and the parallel runner.

Paper, Experimental Setup and Biasing Transferable Push Manipulation Models: pybullet replaces the paper's
Gazebo/ODE as the ground truth. The pieces, in the order data flows through them:

    priors          mass and friction distributions (generalising U, biasing N, fixed)  pushtorch.sim.priors
    plan            every push's inputs, drawn up front from one seeded generator       pushtorch.sim.plan
    settings        simulator settings, the object spec, the world's version            pushtorch.sim.settings
    geometry        the world's edge, quaternions, collision pieces of both engines     pushtorch.sim.geometry
    drive           the Pioneer 3-DX's wheels, traction and motors                      pushtorch.sim.drive
    pybullet_world  one pybullet client: ground, robot, object; reset per push          pushtorch.sim.pybullet_world
    mujoco_world    the same world in MuJoCo                                            pushtorch.sim.mujoco_world
    engines         make_world: the world of the configured engine                      pushtorch.sim.engines
    push            actions a = (ẋ, θ̇), placement, one push and its validity flags      pushtorch.sim.push
    worker          a shard's pushes simulated in one world and written                 pushtorch.sim.worker
    shards          the no-pickle shard format                                          pushtorch.sim.shards
    run_manifest    what a run's folder promises, and how much of it is there           pushtorch.sim.run_manifest
    records         PushRecords, loading a run, its per-push table                      pushtorch.sim.records
    tables          a lab's own push tables: read, checked, exported                   pushtorch.sim.tables
    runner          worker processes, progress bar, resumable shards                    pushtorch.sim.runner
    executors       where the shards run: this machine, Ray or Slurm                    pushtorch.sim.executors
    bodies          the body a cloud builds, and its pushes rolled out as an ensemble   pushtorch.sim.bodies

Quick use::

    from pushtorch.objects import load_object
    from pushtorch.sim import (Normal, Placement, make_actions, object_spec, plan_training_pushes,
                               run_plan, load_records)
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 10, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    run_plan(object_spec(cube), plan, "runs/demo/pushes")
    records = load_records("runs/demo")
"""

from pushtorch.sim.plan import Placement, PushPlan, plan_training_pushes
from pushtorch.sim.priors import Fixed, Normal, Prior, Uniform, prior_from_config
from pushtorch.sim.push import (
    ACTION_DURATION,
    ACTION_SPEED,
    PushOutcome,
    execute_push,
    make_actions,
    place_robot_against,
)
from pushtorch.sim.pybullet_world import PushWorld
from pushtorch.sim.records import PushRecords, load_records
from pushtorch.sim.runner import (
    PushPool,
    RunSummary,
    default_workers,
    run_plan,
    simulate_plan,
    simulate_pushes,
)
from pushtorch.sim.settings import ObjectSpec, SimSettings, object_spec
from pushtorch.sim.shards import read_shard, write_shard

__all__ = [
    "ACTION_DURATION",
    "ACTION_SPEED",
    "Fixed",
    "Normal",
    "ObjectSpec",
    "Placement",
    "Prior",
    "PushOutcome",
    "PushPlan",
    "PushPool",
    "PushRecords",
    "PushWorld",
    "RunSummary",
    "SimSettings",
    "Uniform",
    "default_workers",
    "execute_push",
    "load_records",
    "make_actions",
    "object_spec",
    "place_robot_against",
    "plan_training_pushes",
    "prior_from_config",
    "read_shard",
    "run_plan",
    "simulate_plan",
    "simulate_pushes",
    "write_shard",
]
