"""Every bad input is a clear PushtorchError naming the problem, and no partial data passes silently (issue 21).

A parametrised battery over meshes, clouds, actions, poses, model files, push records and folders: each case
asserts the specific error class and a fragment of its message; the tolerable inputs assert a correct
result instead. Then the general properties: any change to a model file is refused (hypothesis), every
``log_prob`` refuses the same queries, two concurrent writers (real processes) never mix shards, and a run
killed at a random point resumes to the records of an uninterrupted run, whatever the shard size and
worker count. Nothing is mocked: real pybullet pushes, real files.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import (
    FolderInUseError,
    IncompleteRunError,
    InvalidMeshError,
    InvalidParameterError,
    InvalidPointCloudError,
    InvalidPoseError,
    PushtorchError,
    RecordFormatError,
    UnsafeNameError,
)
from pushtorch.io import folder_lock, sealed_archive
from pushtorch.kde import KernelBandwidth, PoseKDE, ProductOfExperts, SharedKernelProduct
from pushtorch.models.model import FORMAT, load_model
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_mesh_file, load_object
from pushtorch.paths import contained_path, safe_name
from pushtorch.perception import PointCloud, capture_partial_cloud
from pushtorch.prediction import predict, predict_many
from pushtorch.sim.plan import PushPlan, plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions, place_robot_against
from pushtorch.sim.records import load_records
from pushtorch.sim.run_manifest import run_status
from pushtorch.sim.runner import run_plan, simulate_pushes
from pushtorch.sim.settings import object_spec
from pushtorch.sim.shards import ARRAYS, read_shard, write_shard

ROOT = Path(__file__).resolve().parents[1]
SMALL = ModelSettings(query_kernels=400, anneal_candidates=60, anneal_steps=15, position_frames=800,
                      environment_kernels=300, manipulator_kernels=40)
MASS, FRICTION = Normal(0.5, 0.025), Normal(0.3, 0.05)
PER_ACTION, SHARD = 3, 2  # 9 pushes of 3 actions in 5 shards: action 2's pushes span shards 3 and 4


def _plan(seed: int = 0, per_action: int = PER_ACTION, actions: int = 3) -> PushPlan:
    return plan_training_pushes(load_object("cube"), make_actions(actions), per_action, MASS, FRICTION, seed=seed)


@dataclass
class Env:
    """What the cases share: a finished run, a trained model and its file, a cloud, a scratch folder."""

    run: Path
    model: Any
    model_path: Path
    cloud: PointCloud
    tmp: Path


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    base = tmp_path_factory.mktemp("bad_inputs")
    run = base / "run"
    run_plan(object_spec(load_object("cube")), _plan(), run / "pushes", workers=1, shard_size=SHARD, progress=False)
    model = train_push_model(load_object("cube"), load_records(run), SMALL, generator=0)
    model_path = model.save(base / "model.npz")
    cube = load_object("cube")
    return run, model, model_path, capture_partial_cloud(cube, cube.resting_pose(yaw=0.2))


@pytest.fixture
def env(shared, tmp_path) -> Env:
    run, model, model_path, cloud = shared
    return Env(run, model, model_path, cloud, tmp_path)


# --- helpers that write bad files ------------------------------------------------------------------


def _model_parts(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    with np.load(path, allow_pickle=False) as archive:
        arrays = {k: archive[k] for k in archive.files}
    return json.loads(arrays.pop("__header__").tobytes().decode()), arrays


def _header_bytes(header: Any) -> np.ndarray:
    return np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)


def _sealed(header: Any, arrays: dict[str, np.ndarray]) -> bytes:
    """A model file's bytes as the library writes them: ``np.savez`` of the header and arrays, sealed."""
    buffer = io.BytesIO()
    np.savez(buffer, __header__=_header_bytes(header), **arrays)
    return sealed_archive(buffer.getvalue())


def _resaved(env: Env, edit, sealed: bool = True) -> Path:
    """The model file with ``edit(header, arrays)`` applied, written sealed (as by an author who knows the
    format: checks beyond the seal) or as ``np.savez`` writes it (as a user editing the file would)."""
    header, arrays = _model_parts(env.model_path)
    header = edit(header, arrays) or header
    out = env.tmp / "edited.npz"
    if sealed:
        out.write_bytes(_sealed(header, arrays))
    else:
        np.savez(out, __header__=_header_bytes(header), **arrays)
    return out


