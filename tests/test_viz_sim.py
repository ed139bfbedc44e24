"""Rerun logging of a recorded push: entity paths and one transform per recorded time on ``sim_time``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.objects import load_object
from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes, simulate_plan
from pushtorch.viz import open_recording, read_entity_paths
from pushtorch.viz.sim import SIM, SIM_TIMELINE, log_push, log_pushes


@pytest.fixture(scope="module")
def records():
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 1, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=2)
    return simulate_plan(object_spec(cube), plan).to(torch.float32)


def test_a_push_is_logged_over_sim_time(tmp_path, records):
    from rerun.chunk import RrdReader

    path = tmp_path / "push.rrd"
    rec = open_recording(path, "pushtorch_test")
    roots = log_pushes(rec, records, [0, 2], load_object("cube").mesh)
    rec.disconnect()  # writes the file's footer
    assert roots == [f"{SIM}/push_0", f"{SIM}/push_2"]
    paths = read_entity_paths(path)
    for root in roots:
        for child in ("object", "object/mesh", "object_final", "robot", "robot/chassis", "robot/bumper",
                      "robot/bumper/mesh", "object_path", "robot_path"):
            assert f"/{root}/{child}" in paths, child
    # the object's transform has one row per recorded time on the sim_time timeline
    rows = 0
    for chunk in RrdReader(str(path)).store().stream().to_chunks():
        if str(chunk.entity_path) == f"/{SIM}/push_0/object":
            batch = chunk.to_record_batch()
            if SIM_TIMELINE in batch.schema.names:
                rows += batch.num_rows
    assert rows == len(records.time)


def test_out_of_range_push_raises(tmp_path, records):
    rec = open_recording(tmp_path / "x.rrd")
    with pytest.raises(InvalidParameterError):
        log_push(rec, records, 3, load_object("cube").mesh)


def test_a_push_under_a_given_root_replays_its_poses(tmp_path, records):
    """Under ``root``: translations and (x, y, z, w) quaternions per recorded time, no final pose if asked."""
    from rerun.chunk import RrdReader

    path = tmp_path / "rooted.rrd"
    rec = open_recording(path, "pushtorch_test")
    root = log_push(rec, records, 1, None, root="world/model/prediction/p/truth_push", with_final_pose=False)
    rec.disconnect()
    assert root == "world/model/prediction/p/truth_push"
    paths = read_entity_paths(path)
    assert f"/{root}/object" in paths and f"/{root}/robot/bumper/mesh" in paths
    assert f"/{root}/object_final" not in paths and f"/{root}/object/mesh" not in paths
    for entity, trajectory in (("object", records.object_trajectory), ("robot", records.robot_trajectory)):
        columns = {}
        for chunk in RrdReader(str(path)).store().stream().to_chunks():
            if str(chunk.entity_path) == f"/{root}/{entity}":
                batch = chunk.to_record_batch()
                if SIM_TIMELINE in batch.schema.names:
                    columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        poses = trajectory.take(1)
        np.testing.assert_allclose(np.asarray(columns["Transform3D:translation"]).reshape(-1, 3),
                                   poses.p.numpy(), atol=1e-6)
        np.testing.assert_allclose(np.asarray(columns["Transform3D:quaternion"]).reshape(-1, 4),
                                   se3.wxyz_to_xyzw(poses.q).numpy(), atol=1e-6)
