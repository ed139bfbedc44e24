"""Surface features (pushtorch.features): normals, principal curvatures and frames on real clouds."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError
from pushtorch.features import SurfaceFeatures, compute_surface_features, radius_neighbourhoods
from pushtorch.objects import load_object
from pushtorch.perception import DepthCamera, PointCloud, capture_full_cloud, capture_partial_cloud

CUBE_HALF = 0.1


def _nearest_neighbour_spacing(points: torch.Tensor) -> torch.Tensor:
    data = o3d.core.Tensor(points.numpy())
    index = o3d.core.nns.NearestNeighborSearch(data)
    index.knn_index()
    _, squared = index.knn_search(data, 2)
    return torch.from_numpy(np.sqrt(squared.numpy()[:, 1]))


@pytest.fixture(scope="module")
def cube_features():
    cube = load_object("cube")
    pose = cube.resting_pose(0.3, 0.2, 0.4)
    cloud = capture_full_cloud(cube, pose)
    features = compute_surface_features(cloud)
    local = se3.apply(se3.inverse(pose), features.p)
    return pose, cloud, features, local


def _cube_regions(local: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Face points farther than ``margin`` from every edge, and points on an edge (not near a corner)."""
    magnitude = local.abs().sort(-1).values  # ascending |coordinate|
    face = (magnitude[:, 2] > CUBE_HALF - 1e-3) & (magnitude[:, 1] < CUBE_HALF - margin)
    edge = (magnitude[:, 1] > CUBE_HALF - 3e-3) & (magnitude[:, 0] < CUBE_HALF - margin)
    return face, edge


# --- acceptance: curvature, normals -----------------------------------------------------------------------


@pytest.mark.parametrize(("name", "radius"), [("cylinder", 0.1), ("cylinder_wide", 0.15)])
def test_cylinder_side_has_curvature_one_over_radius_and_zero_along_the_axis(name, radius):
    cylinder = load_object(name)
    pose = cylinder.resting_pose(-0.2, 0.1, 1.0)
    cloud = capture_full_cloud(cylinder, pose)
    assert torch.quantile(_nearest_neighbour_spacing(cloud.points), 0.99) <= 0.005  # sampled at <= 5 mm
    features = compute_surface_features(cloud)
    local = se3.apply(se3.inverse(pose), features.p)
    # the side, away from both rims by more than the neighbourhood radius
    side = (local[:, :2].norm(dim=-1) > radius - 1e-3) & (local[:, 2].abs() < 0.1 - 0.02)
    assert side.sum() > 1000
    r1, r2 = features.r[side].unbind(-1)
    assert r1.median().item() == pytest.approx(1 / radius, rel=0.10)
    assert r2.abs().median().item() < 0.2 / radius
    # k1 runs around the side (horizontal), k2 along the axis (vertical), the normal points radially out
    assert features.k1[side, 2].abs().median() < 0.05
    assert features.k2[side, 2].abs().median() > 0.99
    radial = torch.cat([local[side, :2], torch.zeros(int(side.sum()), 1)], -1)
    radial_world = pkt.quaternion_apply(pose.q, radial / radial.norm(dim=-1, keepdim=True))
    assert (features.normal[side] * radial_world).sum(-1).min() > 0.98


def test_cube_faces_are_flat_and_edges_are_sharp(cube_features):
    _, _, features, local = cube_features
    face, edge = _cube_regions(local, margin=0.02)
    assert face.sum() > 3000 and edge.sum() > 100
    face_r1 = features.r[face, 0].median().item()
    edge_r1 = features.r[edge, 0].median().item()
    assert abs(face_r1) < 1.0
    assert edge_r1 > 30.0 and edge_r1 > 10 * max(face_r1, 1.0)
    # across a convex edge the surface bends one way only: r2 stays near zero
    assert features.r[edge, 1].abs().median() < 0.2 * edge_r1