def _set(header: dict, key: str, value) -> dict:
    header[key] = value
    return header


def _copy_run(env: Env) -> Path:
    run = env.tmp / "run"
    shutil.copytree(env.run, run)
    return run / "pushes"


def _shard_arrays(env: Env, k: int = 0) -> dict[str, np.ndarray]:
    return {name: np.array(a) for name, a in read_shard(env.run / "pushes" / f"shard-{k:06d}.json").items()}


def _write_obj(path: Path, vertices, faces) -> Path:
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return path


def _two_cubes(env: Env) -> Path:
    a = trimesh.creation.box((0.1, 0.1, 0.1))
    b = a.copy()
    b.apply_translation([1.0, 0.0, 0.0])
    path = env.tmp / "two.stl"
    trimesh.util.concatenate([a, b]).export(path)
    return path


def _two_boxes(env: Env, gap: float) -> Path:
    """Two 0.1 m boxes ``gap`` m apart in one file."""
    a = trimesh.creation.box((0.1, 0.1, 0.1))
    b = a.copy()
    b.apply_translation([0.1 + gap, 0.0, 0.0])
    path = env.tmp / "apart.obj"
    trimesh.util.concatenate([a, b]).export(path)
    return path


def _loose_triangles(env: Env, count: int = 300) -> Path:
    """``count`` separate triangles (a soup, not a solid) within 0.3 m."""
    corners = np.random.default_rng(0).uniform(0.0, 0.3, (count, 1, 3)) + [[0, 0, 0], [0.005, 0, 0], [0, 0.005, 0]]
    return _write_obj(env.tmp / "soup.obj", corners.reshape(-1, 3), np.arange(3 * count).reshape(-1, 3))


def _cube_mm(env: Env) -> Path:
    """A 0.2 m cube written in millimetres."""
    path = env.tmp / "cube_mm.stl"
    trimesh.creation.box((200.0, 200.0, 200.0)).export(path)
    return path


def _nan_mesh(env: Env) -> Path:
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    vertices = np.array(box.vertices)
    vertices[3, 1] = np.nan
    return _write_obj(env.tmp / "nan.obj", vertices, box.faces)


def _l_shape(env: Env, name: str = "l shape (v2).obj") -> Path:
    a = trimesh.creation.box((0.2, 0.1, 0.1))
    b = trimesh.creation.box((0.1, 0.1, 0.1))
    b.apply_translation([0.05, 0.1, 0.0])
    path = env.tmp / name
    a.union(b).export(path)
    return path


def _sim_pushes(env: Env, object_pose: se3.Pose, robot_pose: se3.Pose | None = None):
    cube = load_object("cube")
    robot = robot_pose if robot_pose is not None else place_robot_against(cube.mesh, object_pose)
    return simulate_pushes(cube, robot, object_pose, torch.tensor([0.1, 0.0]), 0.5, 0.3)


def _locked_run(env: Env):
    folder = env.tmp / "locked"
    folder.mkdir()
    with folder_lock(folder):  # as a live run holds it
        run_plan(object_spec(load_object("cube")), _plan(per_action=1, actions=1), folder, workers=1,
                 progress=False)


# --- the battery -------------------------------------------------------------------------------------

