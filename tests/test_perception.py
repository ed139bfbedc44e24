"""The virtual depth camera (pushtorch.perception): full and single-shot clouds of real meshes."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError, InvalidPoseError
from pushtorch.objects import load_object
from pushtorch.perception import (
    DepthCamera,
    PointCloud,
    capture_full_cloud,
    capture_partial_cloud,
    default_partial_camera_position,
    orbit_viewpoints,
    voxel_down_sample,
)

SMALL_CAMERA = DepthCamera(width=320, height=240)


def _world_mesh_scene(obj, pose: se3.Pose) -> o3d.t.geometry.RaycastingScene:
    """The object alone (no ground) placed with a 4×4 matrix: an independent path from se3.apply."""
    mesh = obj.mesh.copy()
    mesh.apply_transform(se3.to_matrix(pose).double().numpy())
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    return scene


def _distance_to_surface(obj, pose: se3.Pose, points: torch.Tensor) -> torch.Tensor:
    scene = _world_mesh_scene(obj, pose)
    return torch.from_numpy(scene.compute_distance(o3d.core.Tensor(points.numpy())).numpy())


def _to_object_frame(pose: se3.Pose, points: torch.Tensor) -> torch.Tensor:
    return se3.apply(se3.inverse(pose), points)


# --- PointCloud -------------------------------------------------------------------------------------------


def test_point_cloud_rejects_empty_nan_inf_and_bad_shapes():
    with pytest.raises(InvalidPointCloudError, match="empty"):
        PointCloud(torch.zeros(0, 3))
    with pytest.raises(InvalidPointCloudError, match="NaN or infinite"):
        PointCloud(torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]]))
    with pytest.raises(InvalidPointCloudError, match="NaN or infinite"):
        PointCloud(torch.tensor([[0.0, float("inf"), 0.0]]))
    with pytest.raises(InvalidPointCloudError, match=r"shape \(N, 3\)"):
        PointCloud(torch.zeros(4, 2))
    with pytest.raises(InvalidPointCloudError, match="view_origins must match"):
        PointCloud(torch.zeros(4, 3), torch.zeros(3, 3))
    with pytest.raises(InvalidPointCloudError, match="view_origins"):
        PointCloud(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0], [0.0, float("nan"), 1.0]]))


def test_point_cloud_select_cat_and_to():
    g = torch.Generator().manual_seed(0)
    cloud = PointCloud(torch.randn(10, 3, generator=g), torch.randn(10, 3, generator=g))
    part = cloud[torch.arange(3)]
    assert len(part) == 3 and torch.equal(part.view_origins, cloud.view_origins[:3])
    both = PointCloud.cat([part, cloud.select(slice(3, None))])
    assert torch.equal(both.points, cloud.points) and torch.equal(both.view_origins, cloud.view_origins)
    assert PointCloud.cat([part, PointCloud(cloud.points[3:])]).view_origins is None
    doubled = cloud.to(torch.float64)
    assert doubled.points.dtype == doubled.view_origins.dtype == torch.float64
    assert PointCloud(np.zeros((2, 3), dtype=np.int64)).points.dtype == torch.float32


# --- camera and scene -------------------------------------------------------------------------------------


def test_camera_rejects_bad_parameters():
    for kwargs in [{"width": 0}, {"height": -1}, {"fov_deg": 0.0}, {"fov_deg": 180.0}, {"max_range": 0.0},
                   {"noise_std": -0.001}, {"noise_std": float("nan")}]:
        with pytest.raises(InvalidParameterError):
            DepthCamera(**kwargs)


def test_orbit_viewpoints_surround_the_target_at_the_given_distance():
    target = torch.tensor([0.3, -0.2, 0.1])
    eyes = orbit_viewpoints(target, 0.8, n_azimuths=8, elevations_deg=(20.0, 50.0), include_top=True)
    assert eyes.shape == (17, 3)
    assert torch.allclose((eyes - target).norm(dim=-1), torch.full((17,), 0.8), atol=1e-6)
    assert torch.allclose(eyes[-1], target + torch.tensor([0.0, 0.0, 0.8]))
    azimuths = torch.atan2(eyes[:-1, 1] - target[1], eyes[:-1, 0] - target[0])
    assert len(set(azimuths.round(decimals=4).tolist())) == 8
    with pytest.raises(InvalidParameterError):
        orbit_viewpoints(target, 0.0)


def test_bad_pose_raises():
    cube = load_object("cube")
    with pytest.raises(InvalidPoseError, match="unit"):
        capture_partial_cloud(cube, se3.Pose(torch.tensor([0.0, 0.0, 0.1]), torch.tensor([2.0, 0, 0, 0])))
    with pytest.raises(InvalidPoseError, match="one pose"):
        capture_partial_cloud(cube, cube.resting_pose().expand(2))
    with pytest.raises(InvalidPoseError, match="NaN"):
        nan_position = torch.tensor([float("nan"), 0.0, 0.1])
        capture_partial_cloud(cube, se3.Pose(nan_position, torch.tensor([1.0, 0, 0, 0])))


def test_object_out_of_view_raises():
    cube = load_object("cube")
    with pytest.raises(InvalidPointCloudError, match="no camera ray hit"):
        capture_partial_cloud(
            cube, camera_position=torch.tensor([-1.0, 0.0, 0.5]), target=torch.tensor([-3.0, 0.0, 0.5]),
            camera=SMALL_CAMERA,
        )
    with pytest.raises(InvalidPointCloudError, match="no camera ray hit"):
        capture_partial_cloud(cube, camera=DepthCamera(width=64, height=48, max_range=0.3))
    with pytest.raises(InvalidParameterError, match="camera_position"):
        capture_partial_cloud(cube, camera_position=torch.zeros(2))


# --- full cloud -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cube_at_random_pose():
    cube = load_object("cube")
    pose = cube.resting_pose(0.37, -0.21, 0.6)
    return cube, pose, capture_full_cloud(cube, pose, voxel_size=None, camera=SMALL_CAMERA)


def test_full_cloud_points_lie_on_the_placed_object(cube_at_random_pose):
    cube, pose, raw = cube_at_random_pose
    # exact ray hits: on the surface up to float32 rounding; ground hits would be centimetres away
    assert _distance_to_surface(cube, pose, raw.points).max() < 1e-4
    down = voxel_down_sample(raw, 0.004)
    distance = _distance_to_surface(cube, pose, down.points)
    assert distance.median() < 1e-4  # voxel means stay on flat faces...
    assert distance.max() < 0.004  # ...and cut corners by less than a voxel


def test_full_cloud_sees_every_face_but_the_one_on_the_ground(cube_at_random_pose):
    cube, pose, raw = cube_at_random_pose
    local = _to_object_frame(pose, raw.points)
    half = 0.1 - 1e-4
    for axis in range(3):
        for sign in (1.0, -1.0):
            on_face = sign * local[:, axis] > half
            others = [a for a in range(3) if a != axis]
            if axis == 2 and sign < 0:
                # points of the side faces touch the ground edge; none lies inside the bottom face
                on_face &= (local[:, others].abs() < 0.099).all(-1)
                assert on_face.sum() == 0, "the face on the ground cannot be seen"
            else:
                # the face is covered everywhere: points reach within 2 mm of all four of its edges
                face = local[on_face][:, others]
                assert face.shape[0] > 1000
                assert (face.amax(0) > 0.098).all() and (face.amin(0) < -0.098).all()


def test_full_cloud_view_origins_see_their_points(cube_at_random_pose):
    cube, pose, raw = cube_at_random_pose
    scene = _world_mesh_scene(cube, pose)
    # the ray from each point's camera through the point first meets the object at that point
    sample = raw.select(torch.randperm(len(raw), generator=torch.Generator().manual_seed(0))[:5000])
    direction = sample.points - sample.view_origins
    rays = torch.cat([sample.view_origins, direction], -1).numpy()
    t_hit = torch.from_numpy(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    assert torch.allclose(t_hit, torch.ones_like(t_hit), atol=1e-4)


def test_full_cloud_default_down_sampling_is_at_most_five_millimetres():
    cylinder = load_object("cylinder")
    cloud = capture_full_cloud(cylinder)
    index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(cloud.points.numpy()))
    index.knn_index()
    _, sq = index.knn_search(o3d.core.Tensor(cloud.points.numpy()), 2)
    spacing = torch.from_numpy(np.sqrt(sq.numpy()[:, 1]))
    assert spacing.median() <= 0.005 and torch.quantile(spacing, 0.99) <= 0.005
    assert cloud.points.dtype == torch.float32 and cloud.view_origins is not None


# --- partial cloud ----------------------------------------------------------------------------------------


def test_partial_cloud_of_a_cube_holds_only_the_near_face_and_the_top():
    cube = load_object("cube")
    pose = cube.resting_pose()
    cloud = capture_partial_cloud(cube, pose, voxel_size=None)
    local = _to_object_frame(pose, cloud.points)
    near_face = local[:, 0] < -0.1 + 1e-4
    top = local[:, 2] > 0.1 - 1e-4
    assert (near_face | top).all(), "the default camera (robot side, -x, elevated) sees only -x and the top"
    assert near_face.sum() > 1000 and top.sum() > 1000
    assert torch.equal(cloud.view_origins, default_partial_camera_position(pose).expand_as(cloud.points))


@settings(max_examples=15, deadline=None)
@given(
    azimuth=st.floats(-math.pi, math.pi),
    horizontal=st.floats(0.5, 1.2),
    height=st.floats(0.05, 1.0),
    yaw=st.floats(-math.pi, math.pi),
)
def test_partial_cloud_of_a_cylinder_holds_only_the_side_facing_the_camera(azimuth, horizontal, height, yaw):
    cylinder = load_object("cylinder")
    radius = 0.1
    pose = cylinder.resting_pose(0.2, -0.1, yaw)
    axis_xy = pose.p[:2]
    eye = torch.tensor([
        axis_xy[0] + horizontal * math.cos(azimuth), axis_xy[1] + horizontal * math.sin(azimuth), height
    ])
    cloud = capture_partial_cloud(cylinder, pose, camera_position=eye, camera=SMALL_CAMERA, voxel_size=None)
    outward = cloud.points[:, :2] - axis_xy
    radial = outward.norm(dim=-1)
    on_top = cloud.points[:, 2] > 0.2 - 1e-4
    side = (radial > radius * math.cos(math.pi / 96) - 1e-5) & ~on_top  # on the 96-facet polygon
    top = on_top & (radial < radius - 1e-3)  # away from the rim, which belongs to both
    assert (side | on_top).all()
    assert side.sum() > 100
    # A side point at angle theta from the camera's azimuth is visible iff cos(theta) > R / d (the tangent
    # rays), up to the half-width of a facet (a facet is seen whole as soon as its normal faces the camera).
    towards_eye = eye[:2] - axis_xy
    cos_theta = (outward[side] * towards_eye).sum(-1) / (radial[side] * towards_eye.norm())
    limit = radius / horizontal
    assert cos_theta.min() > limit - math.sin(math.pi / 96) - 2e-3, "a point on the far side was returned"
    # ...and the visible arc spans the whole silhouette: the points reach the tangent rays on both sides
    across = torch.stack([-towards_eye[1], towards_eye[0]]) / towards_eye.norm()
    lateral = (outward[side] * across).sum(-1)
    tangent_lateral = radius * math.sqrt(1 - limit**2)
    assert lateral.max() > 0.95 * tangent_lateral and lateral.min() < -0.95 * tangent_lateral
    if height < 0.2:  # the camera is below the top face: it cannot see it
        assert top.sum() == 0
    else:
        assert top.sum() > 0


@pytest.mark.parametrize("azimuth_deg", [45.0, 135.0, 180.0])
def test_partial_cloud_points_have_a_clear_line_of_sight(azimuth_deg):
    """On the non-convex modified cube: no returned point hides behind another part of the object."""
    obj = load_object("modified_cube")
    pose = obj.resting_pose(0.0, 0.0, 0.3)
    a = math.radians(azimuth_deg)
    eye = pose.p + torch.tensor([0.7 * math.cos(a), 0.7 * math.sin(a), 0.45])
    cloud = capture_partial_cloud(obj, pose, camera_position=eye, camera=SMALL_CAMERA, voxel_size=None)
    scene = _world_mesh_scene(obj, pose)
    rays = torch.cat([eye.expand_as(cloud.points), cloud.points - eye], -1).numpy()
    t_hit = torch.from_numpy(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    assert torch.allclose(t_hit, torch.ones_like(t_hit), atol=1e-4)
    # and every point lies on a face turned towards the camera
    closest = scene.compute_closest_points(o3d.core.Tensor(cloud.points.numpy()))
    normals = torch.from_numpy(closest["primitive_normals"].numpy())
    assert ((eye - cloud.points) * normals).sum(-1).min() > 0


def test_depth_noise_has_the_requested_spread_and_is_seeded():
    cube = load_object("cube")
    pose = cube.resting_pose()
    above = pose.p + torch.tensor([0.0, 0.0, 0.8])  # looking straight down: depth noise moves points in z
    noisy = DepthCamera(width=320, height=240, noise_std=0.002)

    def shot(seed: int) -> PointCloud:
        return capture_partial_cloud(cube, pose, camera_position=above, camera=noisy, voxel_size=None,
                                     generator=torch.Generator().manual_seed(seed))

    first, again, other = shot(7), shot(7), shot(8)
    assert torch.equal(first.points, again.points)
    assert not torch.equal(first.points, other.points)
    inner = (first.points[:, :2].abs() < 0.09).all(-1)
    offset = first.points[inner, 2] - 0.2
    assert offset.std().item() == pytest.approx(0.002, rel=0.05)
    assert abs(offset.mean().item()) < 1e-4
    clean = capture_partial_cloud(cube, pose, camera_position=above, camera=SMALL_CAMERA, voxel_size=None)
    assert (clean.points[:, 2] - 0.2).abs().max() < 1e-5


# --- voxel down-sampling ----------------------------------------------------------------------------------


def test_voxel_down_sampling_averages_points_and_view_origins_per_voxel():
    g = torch.Generator().manual_seed(0)
    centres = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.03]], dtype=torch.float64)
    jitter = 0.0005 * (torch.rand(3, 20, 3, generator=g, dtype=torch.float64) - 0.5)
    points = (centres.unsqueeze(1) + jitter).reshape(-1, 3)
    origins = torch.randn(60, 3, generator=g, dtype=torch.float64)
    down = voxel_down_sample(PointCloud(points, origins), voxel_size=0.01)
    assert len(down) == 3
    assert down.points.dtype == torch.float64
    order = torch.argsort(down.points[:, 0] * 100 + down.points[:, 1] * 10 + down.points[:, 2])
    expected_order = torch.argsort(centres[:, 0] * 100 + centres[:, 1] * 10 + centres[:, 2])
    expected_points = points.reshape(3, 20, 3).mean(1)[expected_order]
    expected_origins = origins.reshape(3, 20, 3).mean(1)[expected_order]
    assert torch.allclose(down.points[order], expected_points, atol=1e-6)
    assert torch.allclose(down.view_origins[order], expected_origins, atol=1e-5)
    assert voxel_down_sample(PointCloud(points), 0.01).view_origins is None


def test_voxel_down_sampling_keeps_one_layer_on_a_face_at_a_round_coordinate():
    # a plane at z = 0.1 (a multiple of the voxel): one point per 4 mm cell, not two layers
    axis = torch.arange(100) * 0.001
    grid = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1)
    plane = torch.cat([grid.reshape(-1, 2), torch.full((10000, 1), 0.1)], -1)
    plane[0::2, 2] += 1e-7  # rounding noise: neighbouring points on either side of the plane
    plane[1::2, 2] -= 1e-7
    down = voxel_down_sample(PointCloud(plane), 0.004)
    assert len(down) <= 26 * 26  # 0.1 m square, 4 mm voxels: at most 26 cells a side, in one layer
    assert (down.points[:, 2] - 0.1).abs().max() < 1e-6


@pytest.mark.parametrize("voxel", [0.0, -0.004, float("nan"), float("inf")])
def test_voxel_down_sampling_rejects_bad_sizes(voxel):
    with pytest.raises(InvalidParameterError, match="voxel_size"):
        voxel_down_sample(PointCloud(torch.zeros(3, 3)), voxel)