def test_cube_edge_k1_runs_across_the_edge(cube_features):
    pose, _, features, local = cube_features
    _, edge = _cube_regions(local, margin=0.02)
    # the edge direction is the axis of the smallest |coordinate|
    edge_axis = local[edge].abs().argmin(-1)
    edge_direction = pkt.quaternion_apply(pose.q, torch.eye(3)[edge_axis])
    assert (features.k1[edge] * edge_direction).sum(-1).abs().median() < 0.1
    assert (features.k2[edge] * edge_direction).sum(-1).abs().median() > 0.99


def test_cube_face_normals_point_outward(cube_features):
    pose, _, features, local = cube_features
    face, _ = _cube_regions(local, margin=0.015)
    axis = local[face].abs().argmax(-1)
    sign = torch.sign(local[face].gather(-1, axis.unsqueeze(-1)))
    face_normal = pkt.quaternion_apply(pose.q, torch.eye(3)[axis] * sign)
    agreement = (features.normal[face] * face_normal).sum(-1)
    assert agreement.min() > 0.99


def test_partial_cloud_normals_face_the_camera():
    obj = load_object("modified_cube")
    pose = obj.resting_pose(0.1, 0.0, 2.5)
    eye = torch.tensor([-0.6, 0.4, 0.7])
    cloud = capture_partial_cloud(obj, pose, camera_position=eye)
    features = compute_surface_features(cloud)
    assert ((eye - features.p) * features.normal).sum(-1).min() > 0


def test_sign_convention_convex_positive_concave_negative():
    """A sphere seen from outside has r1 = r2 = +1/R; the same points seen from the centre, -1/R."""
    radius, n = 0.05, 4000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    polar = torch.acos(1 - 2 * i / n)
    azimuth = math.pi * (1 + 5**0.5) * i
    sphere = radius * torch.stack([polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos()], -1)
    sphere = sphere.float()
    outside = compute_surface_features(sphere)  # no view origins: away from the centroid
    inside = compute_surface_features(PointCloud(sphere, torch.zeros_like(sphere)))
    assert torch.allclose(outside.r.median(0).values, torch.full((2,), 1 / radius), rtol=0.05)
    assert torch.allclose(inside.r.median(0).values, torch.full((2,), -1 / radius), rtol=0.05)
    assert ((outside.normal * sphere[outside.index]).sum(-1) > 0).all()
    assert ((inside.normal * sphere[inside.index]).sum(-1) < 0).all()


def test_concave_notch_edges_have_negative_curvature():
    obj = load_object("modified_cube")
    pose = obj.resting_pose()
    cloud = capture_full_cloud(obj, pose, camera=DepthCamera(width=320, height=240))
    features = compute_surface_features(cloud)
    # the three inner edges of the notch meet at the notch's inner corner
    notch = 0.2 / 16 ** (1 / 3)
    inner_corner = torch.tensor(obj.mesh.bounds[1].tolist()) - notch
    local = se3.apply(se3.inverse(pose), features.p) - inner_corner
    magnitude = local.abs().sort(-1).values
    inner_edge = (magnitude[:, 1] < 2e-3) & (magnitude[:, 2] > 0.02) & (magnitude[:, 2] < notch - 0.02)
    inner_edge &= (local > -2e-3).all(-1)
    assert inner_edge.sum() > 10
    assert features.r[inner_edge, 1].median() < -30.0
    assert features.r[inner_edge, 0].abs().median() < 0.2 * features.r[inner_edge, 1].abs().median()


# --- properties for all inputs ----------------------------------------------------------------------------