BAD = [
    # meshes
    ("mesh_missing", lambda e: load_mesh_file(e.tmp / "absent.stl"), InvalidMeshError, "not found"),
    ("mesh_not_a_mesh", lambda e: load_mesh_file(_text(e.tmp / "junk.stl", "solid nonsense\n")), InvalidMeshError,
     "mesh"),
    ("mesh_nan_vertex", lambda e: load_mesh_file(_nan_mesh(e)), InvalidMeshError, "NaN"),
    ("mesh_two_bodies", lambda e: load_mesh_file(_two_cubes(e)), InvalidMeshError, "2 disjoint bodies"),
    ("mesh_bodies_5cm_apart", lambda e: load_mesh_file(_two_boxes(e, 0.05)), InvalidMeshError,
     "2 disjoint bodies 50.0 mm apart"),
    ("mesh_in_millimetres", lambda e: load_mesh_file(_cube_mm(e)), InvalidMeshError,
     "object.scale=0.001 would make it 0.2 m (0.001 if the file is in millimetres)"),
    ("mesh_scaled_too_small", lambda e: load_object("mesh", _cube_mm(e), scale=1e-6), InvalidMeshError,
     "0.2 mm across"),
    ("mesh_loose_triangles", lambda e: load_mesh_file(_loose_triangles(e)), InvalidMeshError,
     "holds 300 separate parts; at most 256"),
    ("mesh_up_x", lambda e: load_object("mesh", _l_shape(e), up="x"), InvalidParameterError,
     "object.up must be one of z, y"),
    ("mesh_open_flat", lambda e: load_mesh_file(_write_obj(e.tmp / "flat.obj", [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                                                           [[0, 1, 2]])), InvalidMeshError, "open and flat"),
    ("mesh_scale_zero", lambda e: load_mesh_file(_l_shape(e), scale=0), InvalidParameterError, "scale"),
    ("mesh_scale_text", lambda e: load_mesh_file(_l_shape(e), scale="abc"), InvalidParameterError, "scale"),
    ("mesh_path_unset", lambda e: load_object("mesh", "???"), InvalidParameterError, "object.path is not set"),
    ("mesh_unknown_catalogue", lambda e: load_object("sphere"), InvalidParameterError, "unknown object"),
    ("mesh_unsafe_name", lambda e: load_mesh_file(_l_shape(e), name="a/../../outside"), UnsafeNameError,
     "cannot be part of a file name"),
    # clouds
    ("cloud_empty", lambda e: PointCloud(torch.zeros(0, 3)), InvalidPointCloudError, "empty"),
    ("cloud_nan", lambda e: PointCloud(torch.tensor([[0.0, 0.0, float("nan")]] * 10)), InvalidPointCloudError,
     "NaN"),
    ("cloud_shape", lambda e: PointCloud(torch.zeros(10, 2)), InvalidPointCloudError, "shape"),
    ("cloud_nan_to_predict", lambda e: predict(e.model, torch.full((50, 3), float("nan")), e.model.actions[0], 0),
     InvalidPointCloudError, "NaN"),
    ("cloud_too_sparse", lambda e: predict(e.model, torch.rand(4, 3, dtype=torch.float64), e.model.actions[0], 0),
     InvalidPointCloudError, "point"),
    # actions and generators
    ("action_nan_speed", lambda e: predict(e.model, e.cloud, [float("nan"), 0.0], 0), InvalidParameterError,
     "finite"),
    ("action_nan_rate", lambda e: predict(e.model, e.cloud, [0.1, float("nan")], 0), InvalidParameterError,
     "finite"),
    ("action_inf", lambda e: e.model.action_index([math.inf, 0.0]), InvalidParameterError, "finite"),
    ("action_three_numbers", lambda e: predict(e.model, e.cloud, [0.1, 0.0, 0.0], 0), InvalidParameterError,
     "two real numbers"),
    ("action_text", lambda e: predict(e.model, e.cloud, "fast", 0), InvalidParameterError, "two numbers"),
    ("action_unknown", lambda e: predict(e.model, e.cloud, [0.5, 0.0], 0), InvalidParameterError,
     "not trained for action"),
    ("actions_count", lambda e: predict_many(e.model, [e.cloud] * 3, e.model.actions[:2]), InvalidParameterError,
     "2 actions for 3 clouds"),
    ("generator_text", lambda e: predict(e.model, e.cloud, e.model.actions[0], "seed"), InvalidParameterError,
     "generator must be"),
    ("generator_negative", lambda e: predict(e.model, e.cloud, e.model.actions[0], -1), InvalidParameterError,
     "seed must be"),
    # poses
    ("pose_nan", lambda e: se3.check_pose(se3.Pose(torch.tensor([math.nan, 0, 0]), torch.tensor([1.0, 0, 0, 0]))),
     InvalidPoseError, "NaN"),
    ("pose_q_norm_3", lambda e: se3.check_pose(se3.Pose(torch.zeros(3), torch.tensor([3.0, 0, 0, 0]))),
     InvalidPoseError, "unit quaternion"),
    ("pose_q_shape", lambda e: se3.check_pose(se3.Pose(torch.zeros(3), torch.tensor([1.0, 0, 0]))),
     InvalidPoseError, "shape"),
    ("plan_nan_object_pose", lambda e: _sim_pushes(e, se3.Pose.unchecked(torch.tensor([math.nan, 0, 0.1]),
                                                                          torch.tensor([1.0, 0, 0, 0])),
                                                    se3.identity()), InvalidParameterError, "NaN"),
    ("object_beyond_ground", lambda e: _sim_pushes(e, load_object("cube").resting_pose(60.0, 0.0)),
     InvalidParameterError, "leaves the simulated ground"),
    ("object_below_ground", lambda e: _sim_pushes(e, se3.from_xy_yaw(0.0, 0.0, 0.0, z=0.0),
                                                  place_robot_against(load_object("cube").mesh,
                                                                      load_object("cube").resting_pose())),
     InvalidParameterError, "below the ground"),
    ("robot_beyond_ground", lambda e: _sim_pushes(e, load_object("cube").resting_pose(),
                                                  se3.from_xy_yaw(49.9, 0.0, 0.0)),
     InvalidParameterError, "starts the robot"),
    # model files
    ("model_missing", lambda e: load_model(e.tmp / "absent.npz"), RecordFormatError, "not a readable"),
    ("model_junk", lambda e: load_model(_bytes(e.tmp / "junk.npz", b"not a zip file")), RecordFormatError,
     "not a pushtorch model file"),
    ("model_is_a_shard", lambda e: load_model(sorted((e.run / "pushes").glob("shard-*.npz"))[0]), RecordFormatError,
     "without a model header"),
    ("records_from_a_model_file", lambda e: load_records(e.model_path), RecordFormatError,
     "is not a push-record shard"),
    ("records_missing_folder", lambda e: load_records(e.tmp / "nowhere"), RecordFormatError, "does not exist"),
    ("mesh_is_a_folder", lambda e: load_mesh_file(e.tmp), InvalidMeshError, "is a folder"),
    ("model_truncated", lambda e: load_model(_bytes(e.tmp / "cut.npz", e.model_path.read_bytes()[:-1000])),
     RecordFormatError, "checksum"),
    ("model_old_version", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "version", 2), sealed=False)),
     RecordFormatError, "version 2"),
    # a model trained before issue 17 (no contact patches, paper bandwidths) is refused, sealed or not
    ("model_before_contact_patches", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "version", 3))),
     RecordFormatError, "version 3, this pushtorch reads version 5: retrain"),
    # a model whose kernels do not know their push's friction and mass (before online adaptation) is refused
    ("model_before_kernel_physics", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "version", 4))),
     RecordFormatError, "version 4, this pushtorch reads version 5: retrain"),
    ("model_array_edited", lambda e: load_model(_resaved(e, lambda h, a: a.update(
        {"contact.weight": a["contact.weight"] * 0.5}), sealed=False)), RecordFormatError, "checksum"),
    ("model_action_count_edited", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "actions", 1),
                                                                sealed=False)), RecordFormatError, "checksum"),
    ("model_setting_edited", lambda e: load_model(_resaved(e, lambda h, a: h["settings"].update(
        motion_p_std=0.02), sealed=False)), RecordFormatError, "checksum"),
    ("model_sealed_action_count", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "actions", 1))),
     RecordFormatError, "action count"),
    ("model_sealed_bad_setting", lambda e: load_model(_resaved(e, lambda h, a: h["settings"].update(
        anneal_steps=-3))), RecordFormatError, "anneal_steps"),
    ("model_sealed_fractional_count", lambda e: load_model(_resaved(e, lambda h, a: h["settings"].update(
        position_frames=2.5))), RecordFormatError, "integer"),
    ("model_sealed_unknown_setting", lambda e: load_model(_resaved(e, lambda h, a: h["settings"].update(
        typo=1.0))), RecordFormatError, "unknown model settings"),
    ("model_sealed_no_name", lambda e: load_model(_resaved(e, lambda h, a: h.pop("name") and None)),
     RecordFormatError, "malformed"),
    ("model_sealed_contact_list", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "contact", [1, 2]))),
     RecordFormatError, "malformed"),
    ("model_sealed_name_number", lambda e: load_model(_resaved(e, lambda h, a: _set(h, "name", 7))),
     RecordFormatError, "malformed"),
    ("model_sealed_array_digest", lambda e: load_model(_resaved(e, lambda h, a: a.update(
        {"contact.weight": a["contact.weight"] * 0.5}))), RecordFormatError, "fails its checksum"),
    # push records
    ("records_unfinished", lambda e: load_records(_drop(_copy_run(e), 3)), IncompleteRunError, "Resume it"),
    ("records_missing_action", lambda e: load_records(_drop(_drop(_copy_run(e), 3), 4)), IncompleteRunError,
     "action 2 has no push"),
    ("records_extra_shard", lambda e: load_records(_duplicate(_copy_run(e), 0, 7)), RecordFormatError,
     "beyond the 5 shards"),
    ("records_moved_shard", lambda e: load_records(_duplicate(_copy_run(e), 1, 2)), RecordFormatError,
     "duplicated or moved"),
    ("records_nan_pose", lambda e: read_shard(write_shard(e.tmp, 0, _edit(_shard_arrays(e), "object_final_p",
                                                                             math.nan))), RecordFormatError, "NaN"),
    ("records_non_unit_q", lambda e: read_shard(write_shard(e.tmp, 0, _edit(_shard_arrays(e), "object_final_q",
                                                                               3.0))), RecordFormatError,
     "not unit length"),
    ("records_tampered", lambda e: load_records(_tamper(_copy_run(e), 1)), RecordFormatError, "SHA-256"),
    ("records_empty_folder", lambda e: load_records(_mkdir(e.tmp / "empty")), RecordFormatError, "no finished"),
    ("records_other_run", lambda e: run_plan(object_spec(load_object("cube")), _plan(seed=1), _copy_run(e),
                                             workers=1, shard_size=SHARD, progress=False), RecordFormatError,
     "different run"),
    # folders and names
    ("folder_in_use", _locked_run, FolderInUseError, "being written by"),
    ("name_escapes", lambda e: contained_path(e.tmp, "data", "a/../../outside/p"), UnsafeNameError,
     "cannot be part of a file name"),
    ("name_dots", lambda e: safe_name("..", "prior name"), UnsafeNameError, "prior name"),
    ("name_not_text", lambda e: safe_name(3, "object name"), UnsafeNameError, "must be a string"),
]


