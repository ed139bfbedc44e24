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