def _paraboloid_patch(a: float, b: float, c: float, spacing: float = 0.003, half: int = 10) -> torch.Tensor:
    grid = (torch.arange(2 * half + 1, dtype=torch.float64) - half) * spacing
    x, y = torch.meshgrid(grid, grid, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack([x, y, a * x * x + b * x * y + c * y * y], -1)


curvature = st.floats(-20.0, 20.0)


@settings(max_examples=20, deadline=None)
@given(a=curvature, b=curvature, c=curvature, seed=st.integers(0, 2**31 - 1))
def test_quadric_patch_apex_has_the_analytic_principal_curvatures(a, b, c, seed):
    g = torch.Generator().manual_seed(seed)
    translation = torch.randn(3, generator=g, dtype=torch.float64)
    pose = se3.Pose(translation, se3.random_quaternion((), g, torch.float64))
    patch = _paraboloid_patch(a, b, c)
    apex_index = patch.shape[0] // 2
    # the camera is on the +z side
    above = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(patch)
    cloud = PointCloud(se3.apply(pose, patch).float(), se3.apply(pose, above).float())
    features = compute_surface_features(cloud)
    row = int((features.index == apex_index).nonzero())
    # z = [x y] H [x y]^T / 2 with the normal +z: convex (positive) where the patch bends away, i.e. -H
    hessian = torch.tensor([[2 * a, b], [b, 2 * c]], dtype=torch.float64)
    expected, directions = torch.linalg.eigh(-hessian)
    expected = expected.flip(0)
    assert torch.allclose(features.r[row].double(), expected, rtol=0.02, atol=0.1)
    normal = pkt.quaternion_apply(pose.q, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.dot(features.normal[row].double(), normal) > 0.9999
    if expected[0] - expected[1] > 2.0:  # k1 is defined only where the curvatures differ
        k1 = pkt.quaternion_apply(pose.q, torch.cat([directions[:, 1], torch.zeros(1, dtype=torch.float64)]))
        assert abs(torch.dot(features.k1[row].double(), k1)) > 0.999


@settings(max_examples=20, deadline=None)
@given(a=curvature, b=curvature, c=curvature, seed=st.integers(0, 2**31 - 1))
def test_frames_are_right_handed_orthonormal_and_match_q(a, b, c, seed):
    g = torch.Generator().manual_seed(seed)
    patch = _paraboloid_patch(a, b, c, spacing=0.004).float()
    patch = patch + 0.0005 * torch.randn(patch.shape, generator=g)  # noisy, irregular points
    features = compute_surface_features(patch, radius=0.015)
    frames = features.frames
    eye = torch.eye(3).expand_as(frames)
    assert torch.allclose(frames.transpose(1, 2) @ frames, eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(frames), torch.ones(len(features)), atol=1e-5)
    assert torch.allclose(features.q.norm(dim=-1), torch.ones(len(features)), atol=1e-6)
    assert torch.allclose(pkt.quaternion_to_matrix(features.q), frames, atol=1e-5)
    assert torch.all(features.r[:, 0] >= features.r[:, 1])
    assert torch.equal(features.p, patch[features.index])


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_features_move_with_the_cloud(seed):
    """Rigid motion of the cloud moves p, normals and frames, and leaves the curvatures unchanged."""
    g = torch.Generator().manual_seed(seed)
    cloud = _partial_cylinder_cloud()
    features = compute_surface_features(cloud)
    motion = se3.Pose(torch.randn(3, generator=g), se3.random_quaternion((), g))
    moved_cloud = PointCloud(se3.apply(motion, cloud.points), se3.apply(motion, cloud.view_origins))
    moved = compute_surface_features(moved_cloud)
    assert torch.equal(moved.index, features.index)
    assert torch.allclose(moved.p, se3.apply(motion, features.p), atol=1e-5)
    agreement = (moved.normal * pkt.quaternion_apply(motion.q, features.normal)).sum(-1)
    assert torch.quantile(agreement, 0.01) > 0.9999 and agreement.min() > 0.99
    change = (moved.r - features.r).abs().amax(-1)
    assert torch.quantile(change, 0.99) < 0.05  # float32 rounding and neighbour ties at the radius
    assert change.median() < 1e-2


_CYLINDER_CLOUD: list[PointCloud] = []


def _partial_cylinder_cloud() -> PointCloud:
    if not _CYLINDER_CLOUD:
        cylinder = load_object("cylinder")
        _CYLINDER_CLOUD.append(capture_partial_cloud(cylinder, cylinder.resting_pose()))
    return _CYLINDER_CLOUD[0]


# --- neighbourhoods, dropping, chunks, container ----------------------------------------------------------


def test_radius_neighbourhoods_are_the_points_within_the_radius():
    g = torch.Generator().manual_seed(0)
    points = torch.rand(500, 3, generator=g) * 0.1
    index, mask = radius_neighbourhoods(points, 0.02, max_neighbours=500)
    distance = torch.cdist(points, points)
    within = distance <= 0.02
    assert torch.equal(mask.sum(-1), within.sum(-1))
    assert torch.all(torch.gather(distance, 1, index)[mask] <= 0.02 + 1e-6)
    capped_index, capped_mask = radius_neighbourhoods(points, 0.02, max_neighbours=5)
    assert capped_mask.sum(-1).max() == 5
    # when capped, the nearest are kept
    nearest = distance.masked_fill(~within, float("inf")).topk(5, largest=False).values
    kept = torch.gather(distance, 1, capped_index).masked_fill(~capped_mask, float("inf")).sort(-1).values
    assert torch.allclose(kept[capped_mask.all(-1)], nearest[capped_mask.all(-1)], atol=1e-6)


def test_isolated_points_are_dropped_and_index_maps_back():
    patch = _paraboloid_patch(3.0, 0.0, 3.0).float()
    strays = torch.tensor([[1.0, 1.0, 1.0], [-1.0, 2.0, 0.5]])
    cloud = torch.cat([patch[:200], strays, patch[200:]])
    features = compute_surface_features(cloud)
    assert 200 not in features.index and 201 not in features.index
    assert len(features) >= len(patch) - 40  # only the stray points and thin rim corners may go
    assert torch.equal(features.p, cloud[features.index])


def test_chunked_and_whole_computations_agree():
    cloud = _partial_cylinder_cloud()
    whole = compute_surface_features(cloud)
    chunked = compute_surface_features(cloud, chunk_size=777)
    assert torch.equal(whole.index, chunked.index)
    for name in ("p", "q", "r", "normal", "k1", "k2"):
        assert torch.allclose(getattr(whole, name), getattr(chunked, name), atol=1e-4), name


def test_surface_features_container():
    features = compute_surface_features(_partial_cylinder_cloud())
    n = len(features)
    assert features.p.shape == (n, 3) and features.q.shape == (n, 4) and features.r.shape == (n, 2)
    assert features.normal.shape == features.k1.shape == features.k2.shape == (n, 3)
    assert features.index.dtype == torch.int64
    part = features[torch.arange(10)]
    assert isinstance(part, SurfaceFeatures) and len(part) == 10
    curved = features.r[:, 0] > 5
    assert torch.equal(features.select(curved).index, features.index[curved])
    doubled = features.to(torch.float64)
    assert doubled.p.dtype == torch.float64 and doubled.index.dtype == torch.int64
    assert features.to("cpu").p.device.type == "cpu"
    pose = features.pose
    assert pose.batch_shape == (n,)
    assert len(SurfaceFeatures.cat([part, part])) == 20
    double_cloud = _partial_cylinder_cloud().to(torch.float64)
    assert compute_surface_features(double_cloud).r.dtype == torch.float64


# --- bad input --------------------------------------------------------------------------------------------


def test_bad_clouds_raise():
    with pytest.raises(InvalidPointCloudError, match="empty"):
        compute_surface_features(torch.zeros(0, 3))
    with pytest.raises(InvalidPointCloudError, match="NaN or infinite"):
        compute_surface_features(torch.tensor([[0.0, 0.0, 0.0]] * 20 + [[float("nan"), 0.0, 0.0]]))
    with pytest.raises(InvalidPointCloudError, match="NaN or infinite"):
        compute_surface_features(torch.tensor([[0.0, 0.0, float("-inf")]] * 20))
    with pytest.raises(InvalidPointCloudError, match="at least 10 points"):
        compute_surface_features(torch.rand(9, 3) * 0.01)
    sparse = torch.arange(50, dtype=torch.float32).unsqueeze(-1) * torch.tensor([[1.0, 0.5, 0.2]])
    with pytest.raises(InvalidPointCloudError, match="too sparse"):
        compute_surface_features(sparse)
    line = torch.arange(50, dtype=torch.float32).unsqueeze(-1) * torch.tensor([[0.001, 0.0, 0.0]])
    with pytest.raises(InvalidPointCloudError, match="non-collinear"):
        compute_surface_features(line)



def test_a_cloud_far_from_the_origin_is_refused_where_its_dtype_cannot_resolve_it():
    """Far from the origin float32 coordinates are too coarse for a neighbourhood: the cloud is refused by name,
    not reported as too sparse; in float64 the same cloud there has the features it has at home."""
    cloud = _partial_cylinder_cloud()
    home = compute_surface_features(cloud)
    home64 = compute_surface_features(PointCloud(cloud.points.double(), cloud.view_origins.double()))
    far = torch.tensor([1.0e6, -2.0e6, 0.0])
    with pytest.raises(InvalidPointCloudError, match="from the origin.*frame near the object"):
        compute_surface_features(PointCloud(cloud.points + far, cloud.view_origins + far))
    double = compute_surface_features(PointCloud(cloud.points.double() + far.double(),
                                                 cloud.view_origins.double() + far.double()))
    assert torch.equal(double.index, home64.index)
    assert torch.allclose(double.r, home64.r, rtol=1e-4, atol=1e-6)
    near = compute_surface_features(PointCloud(cloud.points + far / 1e4, cloud.view_origins + far / 1e4))
    assert len(near) >= 0.95 * len(home)

def test_bad_parameters_raise():
    patch = _paraboloid_patch(1.0, 0.0, 1.0).float()
    for kwargs in [{"radius": 0.0}, {"radius": -0.01}, {"radius": float("nan")}, {"min_neighbours": 5},
                   {"min_neighbours": 20, "max_neighbours": 10}, {"chunk_size": 0}]:
        with pytest.raises(InvalidParameterError):
            compute_surface_features(patch, **kwargs)


def test_frames_on_flat_faces_repeat_between_clouds_through_gravity():
    """A face seen in two clouds gets the same frame (rotation about the normal fixed by gravity)."""
    import math

    from pushtorch import se3
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_full_cloud, capture_partial_cloud

    cube = load_object("cube")
    pose = cube.resting_pose(0.0, 0.0, 0.3)
    full = compute_surface_features(capture_full_cloud(cube, pose))
    partial = compute_surface_features(capture_partial_cloud(cube, pose))
    facing = torch.tensor([-math.cos(0.3), -math.sin(0.3), 0.0])  # the face towards the camera at -x

    def face_frames(f):
        on_face = ((f.normal @ facing) > 0.99) & (f.r[:, 0].abs() < 1.0)
        return f.q[on_face]

    a, b = face_frames(full), face_frames(partial)
    assert len(a) > 100 and len(b) > 100
    # every frame of that face, in both clouds, is one rotation
    assert se3.quat_distance(a, a[:1]).max() < 1e-3
    assert se3.quat_distance(b, a[:1]).max() < 1e-3
    k2 = full.k2[((full.normal @ facing) > 0.99) & (full.r[:, 0].abs() < 1.0)]
    assert (k2[:, 2] > 0.99).all()  # k2 points up on a vertical face


def test_cylinder_side_frames_have_k2_up_and_k1_round_the_axis():
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_full_cloud

    cylinder = load_object("cylinder")
    f = compute_surface_features(capture_full_cloud(cylinder, cylinder.resting_pose()))
    side = (f.normal[:, 2].abs() < 0.05) & (f.p[:, 2] > 0.04) & (f.p[:, 2] < 0.16)
    assert side.sum() > 200
    assert (f.k2[side][:, 2] > 0.95).float().mean() > 0.95
    assert (f.k1[side][:, 2].abs() < 0.1).float().mean() > 0.95