def _text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _drop(folder: Path, k: int) -> Path:
    """A killed run: shard ``k``'s manifest never written (its data may be there)."""
    (folder / f"shard-{k:06d}.json").unlink()
    return folder


def _duplicate(folder: Path, k: int, into: int) -> Path:
    """Shard ``k`` copied over (or beyond) shard ``into``, both files."""
    for suffix in (".json", ".npz"):
        shutil.copy(folder / f"shard-{k:06d}{suffix}", folder / f"shard-{into:06d}{suffix}")
    manifest = json.loads((folder / f"shard-{into:06d}.json").read_text())
    manifest["npz"] = f"shard-{into:06d}.npz"
    (folder / f"shard-{into:06d}.json").write_text(json.dumps(manifest))
    return folder


def _tamper(folder: Path, k: int) -> Path:
    path = folder / f"shard-{k:06d}.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    return folder


def _edit(arrays: dict[str, np.ndarray], name: str, value: float) -> dict[str, np.ndarray]:
    arrays[name][0, 0] = value
    return arrays


@pytest.mark.parametrize("case, error, fragment", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_input_is_a_clear_error(env, case, error, fragment):
    with pytest.raises(error) as caught:
        case(env)
    assert isinstance(caught.value, PushtorchError)
    assert fragment in str(caught.value), str(caught.value)


def test_battery_has_at_least_40_cases():
    assert len(BAD) >= 40


# --- tolerable inputs: a correct result ----------------------------------------------------------------


def test_float64_cloud_and_int_seed_predict_as_float32_and_a_generator(env):
    reference = predict(env.model, env.cloud, env.model.actions[1], torch.Generator().manual_seed(3))
    cast = predict(env.model, PointCloud(env.cloud.points.double(), env.cloud.view_origins.double()),
                   env.model.actions[1].double().tolist(), 3)
    assert torch.equal(reference.final_pose.p, cast.final_pose.p)
    assert torch.equal(reference.final_pose.q, cast.final_pose.q)


def test_an_empty_batch_predicts_nothing(env):
    """``predict_many`` of no clouds is no predictions, as ``map`` over nothing (it used to blame the actions)."""
    assert predict_many(env.model, [], []) == []
    assert predict_many(env.model, [], torch.zeros(0, 2), batch_size=8) == []


def test_a_concave_mesh_is_simulated_as_its_convex_decomposition(env):
    obj = load_mesh_file(_l_shape(env), cache_dir=env.tmp / "cache")
    assert obj.name == "l_shape_v2_"  # the file's stem, fit for a file name
    assert obj.collision_source == "v-hacd" and len(obj.collision_parts) >= 2
    hull_volume = obj.mesh.convex_hull.volume
    parts_volume = sum(p.volume for p in obj.collision_parts)
    assert abs(parts_volume - obj.mesh.volume) < 0.5 * (hull_volume - obj.mesh.volume)  # not the hull
    assert list((env.tmp / "cache").glob("vhacd-*.obj"))  # kept where the user named
    again = load_mesh_file(_l_shape(env, "copy.obj"), cache_dir=env.tmp / "cache")
    assert [p.vertices.tolist() for p in again.collision_parts] == [p.vertices.tolist() for p in obj.collision_parts]
    # it rests and is pushed as one body
    records = simulate_pushes(obj, place_robot_against(obj.mesh, obj.resting_pose()), obj.resting_pose(),
                              torch.tensor([0.1, 0.0]), 0.5, 0.3, duration=2.0)
    assert bool(records.touched) and not bool(records.tipped | records.left_ground)
    assert float(records.object_final.p[0, 0]) > 0.05


def test_training_on_part_of_a_run_needs_the_flag_and_is_recorded(env):
    from pushtorch.apps.train import train_from_config

    folder = _drop(_copy_run(env), 4)
    status = run_status(folder)
    assert not status.complete and status.missing_pushes == 1 and status.missing_by_action == {2: 1}
    cfg = {"object": {"name": "cube"}, "data": str(folder.parent), "seed": 0, "recording": False,
           "model": {"settings": {k: getattr(SMALL, k) for k in ("query_kernels", "position_frames")}}}
    with pytest.raises(IncompleteRunError, match="allow_partial"):
        train_from_config(cfg, env.tmp / "out")
    summary = train_from_config({**cfg, "allow_partial": True}, env.tmp / "out")
    assert summary["pushes"] == 8 and summary["partial_data"]["missing_pushes"] == 1
    assert load_model(env.tmp / "out" / "model.npz").partial_data["missing_by_action"] == {"2": 1}
    assert load_model(env.model_path).partial_data is None


def test_open3d_without_its_system_library_names_the_install_command(tmp_path):
    # a stand-in open3d package that fails as the real one does where libusb-1.0 is missing
    fake = tmp_path / "open3d"
    fake.mkdir()
    (fake / "__init__.py").write_text(
        "raise OSError('libusb-1.0.so.0: cannot open shared object file: No such file or directory')\n")
    code = textwrap.dedent("""
        from pushtorch.deps import import_open3d
        from pushtorch.errors import MissingDependencyError
        try:
            import_open3d()
        except MissingDependencyError as exc:
            print(exc)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)])))
    assert "libusb-1.0" in out.stdout and "apt-get install -y libusb-1.0-0" in out.stdout, out.stdout + out.stderr
    assert len(out.stdout.strip().splitlines()) == 1


def test_a_killed_save_leaves_temporaries_the_next_save_removes(env):
    orphan = env.tmp / ".model.npz.tmp-99999-deadbeef"
    orphan.write_bytes(b"half a model")
    env.model.save(env.tmp / "model.npz")
    assert not orphan.exists() and load_model(env.tmp / "model.npz").name == env.model.name


# --- any change to a model file is refused -------------------------------------------------------------


@given(position=st.floats(0.0, 1.0, exclude_max=True), flip=st.integers(1, 255))
def test_any_changed_byte_of_a_model_file_is_refused(shared, tmp_path_factory, position, flip):
    _, _, model_path, _ = shared
    data = bytearray(model_path.read_bytes())
    data[int(position * len(data))] ^= flip
    path = tmp_path_factory.mktemp("flip") / "model.npz"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordFormatError):
        load_model(path)


_HEADER_EDITS = st.sampled_from(["name", "object_name", "actions", "meta", "partial_data", "contact", "settings",
                                 "version", "format"])


@given(key=_HEADER_EDITS, value=st.one_of(st.integers(-3, 5), st.text(max_size=5), st.none(),
                                          st.floats(allow_nan=True), st.lists(st.integers(), max_size=2)),
       setting=st.booleans())
def test_any_edited_header_field_is_refused(shared, tmp_path_factory, key, value, setting):
    _, _, model_path, _ = shared
    header, arrays = _model_parts(model_path)
    if setting:
        header["settings"]["contact_cutoff"] = value
    elif header.get(key) == value:
        return  # no edit
    else:
        header[key] = value
    path = tmp_path_factory.mktemp("edit") / "model.npz"
    buffer = io.BytesIO()
    np.savez(buffer, __header__=_header_bytes(header), **arrays)  # how a hand-edited file is saved
    path.write_bytes(buffer.getvalue())
    with pytest.raises(RecordFormatError):
        load_model(path)


def test_a_model_file_of_another_format_is_named(env):
    header, arrays = _model_parts(env.model_path)
    header["format"] = "someone.else"
    path = env.tmp / "other.npz"
    path.write_bytes(_sealed(header, arrays))
    with pytest.raises(RecordFormatError, match=f"not a {FORMAT}"):
        load_model(path)


# --- every log_prob refuses the same queries ------------------------------------------------------------

# built unchecked: what reaches a density when a caller's tensors bypass Pose(p, q)'s own check
_BAD_QUERIES = {
    "nan_position": se3.Pose.unchecked(torch.tensor([[math.nan, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]])),
    "inf_position": se3.Pose.unchecked(torch.tensor([[math.inf, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]])),
    "nan_quaternion": se3.Pose.unchecked(torch.zeros(1, 3), torch.tensor([[math.nan, 0, 0, 0]])),
    "quaternion_norm_3": se3.Pose.unchecked(torch.zeros(1, 3), torch.tensor([[3.0, 0, 0, 0]])),
    "zero_quaternion": se3.Pose.unchecked(torch.zeros(1, 3), torch.zeros(1, 4)),
    "xyz_quaternion": se3.Pose.unchecked(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0]])),
}


@pytest.fixture(scope="module")
def densities(shared):
    _, model, _, cloud = shared
    g = torch.Generator().manual_seed(0)
    bandwidth = KernelBandwidth(p_std=0.05, rot_std=0.3)
    means = se3.Pose(0.05 * torch.randn(2, 30, 3, generator=g), se3.random_quaternion((2, 30), g))
    kde = PoseKDE(means, bandwidth)
    product = ProductOfExperts(kde)
    shared_product = SharedKernelProduct(se3.Pose(means.p[0], means.q[0]), torch.zeros(2, 30), bandwidth)
    motion = predict(model, cloud, model.actions[0], 0).motion_density
    return {
        "PoseKDE.dense": lambda pose: kde.log_prob(pose, method="dense"),
        "PoseKDE.fast": lambda pose: kde.log_prob(pose, method="fast"),
        "ProductOfExperts.dense": lambda pose: product.log_prob(pose, method="dense"),
        "ProductOfExperts.fast": lambda pose: product.log_prob(pose, method="fast"),
        "SharedKernelProduct": shared_product.log_prob,
        "MotionDensity.dense": lambda pose: motion.log_prob(pose, method="dense"),
        "MotionDensity.fast": lambda pose: motion.log_prob(pose, method="fast"),
    }


_DENSITIES = ["PoseKDE.dense", "PoseKDE.fast", "ProductOfExperts.dense", "ProductOfExperts.fast",
              "SharedKernelProduct", "MotionDensity.dense", "MotionDensity.fast"]


@pytest.mark.parametrize("query", list(_BAD_QUERIES))
def test_every_log_prob_refuses_the_same_queries(densities, query):
    pose = _BAD_QUERIES[query]
    for name in _DENSITIES:
        with pytest.raises(InvalidPoseError):
            densities[name](pose)
    good = se3.Pose(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]))
    for name in _DENSITIES:  # and all take a valid one
        assert densities[name](good).shape[-1] == 1, name


# --- two concurrent writers never mix shards ------------------------------------------------------------

_WRITER = """
import sys, time
from pathlib import Path
from pushtorch.errors import PushtorchError
from pushtorch.objects import load_object
from pushtorch.sim.plan import plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions
from pushtorch.sim.runner import run_plan
from pushtorch.sim.settings import object_spec

seed, folder, go = int(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
cube = load_object("cube")
plan = plan_training_pushes(cube, make_actions(1), 3, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=seed)
spec = object_spec(cube)
while not go.exists():  # both start together
    time.sleep(0.001)
try:
    run_plan(spec, plan, folder, workers=1, shard_size=1, progress=False)
except PushtorchError as exc:
    print(type(exc).__name__, exc)
    sys.exit(2)
"""


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def test_two_concurrent_writers_never_mix_shards(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(_WRITER)
    for round_ in range(2):
        folder, go = tmp_path / f"pushes{round_}", tmp_path / f"go{round_}"
        writers = [subprocess.Popen([sys.executable, str(script), str(seed), str(folder), str(go)], env=_env(),
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
                   for seed in (10 + round_, 20 + round_)]
        time.sleep(3.0)  # both have imported and wait at the start line
        go.touch()
        outcomes = [(w.wait(timeout=300), w.stdout.read()) for w in writers]
        codes = sorted(code for code, _ in outcomes)
        assert codes == [0, 2], outcomes  # exactly one run owns the folder
        refused = next(text for code, text in outcomes if code == 2)
        assert "FolderInUseError" in refused or "different run" in refused, refused
        records = load_records(folder)  # checked against the one manifest
        manifest = json.loads((folder / "manifest.json").read_text())
        assert len(records) == 3 and set(records.seed.tolist()) == {manifest["seed"]}


# --- resume invariance over kill points, shard sizes and worker counts ----------------------------------

_KILLED = """
import sys
from pushtorch.objects import load_object
from pushtorch.sim.plan import plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions
from pushtorch.sim.runner import run_plan
from pushtorch.sim.settings import object_spec

folder, shard_size, workers = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
cube = load_object("cube")
plan = plan_training_pushes(cube, make_actions(3), 4, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=7)
run_plan(object_spec(cube), plan, folder, workers=workers, shard_size=shard_size, progress=False)
"""


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 4, MASS, FRICTION, seed=7)
    folder = tmp_path_factory.mktemp("whole")
    run_plan(object_spec(cube), plan, folder, workers=1, shard_size=12, progress=False)
    return plan, load_records(folder, dtype=torch.float64)


@pytest.mark.parametrize("shard_size, workers, resume_workers, kill_after", [
    (1, 2, 1, 0.3),
    pytest.param(3, 1, 2, 0.0, marks=pytest.mark.slow),
    pytest.param(5, 2, 2, 0.6, marks=pytest.mark.slow),
])
def test_a_run_killed_at_any_point_resumes_to_the_uninterrupted_records(tmp_path, uninterrupted, shard_size,
                                                                         workers, resume_workers, kill_after):
    plan, whole = uninterrupted
    script = tmp_path / "run.py"
    script.write_text(_KILLED)
    folder = tmp_path / "pushes"
    # its own process group, so the kill takes its pool workers too (else they finish their shard)
    process = subprocess.Popen([sys.executable, str(script), str(folder), str(shard_size), str(workers)],
                               env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    deadline = time.monotonic() + 120
    while not list(folder.glob("shard-*.json")) and process.poll() is None:
        assert time.monotonic() < deadline, "no shard after 120 s"
        time.sleep(0.002)
    time.sleep(kill_after)  # a kill point after the first shard, mid-run
    if process.poll() is None:
        os.killpg(process.pid, 9)
    process.wait()
    status = run_status(folder)
    if not status.complete:
        with pytest.raises(IncompleteRunError, match="unfinished run"):
            load_records(folder)
    summary = run_plan(object_spec(load_object("cube")), plan, folder, workers=resume_workers,
                       shard_size=shard_size, progress=False)
    assert summary.resumed_shards == len(status.finished)
    assert not list(folder.glob(".shard-*"))
    resumed = load_records(folder, dtype=torch.float64)
    for name in ARRAYS:  # identical records, interrupted or not, any shard size and worker count
        if name == "object_name":
            assert resumed.object_name == whole.object_name
            continue
        a = getattr(resumed, name.removesuffix("_p").removesuffix("_q"))
        b = getattr(whole, name.removesuffix("_p").removesuffix("_q"))
        if isinstance(a, se3.Pose):
            assert torch.equal(a.p, b.p) and torch.equal(a.q, b.q), name
        elif a.is_floating_point():
            assert torch.equal(a.nan_to_num(-1.0), b.nan_to_num(-1.0)), name
        else:
            assert torch.equal(a, b), name
