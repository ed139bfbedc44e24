"""The residual model's point prediction (pushtorch.models.residual.POINTS) on real pybullet pushes: a model whose
point is learned reports its push model's own prediction of the same push, as the same displacement from the cloud
body's start, while its density stays the corrected one; the point is chosen on held-out training pushes, which
leave the push model's environment kernels of those pushes too; the file keeps it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.evaluation.metrics import displaced
from pushtorch.models.residual import POINTS
from pushtorch.models.residual_file import load_residual_model
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.prediction.residual import corrected_mode, learned_point, predict_residual


@pytest.fixture(scope="module")
def trained(small_cube_residual):
    """The cube, its pybullet pushes (6 per action), a small model and its residual model against pybullet."""
    return small_cube_residual


def _close(a: se3.Pose, b: se3.Pose, atol: float = 1e-4) -> bool:
    return bool(torch.allclose(a.p.double(), b.p.double(), atol=atol)) and \
        float(se3.angle_between(a.q.double(), b.q.double()).max()) < 1e-3


def test_a_learned_point_is_the_push_models_prediction_and_the_density_stays_corrected(trained):
    cube, _, model, residual = trained
    learned = dataclasses.replace(residual, point="learned")
    pose = cube.resting_pose(yaw=0.3)
    cloud = capture_partial_cloud(cube, pose, voxel_size=model.settings.voxel_size)
    action = model.actions[2]
    made = predict(learned, cloud, action, generator=torch.Generator().manual_seed(7))
    own = predict(model, cloud, action, generator=torch.Generator().manual_seed(7))
    assert made.point == "learned"
    assert _close(made.condition.robot_start, own.condition.robot_start)  # the same push condition
    assert _close(made.condition.object_pose, own.condition.object_pose)
    assert _close(displaced(made.start, made.final_pose, pose), displaced(own.condition.object_pose, own.final_pose,
                                                                           pose))
    # the density's mode is still its highest corrected kernel, not the reported point
    mode = se3.Pose.from_vector(made.density.mode)
    assert _close(mode, corrected_mode(made, 1.0))
    assert not _close(mode, made.final_pose, atol=1e-6)
    with pytest.raises(InvalidParameterError, match="push model's own prediction"):
        predict_residual(learned, cloud, action, 0)
    with pytest.raises(InvalidParameterError, match="not both"):
        predict_residual(residual, cloud, action, 0, robot_start=own.condition.robot_start, condition=own.condition)
    with pytest.raises(InvalidParameterError, match="point prediction"):
        predict_residual(dataclasses.replace(residual, point="sideways"), cloud, action, 0)
    # a caller that made pushtorch's prediction already gives it: the same point, nothing predicted twice
    given_ = predict_residual(learned, cloud, action, 3, robot_start=own.condition.robot_start,
                              learned=(own.condition.object_pose, own.final_pose))
    assert _close(displaced(given_.start, given_.final_pose, pose), displaced(own.condition.object_pose,
                                                                               own.final_pose, pose))


def test_a_batch_of_learned_points_is_the_push_models_batch(trained):
    """predict_many anneals a learned-point model's push-model predictions together, as the push model's own."""
    from pushtorch.prediction import predict_many

    cube, _, model, residual = trained
    poses = [cube.resting_pose(yaw=y) for y in (-0.3, 0.2, 0.5)]
    clouds = [capture_partial_cloud(cube, p, voxel_size=model.settings.voxel_size) for p in poses]
    made = predict_many(dataclasses.replace(residual, point="learned"), clouds, model.actions[1], seed=4, batch_size=3)
    own = predict_many(model, clouds, model.actions[1], seed=4, batch_size=3)
    for m, o, pose in zip(made, own, poses, strict=True):
        assert m.point == "learned"
        assert _close(displaced(m.start, m.final_pose, pose), displaced(o.condition.object_pose, o.final_pose, pose))


def test_a_shifted_point_is_a_local_mode_of_the_corrected_kernels_at_the_motion_width(trained):
    from pushtorch.kde import KernelBandwidth, PoseKDE
    from pushtorch.kde.normaliser import NO_CUTOFF
    from pushtorch.prediction.residual import narrow_density

    cube, _, model, residual = trained
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=-0.4), voxel_size=model.settings.voxel_size)
    made = predict(dataclasses.replace(residual, point="shifted"), cloud, model.actions[0], generator=5)
    plain = predict(residual, cloud, model.actions[0], generator=5)
    assert made.point == "shifted" and _close(se3.Pose.from_vector(made.density.mode), plain.final_pose)
    density, motion = narrow_density(made), model.settings.motion_bandwidth
    kde = PoseKDE(se3.Pose.unchecked(density.means.p.unsqueeze(0), density.means.q.unsqueeze(0)),
                  KernelBandwidth(motion.p_std, motion.rot_std, cutoff_std=NO_CUTOFF, alpha_t=motion.alpha_t),
                  density.log_weights.reshape(1, -1))
    at = se3.Pose.unchecked(made.final_pose.p.reshape(1, 1, 3), made.final_pose.q.reshape(1, 1, 4))
    assert _close(kde.mean_shift(at).reshape(1), made.final_pose, atol=2e-4)  # a fixed point: a mode
    # no kernel centre is higher at that width
    centres = se3.Pose.unchecked(density.means.p.unsqueeze(0), density.means.q.unsqueeze(0))
    assert float(kde.log_prob(at).max()) >= float(kde.log_prob(centres).max()) - 1e-4


finite = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)
quat_raw = st.tuples(finite, finite, finite, finite).filter(lambda v: sum(x * x for x in v) > 1e-2)


@st.composite
def poses(draw) -> se3.Pose:
    q = torch.tensor(draw(quat_raw), dtype=torch.float64)
    return se3.Pose.unchecked(torch.tensor([draw(finite) for _ in range(3)], dtype=torch.float64), q / q.norm())


@given(poses(), poses(), poses(), poses())
def test_a_learned_point_keeps_the_push_models_displacement_whatever_the_bodys_frame(start, final, body, truth):
    moved = learned_point((start, final), body)
    assert _close(displaced(body, moved, truth), displaced(start, final, truth), atol=1e-9)


def test_the_point_is_chosen_on_held_out_pushes_and_kept_in_the_file(trained, tmp_path):
    from pushtorch.evaluation.transfer import choose_residual_scale

    cube, records, model, residual = trained
    push = model.motions[1].environment.push
    without = residual.without_pushes(1, torch.tensor([int(push[0])]))
    assert int(push[0]) not in without.model.motions[1].environment.push.tolist()
    assert len(without.model.motions[1].environment) == len(model.motions[1].environment) - int((push == push[0]).sum())
    assert [len(m.environment) for i, m in enumerate(without.model.motions) if i != 1] == \
        [len(m.environment) for i, m in enumerate(model.motions) if i != 1]
    chosen = choose_residual_scale(residual, cube, records, 1, torch.Generator().manual_seed(0))
    point = chosen.meta["scale"]["point"]
    assert point["pushes"] == 3 and all(math.isfinite(h) and h >= 0 for h in point["hacc"])
    assert point["chosen"] == chosen.point == POINTS[int(np.argmin(point["hacc"]))]
    for kept in ("learned", "corrected"):
        path = dataclasses.replace(chosen, point=kept).save(tmp_path / f"{kept}.npz")
        assert load_residual_model(path).point == kept
    dataclasses.replace(chosen, point="sideways").save(tmp_path / "bad.npz")  # refused by name when read
    with pytest.raises(RecordFormatError, match="point prediction"):
        load_residual_model(tmp_path / "bad.npz")
