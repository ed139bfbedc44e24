"""Push tables (pushtorch.sim.tables): a lab's own pushes read, checked, trained on and conditioned on; a simulated
run exported as one; every bad table refused with the column and row, and no model file written."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.apps.train import train_from_config
from pushtorch.errors import InvalidParameterError, ModelError, RecordFormatError
from pushtorch.models.conditioning import observations_from_table
from pushtorch.models.model import load_model
from pushtorch.models.residual import train_residual_model
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_mesh_file, load_object, save_mesh_file
from pushtorch.objects.shapes import random_shape
from pushtorch.prediction import predict
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.tables import (
    TOUCH_DISTANCE,
    export_run_table,
    infer_flags,
    read_push_table,
    write_push_table,
)

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "tests" / "data" / "lab_table"
SMALL = {"query_kernels": 400, "anneal_candidates": 60, "anneal_steps": 15, "position_frames": 800,
         "environment_kernels": 300, "manipulator_kernels": 40}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A generated shape (not in the catalogue) pushed 8 times per action in pybullet, its run exported as a table."""
    obj = random_shape(3)
    root = tmp_path_factory.mktemp("exported")
    plan = plan_training_pushes(obj, make_actions(3), 8, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    run_plan(object_spec(obj), plan, root / "pushes", workers=1, progress=False)
    return obj, root, export_run_table(root / "pushes", obj, "p3dx", 4.0)


def _copy(tmp_path: Path) -> Path:
    folder = tmp_path / "table"
    shutil.copytree(SHIPPED, folder)
    return folder / "pushes.parquet"


def _edit(path: Path, edit) -> Path:
    """Rewrite the table at ``path`` with ``edit(table) -> table`` (its metadata kept unless ``edit`` changes it)."""
    table = pq.read_table(path)
    pq.write_table(edit(table), path)
    return path


def _set(table: pa.Table, column: str, row: int, value) -> pa.Table:
    values = table.column(column).to_pylist()
    values[row] = value
    index = table.column_names.index(column)
    return table.set_column(index, column, pa.array(values, type=table.schema.field(column).type))


def _train(path: Path, out: Path, **extra) -> dict:
    return train_from_config({"data": str(path), "recording": False, "model": {"settings": SMALL}, **extra}, out)


def test_a_run_exported_as_a_table_trains_the_same_model_bit_for_bit(exported):
    obj, root, table_path = exported
    table = read_push_table(table_path, make_actions(3), 4.0)
    assert table.object_names == (obj.name,) and table.has_physics and not table.inferred
    assert {p.name for p in (root / "pushes" / "meshes").iterdir()} == {f"{obj.name}.ply"}
    reloaded = table.object(obj.name)
    assert np.array_equal(reloaded.mesh.vertices, obj.mesh.vertices)  # a lossless mesh
    settings = ModelSettings(**SMALL)
    a = train_push_model(obj, load_records(root, trajectories=False), settings, generator=0)
    b = train_push_model(reloaded, table.records, settings, generator=0)
    a.save(root / "a.npz")
    b.save(root / "b.npz")
    assert (root / "a.npz").read_bytes() == (root / "b.npz").read_bytes()
    cloud = table.cloud(0)
    pa_, pb = (predict(m, cloud, m.actions[1], torch.Generator().manual_seed(3)) for m in (a, b))
    assert torch.equal(pa_.final_pose.p, pb.final_pose.p) and torch.equal(pa_.final_pose.q, pb.final_pose.q)
    # every row shares the one cloud of the object's one start pose
    assert len(set(table.clouds)) == 1
    with pytest.raises(RecordFormatError, match="read_push_table"):  # the sibling reads tables
        load_records(table_path)


def test_a_table_without_physics_trains_and_predicts_and_conditioning_names_the_missing_columns(exported, tmp_path):
    _, root, table_path = exported
    path = tmp_path / "pushes.parquet"
    shutil.copytree(root / "pushes" / "meshes", tmp_path / "meshes")
    shutil.copytree(root / "pushes" / "clouds", tmp_path / "clouds")
    table = pq.read_table(table_path)
    pq.write_table(table.drop_columns(["mass", "ground_friction"]), path)
    read = read_push_table(path)
    assert not read.has_physics and torch.isnan(read.records.mass).all()
    summary = _train(path, tmp_path / "out")
    model = load_model(summary["model"])
    prediction = predict(model, read.cloud(0), model.actions[0], torch.Generator().manual_seed(0))
    assert torch.isfinite(prediction.final_pose.p).all()
    with pytest.raises(ModelError, match="'mass' and 'ground_friction'"):
        model.condition_on(observations_from_table(read, [0, 1]))
    with pytest.raises(InvalidParameterError, match="'mass' and 'ground_friction'"):  # nor can the residual model
        train_residual_model(model, read.object(read.object_names[0]), read.records)
    # the same pushes with their physics condition from the table's rows directly
    full = load_model(_train(table_path, tmp_path / "full")["model"])
    conditioned = full.condition_on(read_push_table(table_path, make_actions(3), 4.0))
    assert conditioned.physics_posterior.observed + conditioned.physics_posterior.rejected == len(read.records)


def test_the_shipped_table_reads_with_its_flags_inferred_and_trains_from_the_command_line(tmp_path):
    table = read_push_table(SHIPPED / "pushes.parquet", make_actions(3), 4.0)
    assert table.inferred == ("touched", "tipped", "left_ground") and table.object_names == ("lab_prism",)
    assert bool(table.records.valid.all()) and len(table.records) == 36
    summary = _train(SHIPPED / "pushes.parquet", tmp_path / "out", recording=True)
    assert Path(summary["model"]).name == "model.npz" and Path(summary["recording"]).stat().st_size > 0
    assert load_model(summary["model"]).object_name == "lab_prism"


@pytest.mark.parametrize(("edit", "match"), [
    (lambda t: t.drop_columns(["object_final_qz"]), r"missing column 'object_final_qz'"),
    (lambda t: t.set_column(t.column_names.index("speed"), "speed", pa.array(["fast"] * t.num_rows)),
     r"column 'speed' holds string, not numbers"),
    (lambda t: _set(t, "object_final_x", 5, math.nan), r"row 5, column 'object_final_x': NaN or infinite"),
    (lambda t: _set(t, "robot_start_y", 7, math.inf), r"row 7, column 'robot_start_y': NaN or infinite"),
    (lambda t: _set(t, "object_initial_x", 3, 250.0), r"row 3, column 'object_initial_x'.*millimetres"),
    (lambda t: _set(t, "object_final_qw", 2, 0.5), r"row 2, column 'object_final_qw'.*norm"),
    (lambda t: _set(t, "ground_friction", 4, 0.0), r"row 4, column 'ground_friction'.*positive"),
    (lambda t: _set(t, "mass", 6, -1.0), r"row 6, column 'mass'.*positive"),
    (lambda t: _set(t, "action_index", 1, 7), r"row 1, column 'action_index'.*configured actions"),
    (lambda t: _set(t, "yaw_rate", 8, 0.5), r"row 8, column 'yaw_rate'.*configured actions"),
    (lambda t: _set(t, "cloud", 9, "clouds/absent.npz"), r"row 9, column 'cloud'.*not found"),
    (lambda t: t.drop_columns(["mass"]), r"'ground_friction' without 'mass'"),
    (lambda t: t.replace_schema_metadata({**t.schema.metadata, b"pushtorch.pusher": b"point"}),
     r"'point' pusher"),
    (lambda t: t.replace_schema_metadata({k: v for k, v in t.schema.metadata.items() if k != b"pushtorch.robot"}),
     r"names no robot"),
    (lambda t: t.replace_schema_metadata({**t.schema.metadata, b"pushtorch.duration": b"2.0"}), r"last 2 s"),
    (lambda t: t.replace_schema_metadata({**t.schema.metadata, b"pushtorch.meshes": b'{"lab_prism": "x.ply"}'}),
     r"mesh of object 'lab_prism'.*not found"),
])
def test_a_bad_table_is_refused_by_name_and_no_model_is_written(tmp_path, edit, match):
    path = _edit(_copy(tmp_path), edit)
    with pytest.raises(RecordFormatError, match=match):
        _train(path, tmp_path / "out")
    assert not list((tmp_path / "out").glob("*.npz"))


def test_a_cloud_or_mesh_file_that_does_not_load_is_refused(tmp_path):
    path = _copy(tmp_path)
    (path.parent / "clouds" / "start_0.npz").write_bytes(b"not a zip archive")
    with pytest.raises(RecordFormatError, match=r"row 0, column 'cloud'.*could not read"):
        _train(path, tmp_path / "out")
    path = _copy(tmp_path / "again")
    (path.parent / "meshes" / "lab_prism.ply").write_text("ply\nnonsense\n")
    with pytest.raises(RecordFormatError, match=r"mesh of object 'lab_prism'.*could not read"):
        _train(path, tmp_path / "out")
    assert not list((tmp_path / "out").glob("*.npz"))


def test_poses_of_an_off_centre_mesh_frame_become_centre_of_mass_poses(tmp_path):
    """A mesh whose file frame is not its centre of mass: the table's poses are the file frame's, and the records
    hold the centre of mass's, which the mesh loader places at the origin."""
    cube = load_object("cube")
    shift = np.array([0.03, -0.02, 0.05])
    moved = cube.mesh.copy()
    moved.apply_translation(shift)  # the file's frame: the centre of mass sits at +shift
    save_mesh_file(moved, tmp_path / "meshes" / "box.ply")
    obj = load_mesh_file(tmp_path / "meshes" / "box.ply", name="box")
    assert np.allclose(obj.source_origin, shift, atol=1e-9)
    records = read_push_table(SHIPPED / "pushes.parquet").records.take(list(range(4)))
    truth = [se3.from_xy_yaw(0.1 * k, 0.0, 0.3 * k, z=0.1) for k in range(4)]
    p = torch.stack([t.p.reshape(3) for t in truth]).double()
    q = torch.stack([t.q.reshape(4) for t in truth]).double()
    mesh_frame = se3.compose(se3.Pose.unchecked(p, q), se3.Pose.unchecked(-torch.as_tensor(shift).expand(4, 3),
                                                                        torch.tensor([1.0, 0, 0, 0]).expand(4, 4)))
    records = dataclasses.replace(records, object_name=("box",) * 4, object_initial=mesh_frame.to(torch.float32),
                                  object_final=mesh_frame.to(torch.float32))
    write_push_table(tmp_path / "t.parquet", records, "p3dx", 4.0, {"box": "meshes/box.ply"})
    read = read_push_table(tmp_path / "t.parquet")
    assert torch.allclose(read.records.object_initial.p.double(), p, atol=1e-6)


@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-math.pi, math.pi), st.floats(0.0, 0.3),
       st.floats(0.0, 2 * math.pi), st.floats(-0.8, 0.8))
