"""Batched SE(3): group laws, double cover, conversions and samplers (pushtorch.se3)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidPoseError

finite = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite)
# Quaternions from 4 Gaussian-like draws, kept away from zero length.
quat_raw = st.tuples(finite, finite, finite, finite).filter(lambda v: sum(x * x for x in v) > 1e-2)


@st.composite
def poses(draw, n=4):
    ps = [draw(vec3) for _ in range(n)]
    qs = [draw(quat_raw) for _ in range(n)]
    q = torch.tensor(qs, dtype=torch.float64)
    return se3.Pose(torch.tensor(ps, dtype=torch.float64), q / q.norm(dim=-1, keepdim=True))


def assert_same_pose(a: se3.Pose, b: se3.Pose, atol=1e-9):
    torch.testing.assert_close(a.p, b.p, atol=atol, rtol=0)
    # q and -q are the same rotation
    assert torch.all(se3.quat_distance(a.q, b.q) < atol)


@given(poses(), poses(), poses())
def test_composition_is_associative(a, b, c):
    assert_same_pose(se3.compose(se3.compose(a, b), c), se3.compose(a, se3.compose(b, c)))


@given(poses())
def test_inverse_gives_identity_on_both_sides(a):
    ident = se3.identity((4,), dtype=torch.float64)
    assert_same_pose(se3.compose(a, se3.inverse(a)), ident)
    assert_same_pose(se3.compose(se3.inverse(a), a), ident)
    assert_same_pose(se3.inverse(se3.inverse(a)), a)


@given(poses(), poses(), st.lists(vec3, min_size=4, max_size=4))
def test_apply_of_composition_is_composition_of_applies(a, b, pts):
    x = torch.tensor(pts, dtype=torch.float64)
    torch.testing.assert_close(se3.apply(se3.compose(a, b), x), se3.apply(a, se3.apply(b, x)))


@given(poses(), poses(), st.lists(vec3, min_size=4, max_size=4))
def test_q_and_minus_q_act_identically(a, b, pts):
    x = torch.tensor(pts, dtype=torch.float64)
    flipped = se3.Pose(a.p, -a.q)
    torch.testing.assert_close(se3.apply(flipped, x), se3.apply(a, x))
    assert_same_pose(se3.compose(flipped, b), se3.compose(a, b))
    assert torch.all(se3.quat_distance(a.q, -a.q) < 1e-12)
    assert torch.all(se3.angle_between(a.q, -a.q) < 1e-5)


@given(poses(), poses())
def test_relative_pose_recovers_b(a, b):
    assert_same_pose(se3.compose(a, se3.relative(a, b)), b)


@given(poses(), poses(n=1), st.floats(-3.0, 3.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_onto_plane_keeps_x_y_and_the_twist_and_takes_the_references_height_and_tilt(a, ref, yaw, dx, dy):
    """The moved poses are the reference turned about world z and shifted in x, y: the reference's height, its
    tilt, the pose's x and y; a pose already on the plane stays where it is, and moving twice is moving once."""
    ref = se3.Pose(ref.p[0], ref.q[0])
    moved = se3.onto_plane_of(a, ref)
    torch.testing.assert_close(moved.p[:, :2], a.p[:, :2])
    torch.testing.assert_close(moved.p[:, 2], ref.p[2].expand(4))
    turn = pkt.quaternion_raw_multiply(moved.q, pkt.quaternion_invert(ref.q))  # a turn about world z only
    torch.testing.assert_close(turn[:, 1:3], torch.zeros(4, 2, dtype=torch.float64), atol=1e-9, rtol=0)
    assert_same_pose(se3.onto_plane_of(moved, ref), moved)
    on_plane = se3.Pose(ref.p + torch.tensor([dx, dy, 0.0], dtype=torch.float64),
                        pkt.quaternion_raw_multiply(se3.yaw_quaternion(torch.tensor(yaw, dtype=torch.float64)),
                                                    ref.q))
    assert_same_pose(se3.onto_plane_of(on_plane, ref), on_plane)


@given(poses())
def test_matrix_round_trip_and_matrix_product_matches_compose(a):
    assert_same_pose(se3.from_matrix(se3.to_matrix(a)), a, atol=1e-9)
    b = se3.Pose(a.p.flip(0), a.q.flip(0))
    torch.testing.assert_close(se3.to_matrix(se3.compose(a, b)), se3.to_matrix(a) @ se3.to_matrix(b))


@given(poses())
def test_xyzw_round_trip(a):
    torch.testing.assert_close(se3.xyzw_to_wxyz(se3.wxyz_to_xyzw(a.q)), a.q)
    one = se3.Pose(a.p[0], a.q[0])
    p, q = se3.to_pybullet(one)
    assert_same_pose(se3.from_pybullet(p, q, dtype=torch.float64), one)


