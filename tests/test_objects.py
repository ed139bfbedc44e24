"""The object catalogue and user meshes (pushtorch.objects): sizes, centre, symmetries, resting, loading."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidMeshError, InvalidParameterError, PushtorchError
from pushtorch.objects import catalogue_names, load_mesh_file, load_object

EXPECTED_DIMENSIONS = {
    "cube": (0.2, 0.2, 0.2),
    "prism_thin": (0.1, 0.2, 0.2),
    "prism_long": (0.3, 0.2, 0.2),
    "cylinder": (0.2, 0.2, 0.2),
    "cylinder_wide": (0.3, 0.3, 0.2),
    "hybrid": (0.2, 0.2, 0.2),
    "modified_cube": (0.2, 0.2, 0.2),
}
EXPECTED_GROUP_ORDER = {
    "cube": 24,
    "prism_thin": 8,
    "prism_long": 8,
    "hybrid": 2,
    "modified_cube": 3,
    "cylinder": math.inf,
    "cylinder_wide": math.inf,
}


def test_catalogue_lists_the_papers_seven_objects():
    assert sorted(catalogue_names()) == sorted(EXPECTED_DIMENSIONS)


@pytest.mark.parametrize("name", sorted(EXPECTED_DIMENSIONS))
def test_catalogue_object_has_the_papers_dimensions(name):
    obj = load_object(name)
    assert torch.allclose(obj.dimensions, torch.tensor(EXPECTED_DIMENSIONS[name]), atol=1e-6)
    assert obj.dimensions.dtype == torch.float32


@pytest.mark.parametrize("name", sorted(EXPECTED_DIMENSIONS))
def test_catalogue_mesh_is_watertight_with_its_centre_of_mass_at_the_origin(name):
    mesh = load_object(name).mesh
    assert mesh.is_watertight
    assert mesh.volume > 0
    assert np.allclose(mesh.center_mass, 0.0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(EXPECTED_DIMENSIONS))
def test_collision_parts_are_convex_and_fill_the_mesh(name):
    obj = load_object(name)
    assert all(part.is_convex for part in obj.collision_parts)
    # the parts tile the object: their volumes add up to its volume (no gaps, no overlaps)
    assert sum(part.volume for part in obj.collision_parts) == pytest.approx(obj.mesh.volume, rel=1e-6)


@pytest.mark.parametrize("name", sorted(EXPECTED_GROUP_ORDER))
def test_symmetry_group_has_the_expected_size(name):
    symmetry = load_object(name).symmetry
    assert symmetry.order == EXPECTED_GROUP_ORDER[name]
    assert symmetry.continuous_z == (name.startswith("cylinder"))
    assert torch.allclose(symmetry.discrete[0], torch.tensor([1.0, 0.0, 0.0, 0.0]))  # identity first


@pytest.mark.parametrize("name", sorted(EXPECTED_GROUP_ORDER))
def test_every_listed_symmetry_maps_the_mesh_onto_itself(name, rotated_surface_gap):
    obj = load_object(name)
    for q in obj.symmetry.discrete:
        assert rotated_surface_gap(obj.mesh, q) < 1e-4, f"{name}: {q.tolist()} is not a symmetry"


@pytest.mark.parametrize("name", ["cube", "prism_thin", "hybrid", "modified_cube"])
def test_symmetry_group_is_closed_under_composition(name):
    group = load_object(name).symmetry.discrete
    products = pkt.quaternion_raw_multiply(group.unsqueeze(1), group.unsqueeze(0)).reshape(-1, 4)
    # every product equals some element up to sign
    alignment = (products.unsqueeze(1) * group.unsqueeze(0)).sum(-1).abs().amax(-1)
    assert torch.all(alignment > 1 - 1e-5)


@pytest.mark.parametrize(
    ("name", "axis_angle"),
    [
        ("prism_thin", (0.0, 0.0, math.pi / 2)),  # swaps the 0.1 and 0.2 sides
        ("hybrid", (0.0, 0.0, math.pi)),  # sends the round back to the apex
        ("modified_cube", (0.0, 0.0, math.pi / 2)),  # moves the notch to another corner
        ("cube", (0.0, 0.0, math.pi / 4)),
    ],
)
def test_a_rotation_that_changes_the_look_is_not_in_the_group(name, axis_angle, rotated_surface_gap):
    obj = load_object(name)
    q = pkt.axis_angle_to_quaternion(torch.tensor(axis_angle))
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0])
    assert rotated_surface_gap(obj.mesh, q) > 5e-3  # the rotation really changes the shape's look...
    assert obj.symmetry.canonical_distance(q, identity) > 1e-2  # ...and the measure tells it apart


@settings(max_examples=20, deadline=None)
@given(
    angle=st.floats(-math.pi, math.pi),
    flip=st.booleans(),
    name=st.sampled_from(["cylinder", "cylinder_wide"]),
)
def test_cylinder_is_invariant_to_any_rotation_about_its_axis(angle, flip, name, rotated_surface_gap):
    obj = load_object(name)
    q = pkt.axis_angle_to_quaternion(torch.tensor([0.0, 0.0, angle], dtype=torch.float64))
    if flip:  # the half turn about x is in the group as well
        q = pkt.quaternion_raw_multiply(q, torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    # 96 facets: the polygon deviates from the circle by R (1 - cos(pi / 96)) < 0.1 mm
    assert rotated_surface_gap(obj.mesh, q.float()) < 2e-4
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0])
    assert obj.symmetry.canonical_distance(q.float(), identity) < 1e-6


def test_modified_cube_misses_one_sixteenth_of_the_cube():
    obj = load_object("modified_cube")
    assert obj.mesh.volume == pytest.approx(15 / 16 * 0.2**3, rel=1e-6)
    # the notch is at the (+x, +y, +z) corner: the point just inside that corner of the bounding box is
    # outside the object, the opposite corner is inside
    lo, hi = obj.mesh.bounds
    probe = np.array([hi - 0.005, lo + 0.005])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(obj.mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(obj.mesh.faces, np.uint32)),
    )
    occupancy = scene.compute_occupancy(o3d.core.Tensor(probe.astype(np.float32))).numpy()
    assert occupancy.tolist() == [0.0, 1.0]


@settings(max_examples=25, deadline=None)
@given(
    name=st.sampled_from(sorted(EXPECTED_DIMENSIONS)),
    x=st.floats(-2.0, 2.0),
    y=st.floats(-2.0, 2.0),
    yaw=st.floats(-math.pi, math.pi),
)
def test_resting_pose_stands_the_object_on_the_ground(name, x, y, yaw):
    obj = load_object(name)
    pose = obj.resting_pose(x, y, yaw)
    vertices = se3.apply(pose, torch.as_tensor(np.asarray(obj.mesh.vertices), dtype=torch.float32))
    assert vertices[:, 2].min().item() == pytest.approx(0.0, abs=1e-6)
    assert vertices[:, 2].max().item() == pytest.approx(float(obj.dimensions[2]), abs=1e-5)
    assert torch.allclose(pose.p[:2], torch.tensor([x, y]), atol=1e-6)
    heading = pkt.quaternion_apply(pose.q, torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(heading, torch.tensor([math.cos(yaw), math.sin(yaw), 0.0]), atol=1e-5)


def _off_centre_box_mm() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(100.0, 50.0, 20.0))  # millimetres, three distinct sides
    box.apply_translation((40.0, -7.0, 3.0))
    return box


@pytest.mark.parametrize("suffix", ["stl", "obj", "ply"])
def test_user_mesh_file_loads_scaled_and_centred(tmp_path, suffix):
    path = tmp_path / f"part.{suffix}"
    _off_centre_box_mm().export(path)
    obj = load_mesh_file(path, scale=0.001)
    assert obj.name == "part"
    assert torch.allclose(obj.dimensions, torch.tensor([0.1, 0.05, 0.02]), atol=1e-6)
    assert np.allclose(obj.mesh.center_mass, 0.0, atol=1e-9)
    assert obj.mesh.volume == pytest.approx(0.1 * 0.05 * 0.02, rel=1e-6)
    # a box with three different sides looks the same under the identity and the three half turns only
    assert obj.symmetry.order == 4
    assert obj.rest_height == pytest.approx(0.01, abs=1e-7)


def test_user_mesh_loads_through_load_object(tmp_path):
    path = tmp_path / "part.stl"
    _off_centre_box_mm().export(path)
    obj = load_object("mesh", path=path, scale=0.002)
    assert torch.allclose(obj.dimensions, torch.tensor([0.2, 0.1, 0.04]), atol=1e-6)


def test_open_mesh_is_replaced_by_its_convex_hull(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])  # one face missing: not watertight
    path = tmp_path / "open.ply"
    open_box.export(path)
    obj = load_mesh_file(path, scale=0.1)
    assert obj.mesh.is_watertight
    assert obj.mesh.volume == pytest.approx(0.1 * 0.2 * 0.3, rel=1e-6)


def test_missing_mesh_file_raises(tmp_path):
    with pytest.raises(InvalidMeshError, match="not found"):
        load_mesh_file(tmp_path / "nothing_here.stl")
    with pytest.raises(InvalidMeshError, match="is a folder"):
        load_mesh_file(tmp_path)  # a directory is not a mesh file


@pytest.mark.parametrize(
    ("filename", "content"),
    [
        ("junk.stl", "hello world\n"),
        ("junk.ply", "hello world\n"),
        ("empty.obj", ""),
        ("notes.txt", "v 0 0 0\n"),
    ],
)
def test_non_mesh_file_raises(tmp_path, filename, content):
    path = tmp_path / filename
    path.write_text(content)
    with pytest.raises(InvalidMeshError):
        load_mesh_file(path)


def test_flat_open_mesh_raises_invalid_mesh(tmp_path):
    path = tmp_path / "triangle.stl"
    trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]]).export(path)
    with pytest.raises(InvalidMeshError):
        load_mesh_file(path)


@pytest.mark.parametrize("scale", [0.0, -1.0, -0.001, float("nan"), float("inf"), None, "big"])
def test_bad_scale_raises(tmp_path, scale):
    path = tmp_path / "part.stl"
    _off_centre_box_mm().export(path)
    with pytest.raises(InvalidParameterError, match="scale"):
        load_mesh_file(path, scale=scale)
    with pytest.raises(InvalidParameterError, match="scale"):
        load_object("mesh", path=path, scale=scale)


def test_unknown_catalogue_name_and_missing_path_raise():
    with pytest.raises(InvalidParameterError, match="unknown object"):
        load_object("dodecahedron")
    with pytest.raises(InvalidParameterError, match="path"):
        load_object("mesh")


def test_errors_are_pushtorch_errors():
    assert issubclass(InvalidMeshError, PushtorchError)
    assert issubclass(InvalidParameterError, PushtorchError)


# --- meshes of several parts, up axis, units -------------------------------------------------------------------


def _pybullet_mesh(relative: str):
    import pybullet_data

    return pybullet_data.getDataPath() + "/" + relative


def _write_boxes(path, *boxes: tuple[tuple[float, float, float], tuple[float, float, float]]):
    """One mesh file of several separate box components, each ``(extents, centre)`` in file units."""
    meshes = []
    for extents, centre in boxes:
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(centre)
        meshes.append(box)
    trimesh.util.concatenate(meshes).export(path)
    return path


@pytest.mark.parametrize("relative", ["duck_vhacd.obj", "objects/mug_col.obj"])
def test_pybullet_meshes_of_several_parts_load_as_one_body(relative):
    """pybullet_data's V-HACD duck (5 hulls, 0.003 mm apart) and the mug's collision mesh (a cylinder and 5
    handle pieces that overlap it and each other), scaled to 0.2 m: one watertight body of convex parts."""
    import time

    path = _pybullet_mesh(relative)
    raw = trimesh.load(path, force="mesh", process=False)
    scale = 0.2 / float(np.max(trimesh.Trimesh(raw.vertices, raw.faces).extents))
    start = time.perf_counter()
    obj = load_mesh_file(path, scale=scale)
    assert time.perf_counter() - start < 30.0  # decomposition included (0.6 s measured)
    assert obj.collision_source.startswith("convex parts") and len(obj.collision_parts) >= 5
    assert all(part.is_convex for part in obj.collision_parts)
    assert obj.mesh.is_watertight and obj.mesh.volume > 0
    assert float(obj.dimensions.max()) == pytest.approx(0.2, rel=1e-6)
    assert np.allclose(obj.mesh.center_mass, 0.0, atol=1e-9)
    union = trimesh.boolean.union(obj.collision_parts, engine="manifold")
    assert obj.mesh.volume == pytest.approx(union.volume, rel=0.01)


@pytest.mark.parametrize("suffix", ["obj", "stl"])
def test_an_l_of_two_overlapping_boxes_is_one_body_with_its_true_volume(tmp_path, suffix):
    # 0.2 x 0.1 x 0.1 and 0.1 x 0.1 x 0.1, overlapping by 0.1 x 0.025 x 0.1 (their top faces coplanar)
    path = _write_boxes(tmp_path / f"l.{suffix}", ((0.2, 0.1, 0.1), (0.0, 0.0, 0.0)),
                        ((0.1, 0.1, 0.1), (0.05, 0.075, 0.0)))
    obj = load_mesh_file(path)
    assert obj.mesh.is_watertight
    assert obj.mesh.volume == pytest.approx(0.002 + 0.001 - 0.00025, rel=1e-6)  # the union, not the sum
    assert obj.collision_source == "convex parts"
    assert sorted(round(p.volume, 9) for p in obj.collision_parts) == [0.001, 0.002]
    assert torch.allclose(obj.dimensions, torch.tensor([0.2, 0.175, 0.1]), atol=1e-6)
    assert np.allclose(obj.mesh.center_mass, 0.0, atol=1e-9)
    assert obj.symmetry.order == 1


def test_boxes_half_a_millimetre_apart_are_one_body(tmp_path):
    path = _write_boxes(tmp_path / "near.obj", ((0.1, 0.1, 0.1), (0.0, 0.0, 0.0)),
                        ((0.1, 0.1, 0.1), (0.1005, 0.0, 0.0)))
    obj = load_mesh_file(path)
    assert len(obj.collision_parts) == 2 and obj.mesh.is_watertight
    assert obj.mesh.volume == pytest.approx(0.002, rel=1e-6)
    assert float(obj.dimensions[0]) == pytest.approx(0.2005, rel=1e-6)


def test_boxes_crossing_edge_to_edge_are_one_body(tmp_path):
    """Two boxes turned 45° whose edges cross 0.2 mm apart: no vertex is near the other box, the edges are."""
    a = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    a.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [1, 0, 0]))
    b = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [0, 1, 0]))
    half_diagonal = 0.05 * np.sqrt(2)
    b.apply_translation([0.0, 0.0, 2 * half_diagonal + 0.0002])
    path = tmp_path / "edges.stl"
    trimesh.util.concatenate([a, b]).export(path)
    assert len(load_mesh_file(path).collision_parts) == 2
    b.apply_translation([0.0, 0.0, 0.0018])  # 2 mm apart
    trimesh.util.concatenate([a, b]).export(path)
    with pytest.raises(InvalidMeshError, match=r"2 disjoint bodies 2\.0 mm apart"):
        load_mesh_file(path)


def test_boxes_five_centimetres_apart_are_refused_naming_the_gap(tmp_path):
    path = _write_boxes(tmp_path / "apart.obj", ((0.1, 0.1, 0.1), (0.0, 0.0, 0.0)),
                        ((0.1, 0.1, 0.1), (0.15, 0.0, 0.0)))
    with pytest.raises(InvalidMeshError, match=r"2 disjoint bodies 50\.0 mm apart; parts 1 mm apart or closer"):
        load_mesh_file(path)
    with pytest.raises(InvalidMeshError, match=r"50\.0 mm"):
        load_object("mesh", path=path)
    three = _write_boxes(tmp_path / "three.stl", ((0.1, 0.1, 0.1), (0.0, 0.0, 0.0)),
                         ((0.1, 0.1, 0.1), (0.15, 0.0, 0.0)), ((0.1, 0.1, 0.1), (0.27, 0.0, 0.0)))
    with pytest.raises(InvalidMeshError, match=r"3 disjoint bodies, the nearest two 20\.0 mm apart"):
        load_mesh_file(three)


def test_a_millimetre_file_at_scale_one_is_refused_with_the_scale_that_fits(tmp_path):
    path = tmp_path / "cube_mm.stl"
    trimesh.creation.box(extents=(200.0, 200.0, 200.0)).export(path)
    for load in (lambda: load_mesh_file(path), lambda: load_object("mesh", path=path)):
        with pytest.raises(InvalidMeshError, match=r"is 200 m across .*object\.scale=0\.001 would make it 0\.2 m "
                                                   r"\(0\.001 if the file is in millimetres\)"):
            load()
    assert load_mesh_file(path, scale=0.001).mesh.volume == pytest.approx(0.008, rel=1e-6)


def test_a_fifth_of_a_millimetre_object_is_refused_too(tmp_path):
    path = tmp_path / "speck.stl"
    trimesh.creation.box(extents=(0.0002, 0.0002, 0.0002)).export(path)
    with pytest.raises(InvalidMeshError, match=r"is 0\.2 mm across .*object\.scale=1000 would make it 0\.2 m"):
        load_mesh_file(path)
    metres = tmp_path / "cube.stl"
    trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(metres)
    with pytest.raises(InvalidMeshError, match=r"is 0\.2 mm across .*object\.scale=1 would make it 0\.2 m "
                                               r"\(1 if the file is in metres\)"):
        load_mesh_file(metres, scale=0.001)  # a file in metres given a millimetre scale


def test_up_y_turns_a_y_up_file_so_its_tall_axis_is_z(tmp_path):
    path = _write_boxes(tmp_path / "tall.obj", ((0.05, 0.2, 0.08), (0.0, 0.1, 0.0)))  # standing along +y
    assert torch.allclose(load_mesh_file(path).dimensions, torch.tensor([0.05, 0.2, 0.08]), atol=1e-6)
    turned = load_object("mesh", path=path, up="y")
    assert torch.allclose(turned.dimensions, torch.tensor([0.05, 0.08, 0.2]), atol=1e-6)
    assert turned.rest_height == pytest.approx(0.1, abs=1e-7)
    # +90° about x, right-handed: the file's +z becomes -y
    trimesh.creation.cone(0.05, 0.2).export(tmp_path / "cone.stl")  # tip at the file's +z
    cone = load_mesh_file(tmp_path / "cone.stl", up="y")
    tip = cone.mesh.vertices[np.argmax(np.linalg.norm(cone.mesh.vertices, axis=1))]
    assert tip[1] < -0.1 and abs(tip[0]) < 1e-9 and abs(tip[2]) < 1e-9


@pytest.mark.parametrize("up", ["x", "Y", "-y", "", None, 1])
def test_unknown_up_axis_raises_naming_the_choices(tmp_path, up):
    path = tmp_path / "part.stl"
    _off_centre_box_mm().export(path)
    with pytest.raises(InvalidParameterError, match="object.up must be one of z, y"):
        load_mesh_file(path, scale=0.001, up=up)
    with pytest.raises(InvalidParameterError, match="object.up must be one of z, y"):
        load_object("mesh", path=path, scale=0.001, up=up)


def test_the_command_line_refuses_a_millimetre_mesh_in_one_line_without_a_run_folder(tmp_path):
    import os
    import subprocess
    import sys

    path = tmp_path / "cube_mm.stl"
    trimesh.creation.box(extents=(200.0, 200.0, 200.0)).export(path)
    run = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if not k.startswith("HYDRA_")}
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch.apps.simulate", "object=mesh", f"object.path={path}", "samples_per_action=2",
         "workers=1", "rerun_pushes=0", "progress=false", f"hydra.run.dir={run}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "object.scale=0.001 would make it 0.2 m" in lines[0], result.stderr
    assert "Traceback" not in result.stderr and not run.exists()