def test_flags_inferred_from_planar_motion_are_never_tipped_or_lifted_and_touched_by_motion(x, y, yaw, step, heading,
                                                                                            turn):
    start = se3.from_xy_yaw(x, y, yaw, z=0.1)
    end = se3.from_xy_yaw(x + step * math.cos(heading), y + step * math.sin(heading), yaw + turn, z=0.1)
    poses = {name: (pose.p.reshape(1, 3).double().numpy(), pose.q.reshape(1, 4).double().numpy())
             for name, pose in (("object_initial", start), ("object_final", end))}
    flags = infer_flags(poses)
    assert not flags["tipped"][0] and not flags["left_ground"][0]
    moved = step > TOUCH_DISTANCE * 1.01 or abs(turn) > 0.0201
    still = step < TOUCH_DISTANCE * 0.99 and abs(turn) < 0.0199
    assert (moved and flags["touched"][0]) or (still and not flags["touched"][0]) or not (moved or still)


def test_a_tipped_or_lifted_object_is_flagged():
    start = se3.from_xy_yaw(0.0, 0.0, 0.0, z=0.1)
    tipped = se3.Pose(torch.tensor([0.2, 0.0, 0.1]), torch.tensor([math.cos(0.15), math.sin(0.15), 0.0, 0.0]))
    lifted = se3.from_xy_yaw(0.2, 0.0, 0.0, z=0.15)
    for end, flag in ((tipped, "tipped"), (lifted, "left_ground")):
        poses = {name: (pose.p.reshape(1, 3).double().numpy(), pose.q.reshape(1, 4).double().numpy())
                 for name, pose in (("object_initial", start), ("object_final", end))}
        assert infer_flags(poses)[flag][0]


