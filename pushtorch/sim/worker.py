"""What every simulation worker runs: a plan slice's pushes in one world, stacked into shard arrays and written.

Paper, Experimental Setup ("a push action is generated and a PDR is recorded", tens of thousands of pushes
per experiment). A task is one shard of consecutive pushes of a plan (:mod:`pushtorch.sim.plan`): the worker
runs each push in its world (:func:`pushtorch.sim.push.execute_push`, in either engine) and writes the
shard itself, atomically (:func:`pushtorch.sim.shards.write_shard`). Every executor's workers run
:func:`run_shard_in`: this process (:mod:`pushtorch.sim.runner`), its process pool, or Ray and Slurm
(:mod:`pushtorch.sim.executors`).

Numpy only: no torch on the workers' hot path.
"""

from __future__ import annotations

import numpy as np

from pushtorch.sim.push import execute_push
from pushtorch.sim.shards import write_shard

__all__ = ["run_shard_in", "simulate_arrays"]


def simulate_arrays(world, plan_arrays: dict[str, np.ndarray], object_name: str, seed: int,
                    duration: float) -> dict[str, np.ndarray]:
    """Simulate the pushes of one plan slice in ``world``; return the shard arrays (numpy, no torch)."""
    n = len(plan_arrays["index"])
    outcomes = []
    for i in range(n):
        outcomes.append(
            execute_push(
                world,
                plan_arrays["robot_start_p"][i],
                plan_arrays["robot_start_q"][i],
                plan_arrays["object_initial_p"][i],
                plan_arrays["object_initial_q"][i],
                float(plan_arrays["action"][i, 0]),
                float(plan_arrays["action"][i, 1]),
                float(duration),
                float(plan_arrays["mass"][i]),
                float(plan_arrays["ground_friction"][i]),
            )
        )
    times = outcomes[0].time if outcomes else np.zeros(1)
    t = len(times)

    def stack(name: str, trailing: tuple[int, ...]) -> np.ndarray:
        if not outcomes:
            return np.zeros((0, *trailing))
        return np.stack([getattr(o, name) for o in outcomes]).astype(np.float64)

    return {
        "index": np.asarray(plan_arrays["index"], dtype=np.int64),
        "seed": np.full(n, int(seed), dtype=np.int64),
        "object_name": np.array([object_name] * n, dtype=str).reshape(n),
        "action_index": np.asarray(plan_arrays["action_index"], dtype=np.int64),
        "action": np.asarray(plan_arrays["action"], dtype=np.float64),
        "object_initial_p": stack("object_initial_p", (3,)),
        "object_initial_q": stack("object_initial_q", (4,)),
        "object_final_p": stack("object_final_p", (3,)),
        "object_final_q": stack("object_final_q", (4,)),
        "robot_start_p": np.asarray(plan_arrays["robot_start_p"], dtype=np.float64),
        "robot_start_q": np.asarray(plan_arrays["robot_start_q"], dtype=np.float64),
        "object_trajectory_p": stack("object_trajectory_p", (t, 3)),
        "object_trajectory_q": stack("object_trajectory_q", (t, 4)),
        "robot_trajectory_p": stack("robot_trajectory_p", (t, 3)),
        "robot_trajectory_q": stack("robot_trajectory_q", (t, 4)),
        "time": np.asarray(times, dtype=np.float64),
        "mass": np.asarray(plan_arrays["mass"], dtype=np.float64),
        "ground_friction": np.asarray(plan_arrays["ground_friction"], dtype=np.float64),
        "object_friction": np.full(n, world.settings.object_friction, dtype=np.float64),
        "touched": np.array([o.touched for o in outcomes], dtype=bool).reshape(n),
        "tipped": np.array([o.tipped for o in outcomes], dtype=bool).reshape(n),
        "left_ground": np.array([o.left_ground for o in outcomes], dtype=bool).reshape(n),
        "first_contact_time": np.array([o.first_contact_time for o in outcomes], dtype=np.float64).reshape(n),
    }


def run_shard_in(world, task: tuple[int, str, dict[str, np.ndarray], str, int, float]) -> tuple[int, int, int]:
    """Simulate one task's shard in ``world`` and write it (atomically) into the task's folder; returns
    ``(shard id, pushes, valid pushes)``. Every executor's workers run this."""
    shard_id, folder, arrays, object_name, seed, duration = task
    result = simulate_arrays(world, arrays, object_name, seed, duration)
    write_shard(folder, shard_id, result)
    valid = int((result["touched"] & ~result["tipped"] & ~result["left_ground"]).sum())
    return shard_id, len(result["index"]), valid
