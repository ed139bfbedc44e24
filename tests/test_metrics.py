"""H_acc (Eq. pam) and raw errors on the catalogue objects' symmetries (pushtorch.evaluation.metrics)."""

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.evaluation import metrics
from pushtorch.objects import load_object


def test_identical_poses_score_zero():
    cube = load_object("cube")
    truth = cube.resting_pose(0.3, -0.2, 0.4)
    assert metrics.hacc(truth, truth, cube.dimensions, cube.symmetry).item() == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_cube_quarter_turns_about_z_score_zero_on_angle(turns):
    cube = load_object("cube")
    truth = cube.resting_pose(yaw=0.3)
    turned = cube.resting_pose(yaw=0.3 + turns * math.pi / 2)
    acc = metrics.accuracy(turned, truth, cube)
    assert acc.angular.item() == pytest.approx(0.0, abs=1e-6)
    assert acc.angular_deg.item() == pytest.approx(0.0, abs=1e-2)


def test_prism_quarter_turn_is_not_a_symmetry_but_half_turn_is():
    prism = load_object("prism_long")
    truth = prism.resting_pose()
    assert metrics.accuracy(prism.resting_pose(yaw=math.pi / 2), truth, prism).angular_deg.item() == pytest.approx(
        90.0, abs=0.01
    )
    assert metrics.accuracy(prism.resting_pose(yaw=math.pi), truth, prism).angular.item() < 1e-6


@given(st.floats(-10, 10, allow_nan=False))
def test_cylinder_rotated_about_its_axis_scores_zero(angle):
    cylinder = load_object("cylinder")
    tilt = se3.Pose(torch.zeros(3), se3.quat_normalize(torch.tensor([0.9, 0.3, -0.2, 0.1])))
    truth = se3.compose(cylinder.resting_pose(), tilt)
    spun = se3.compose(truth, se3.from_xy_yaw(0.0, 0.0, angle))  # about the object's own axis
    assert metrics.accuracy(spun, truth, cylinder).hacc.item() == pytest.approx(0.0, abs=1e-5)


def test_cylinder_tipped_over_scores_on_angle():
    cylinder = load_object("cylinder")
    truth = cylinder.resting_pose()
    tipped = se3.Pose(truth.p, torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]))
    acc = metrics.accuracy(tipped, truth, cylinder)
    assert acc.angular.item() == pytest.approx(0.5, abs=1e-5)  # 1 - cos^2(45°)
    assert acc.angular_deg.item() == pytest.approx(90.0, abs=1e-3)


@pytest.mark.parametrize("name", ["cube", "prism_thin", "prism_long", "cylinder_wide"])
def test_translation_of_one_object_size_along_x_scores_one(name):
    obj = load_object(name)
    truth = obj.resting_pose()
    size_x = obj.dimensions[0].item()
    moved = obj.resting_pose(x=size_x)
    acc = metrics.accuracy(moved, truth, obj)
    assert acc.linear.item() == pytest.approx(1.0, abs=1e-6)
    assert acc.linear_cm.item() == pytest.approx(100 * size_x, abs=1e-4)


def test_linear_term_uses_the_object_frame():
    prism = load_object("prism_long")  # 0.3 along its own x
    truth = prism.resting_pose(yaw=math.pi / 2)  # its x now points along world y
    moved = prism.resting_pose(y=0.3, yaw=math.pi / 2)
    assert metrics.accuracy(moved, truth, prism).linear.item() == pytest.approx(1.0, abs=1e-5)


def test_batched_over_leading_dims():
    cube = load_object("cube")
    g = torch.Generator().manual_seed(0)
    est = se3.Pose(torch.randn(2, 3, 3, generator=g) * 0.05, se3.random_quaternion((2, 3), g))
    truth = cube.resting_pose()
    acc = metrics.accuracy(est, truth, cube)
    assert acc.hacc.shape == (2, 3)
    single = metrics.accuracy(est.take((1, 2)), truth, cube)
    assert acc.hacc[1, 2].item() == pytest.approx(single.hacc.item(), abs=1e-6)
    assert (acc.angular >= 0).all() and (acc.angular <= 1).all()


def test_bad_inputs_raise_named_errors():
    cube = load_object("cube")
    truth = cube.resting_pose()
    bad_q = se3.Pose.unchecked(truth.p, torch.tensor([1.0, 1.0, 0.0, 0.0]))
    with pytest.raises(InvalidPoseError, match="unit quaternion"):
        metrics.hacc(bad_q, truth, cube.dimensions, cube.symmetry)
    with pytest.raises(InvalidParameterError, match="dimensions"):
        metrics.hacc(truth, truth, torch.tensor([0.2, 0.0, 0.2]), cube.symmetry)


def _planar(x: float, y: float, yaw: float, z: float = 0.1) -> se3.Pose:
    return se3.from_xy_yaw(torch.tensor(x), torch.tensor(y), torch.tensor(yaw), z=z)


@given(start=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-math.pi, math.pi)),
       motion=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(-math.pi, math.pi)),
       offset=st.tuples(st.floats(-0.1, 0.1), st.floats(-0.1, 0.1), st.floats(-math.pi, math.pi)),
       symmetry=st.integers(0, 23))
def test_displacement_score_is_invariant_to_the_estimated_frame(start, motion, offset, symmetry):
    """The same motion, predicted from two frames related by a symmetry of the training object (the cube's
    24 rotations) or by any body-fixed offset, moves the true start pose to where the true push ends."""
    cube = load_object("cube")
    truth_initial = _planar(*start)
    world_motion = _planar(*motion, z=0.0)
    truth_final = se3.compose(world_motion, truth_initial)
    scores = []
    for frame in (cube.symmetry.discrete[symmetry], None):
        body = se3.Pose(torch.zeros(3), frame) if frame is not None else _planar(*offset, z=0.0)
        estimate_initial = se3.compose(truth_initial, body)  # the true start seen in another frame
        estimate_final = se3.compose(world_motion, estimate_initial)
        moved = metrics.displaced(estimate_initial, estimate_final, truth_initial)
        scores.append(float(metrics.accuracy(moved, truth_final, cube).hacc))
    assert scores[0] == pytest.approx(0.0, abs=1e-5) and scores[1] == pytest.approx(0.0, abs=1e-5)


def test_displacement_moves_the_true_start_and_broadcasts():
    """``(B̂1 ∘ B̂0⁻¹) ∘ B0`` for estimates ``(N, A)`` and true starts ``(N, 1)``."""
    truth_initial = se3.Pose(torch.tensor([[0.0, 0.0, 0.1], [1.0, 0.0, 0.1]]).unsqueeze(1),
                             torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2).unsqueeze(1))
    estimate_initial = _planar(0.05, 0.0, 0.0).expand(2, 3)
    estimate_final = _planar(0.35, 0.0, 0.0).expand(2, 3)  # a 30 cm push along x
    moved = metrics.displaced(estimate_initial, estimate_final, truth_initial)
    assert moved.batch_shape == (2, 3)
    torch.testing.assert_close(moved.p[:, 0, 0], torch.tensor([0.3, 1.3]))
    # no motion leaves the true start where it is, whatever the estimate
    still = metrics.displaced(estimate_initial, estimate_initial, truth_initial)
    torch.testing.assert_close(still.p, truth_initial.p.expand(2, 3, 3))