def test_xyzw_matches_pybullet_convention():
    pybullet = pytest.importorskip("pybullet")
    yaw = 0.7
    q_xyzw = pybullet.getQuaternionFromEuler([0.0, 0.0, yaw])
    pose = se3.from_pybullet([0, 0, 0], q_xyzw)
    assert abs(se3.yaw_of(pose.q).item() - yaw) < 1e-6
    torch.testing.assert_close(pose.q, se3.from_xy_yaw(0.0, 0.0, yaw).q)


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_batch_shapes_broadcast(shape):
    g = torch.Generator().manual_seed(0)
    a = se3.Pose(torch.randn(*shape, 3, generator=g), se3.random_quaternion(shape, g))
    single = se3.Pose(torch.randn(3, generator=g), se3.random_quaternion((), g))
    assert se3.compose(a, single).batch_shape == torch.Size(shape)
    assert se3.apply(a, torch.zeros(*shape, 3)).shape == (*shape, 3)
    assert se3.to_matrix(a).shape == (*shape, 4, 4)


def test_uniform_rotation_sampler_matches_haar_angle_distribution():
    # The rotation angle of a Haar-uniform rotation has density (1 - cos θ) / π on [0, π].
    g = torch.Generator().manual_seed(1)
    q = se3.random_quaternion((20000,), g, dtype=torch.float64)
    angles = se3.angle_between(q, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)).numpy()
    edges = np.linspace(0, math.pi, 11)
    cdf = (edges - np.sin(edges)) / math.pi
    expected = np.diff(cdf) * len(angles)
    observed, _ = np.histogram(angles, edges)
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert chi2 < 27.9  # 99.9 % quantile of chi-square with 9 degrees of freedom


@pytest.mark.parametrize("kappa", [0.0, 10.0, 400.0, 1e5])
def test_vmf_sampler_matches_expected_concentration(kappa):
    # For a vMF on S^3, E[w] = I_2(κ)/I_1(κ) (w = <q, mean>; the antipodal fold adds e^(−2κ), nothing at
    # κ >= 10); uniform rotations on the mean's hemisphere have E[w] = 4/(3π). Compared through scipy.
    from scipy.special import ive

    g = torch.Generator().manual_seed(2)
    mean = se3.random_quaternion((), g, dtype=torch.float64).expand(40000, 4)
    q = se3.sample_vmf_quaternion(mean, kappa, g)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(40000, dtype=torch.float64))
    w = (q * mean).sum(-1)
    expected = 4.0 / (3.0 * math.pi) if kappa == 0 else ive(2, kappa) / ive(1, kappa)
    assert abs(w.mean().item() - expected) < 4 * w.std().item() / math.sqrt(len(w)) + 1e-6


@pytest.mark.parametrize("kappa", [20.0, 60.0, 1111.0, 1e5])
def test_vmf_offsets_follow_scipys_von_mises_fisher(kappa):
    """The one sampler against scipy.stats.vonmises_fisher on S^3 (its fold is e^(−2κ): nothing here): the
    law of the angle by a two-sample KS test, and isotropic axes."""
    from scipy import stats

    n = 20_000
    ours = se3.vmf_offsets(kappa, (n,), torch.Generator().manual_seed(0), torch.float64)
    assert torch.allclose(ours.norm(dim=-1), torch.ones(n, dtype=torch.float64), atol=1e-12)
    theirs = stats.vonmises_fisher([1.0, 0.0, 0.0, 0.0], kappa).rvs(n, random_state=1)
    assert stats.ks_2samp(ours[:, 0].numpy(), abs(theirs[:, 0])).pvalue > 1e-3
    axis = torch.nn.functional.normalize(ours[:, 1:], dim=-1)
    assert axis.mean(0).abs().max() < 0.03


def test_vmf_offsets_respect_a_cut_off_and_draw_the_same_for_every_dtype():
    kappa = torch.tensor([5.0, 400.0])
    drawn = se3.vmf_offsets(kappa, (3000, 2), torch.Generator().manual_seed(3), torch.float64, delta=2.0)
    assert (kappa * (1.0 - drawn[..., 0].abs()) < 2.0).all()
    narrow = se3.vmf_offsets(kappa, (3000, 2), torch.Generator().manual_seed(3), torch.float32, delta=2.0)
    torch.testing.assert_close(narrow, drawn.float())
    with pytest.raises(InvalidPoseError, match="kappa"):
        se3.vmf_offsets(-1.0, (3,))