@pytest.mark.slow  # 22-25 s: three trainings
def test_a_table_of_two_objects_trains_one_model_each_or_one_pooled_model(tmp_path):
    path = _copy(tmp_path)
    table = pq.read_table(path)
    twin = table.set_column(0, "object_name", pa.array(["lab_twin"] * table.num_rows))
    meta = {**table.schema.metadata, b"pushtorch.meshes": b'{"lab_prism": "meshes/lab_prism.ply", '
                                                          b'"lab_twin": "meshes/lab_prism.ply"}'}
    pq.write_table(pa.concat_tables([table, twin]).replace_schema_metadata(meta), path)
    each = _train(path, tmp_path / "each")
    assert [Path(m["model"]).name for m in each["models"]] == ["model_lab_prism.npz", "model_lab_twin.npz"]
    assert [m["pushes"] for m in each["models"]] == [36, 36]
    pooled = _train(path, tmp_path / "pooled", model={"settings": SMALL, "training_objects": ["lab_prism", "lab_twin"]})
    model = load_model(pooled["model"])
    assert model.meta["pooled"] == ["lab_prism", "lab_twin"] and pooled["pushes"] == 72
    with pytest.raises(InvalidParameterError, match="lab_other"):
        _train(path, tmp_path / "bad", model={"settings": SMALL, "training_objects": ["lab_other"]})