def test_perturb_spreads_translation_with_requested_std():
    g = torch.Generator().manual_seed(3)
    base = se3.identity((50000,))
    moved = se3.perturb(base, 0.01, 1e4, g)
    assert abs(moved.p.std().item() - 0.01) < 5e-4
    assert se3.angle_between(moved.q, base.q).mean().item() < 0.05


def test_non_unit_quaternion_is_refused():
    with pytest.raises(InvalidPoseError, match="unit quaternion"):
        se3.check_unit_quaternion(torch.tensor([1.0, 1.0, 0.0, 0.0]))
    with pytest.raises(InvalidPoseError, match="NaN"):
        se3.check_unit_quaternion(torch.tensor([float("nan"), 0.0, 0.0, 0.0]))
    with pytest.raises(InvalidPoseError, match="shape"):
        se3.check_unit_quaternion(torch.tensor([1.0, 0.0, 0.0]))
    with pytest.raises(InvalidPoseError, match="zero length"):
        se3.quat_normalize(torch.zeros(4))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1e-7, 3.1))
def test_angle_between_is_the_geodesic_angle_and_stable_near_zero(seed, angle):
    """``angle_between`` returns the turn angle of a known rotation (float64, to 1e-9 rad however small),
    ignores the quaternion's sign, and its gradient stays finite and bounded where ``acos`` would not be."""
    g = torch.Generator().manual_seed(seed)
    q = se3.random_quaternion((), g, dtype=torch.float64)
    axis = torch.randn(3, generator=g, dtype=torch.float64)
    turn = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64),
                      math.sin(angle / 2) * axis / axis.norm()])
    turned = pkt.quaternion_raw_multiply(q, turn)
    assert abs(float(se3.angle_between(q, turned)) - angle) < 1e-9
    assert abs(float(se3.angle_between(q, -turned)) - angle) < 1e-9
    moved = turned.clone().requires_grad_(True)
    se3.angle_between(q, moved).backward()
    assert torch.isfinite(moved.grad).all() and float(moved.grad.norm()) < 10.0


def test_mean_pose_rotation_is_scipys_rotation_mean():
    """Markley's eigenvector mean (sign-invariant) against scipy's ``Rotation.mean``, on a spread cluster with
    random signs."""
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(21)
    centre = se3.random_quaternion((), g, dtype=torch.float64)
    q = se3.sample_vmf_quaternion(centre.expand(200, 4), 30.0, g)
    q = q * torch.where(torch.rand(200, 1, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    ours = se3.mean_pose(se3.Pose(torch.zeros(200, 3, dtype=torch.float64), q), dim=0).q
    theirs = torch.from_numpy(Rotation.from_quat(se3.wxyz_to_xyzw(q).numpy()).mean().as_quat())
    assert float(se3.angle_between(ours, se3.xyzw_to_wxyz(theirs))) < 1e-9


@given(st.floats(0.0, 3.0, allow_nan=False), st.sampled_from([torch.float32, torch.float64]))
def test_a_pose_built_from_user_values_refuses_a_quaternion_off_unit_norm(norm, dtype):
    """``Pose(p, q)`` accepts |q| within 1e-4 of 1 and refuses anything further (a norm of 2 would double
    every point ``apply`` maps); ``Pose.unchecked`` takes it as given, for the library's own poses."""
    q = torch.tensor([0.5, 0.5, 0.5, 0.5], dtype=dtype) * norm
    p = torch.zeros(3, dtype=dtype)
    if abs(norm - 1.0) <= 0.9e-4:
        assert torch.equal(se3.Pose(p, q).q, q)
    elif abs(norm - 1.0) > 1.1e-4:
        with pytest.raises(InvalidPoseError, match="unit quaternion"):
            se3.Pose(p, q)
    assert torch.equal(se3.Pose.unchecked(p, q).q, q)


@pytest.mark.parametrize("where", ["p", "q"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_pose_built_from_user_values_refuses_non_finite_entries(where, bad):
    p, q = torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    (p if where == "p" else q)[1, 2] = bad
    with pytest.raises(InvalidPoseError, match="NaN or infinite"):
        se3.Pose(p, q)
    with pytest.raises(InvalidPoseError, match="shape"):
        se3.Pose(torch.zeros(3), torch.zeros(3))


def test_poses_the_library_builds_survive_pickling_unchecked():
    import pickle

    pose = se3.Pose(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0]]))
    back = pickle.loads(pickle.dumps(pose))
    assert type(back) is se3.Pose and torch.equal(back.p, pose.p) and torch.equal(back.q, pose.q)
    drifted = se3.Pose.unchecked(torch.zeros(3), torch.tensor([2.0, 0, 0, 0]))  # as a hot loop may hold it
    assert torch.equal(pickle.loads(pickle.dumps(drifted)).q, drifted.q)
