"""The likelihood score (issue 15, item 2) and the equal-information baselines (item 3): normalisers against
closed forms and Monte Carlo, the nll of a real prediction's density at its own samples against far poses,
symmetry and frame invariance, and the baselines on real clouds, models and pybullet pushes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError
from pushtorch.evaluation.baselines import (
    cloud_body,
    nearest_push_prediction,
    oracle_physics_prediction,
    physics_from_cloud_prediction,
)
from pushtorch.evaluation.likelihood import (
    calibrated_choice,
    log_rotation_normaliser,
    mean_motion_density,
    motion_product_density,
    nll,
    point_density,
    product_density,
    truth_copies,
)
from pushtorch.features import compute_surface_features
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import contact_bandwidth, predict


def _unit(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True)


# -- normalisers -------------------------------------------------------------------------------------


@pytest.mark.parametrize("kappa", [0.3, 3.0, 40.0])
def test_rotation_normaliser_matches_monte_carlo_over_uniform_rotations(kappa):
    g = torch.Generator().manual_seed(0)
    q = _unit(torch.randn(1_000_000, 4, generator=g, dtype=torch.float64))
    estimate = torch.exp(-kappa * (1.0 - q[:, 0].abs())).mean().log()
    assert float(log_rotation_normaliser(torch.tensor(kappa))) == pytest.approx(float(estimate), abs=5e-3)


def test_rotation_normaliser_tends_to_the_gaussian_limit():
    # large κ: (4/π) κ^(-3/2) √2 Γ(3/2) = √(2/π) · 2 κ^(-3/2) / √π · ...: the closed Laplace limit
    kappa = torch.tensor([1e4, 1e6])
    limit = math.log(4.0 / math.pi) - 1.5 * torch.log(kappa) + math.log(math.sqrt(2.0) * math.gamma(1.5))
    torch.testing.assert_close(log_rotation_normaliser(kappa), limit.double(), atol=1e-3, rtol=0)


@given(offset=st.floats(0.0, 0.04), p_std=st.floats(0.005, 0.03), seed=st.integers(0, 2**31 - 1))
def test_product_of_two_kernels_is_normalised_as_the_closed_form(offset, p_std, seed):
    rot_std = 0.05
    means = se3.Pose(torch.tensor([[0.0, 0.0, 0.0], [offset, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]] * 2))
    weights = torch.tensor([[0.0, -math.inf], [-math.inf, 0.0]])  # expert e holds kernel e only
    mode = se3.Pose(torch.tensor([[offset / 2, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]]))  # as annealing finds
    density = product_density(means, weights, p_std, rot_std, generator=torch.Generator().manual_seed(seed),
                              centres=mode, samples=1024)
    variance = 2.0 * p_std**2  # ∫ N(x; 0, s²) N(x; δ, s²) dx = N(δ; 0, 2 s²)
    kappa = 4.0 / rot_std**2
    rotation = log_rotation_normaliser(torch.tensor(2 * kappa)) - 2 * log_rotation_normaliser(torch.tensor(kappa))
    closed = -offset**2 / (2 * variance) - 1.5 * math.log(2 * math.pi * variance) + float(rotation)
    assert float(density.log_normaliser()) == pytest.approx(closed, abs=0.05)


def test_one_kernel_scores_its_documented_peak():
    peak = point_density(se3.identity(), 0.01, 0.05).log_prob(se3.identity().vector())
    assert -float(peak) == pytest.approx(-21.66, abs=0.01)  # docs/method.md, "Likelihood score"


def test_mean_motion_density_fits_the_spread_of_its_motions():
    g = torch.Generator().manual_seed(1)
    sigma = 0.02
    p = torch.tensor([0.3, -0.1, 0.0]) + sigma * torch.randn(4000, 3, generator=g)
    q = _unit(torch.cat([torch.ones(4000, 1), 0.5 * 0.03 * torch.randn(4000, 3, generator=g)], -1))
    centre = se3.Pose(torch.tensor([0.3, -0.1, 0.0]), torch.tensor([1.0, 0, 0, 0]))
    density = mean_motion_density(se3.Pose(p, q), centre, se3.identity(), se3.identity())
    bandwidth = density.bandwidth
    assert bandwidth.p_std == pytest.approx(sigma, rel=0.05)
    assert bandwidth.rot_std == pytest.approx(0.03, rel=0.1)


# -- a real prediction's density ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def cube_prediction(small_model):
    cube = load_object("cube")
    model = small_model("cube")
    pose = cube.resting_pose(yaw=0.3)
    cloud = capture_partial_cloud(cube, pose)
    prediction = predict(model, cloud, model.actions[2], torch.Generator().manual_seed(0))
    return cube, model, pose, cloud, prediction


def test_nll_at_the_densitys_own_samples_is_lower_than_at_far_poses(cube_prediction):
    cube, _, pose, _, prediction = cube_prediction
    density = motion_product_density(prediction.motion_density, torch.Generator().manual_seed(0))
    samples = se3.Pose.from_vector(prediction.density.sample((64,), torch.Generator().manual_seed(1)))
    start = prediction.condition.object_pose
    # samples of B̂1, read as truths moving from the estimated start itself
    near = nll(density, samples, start, start, cube.symmetry)
    far_shift = se3.Pose(samples.p + torch.tensor([0.15, -0.1, 0.0]), samples.q)
    far = nll(density, far_shift, start, start, cube.symmetry)
    assert torch.isfinite(near).all() and torch.isfinite(far).all()
    assert float(near.max()) < float(far.min())
    print(f"\nnll at own samples: median {float(near.median()):.1f}, 15 cm away: median {float(far.median()):.1f}")


def test_nll_does_not_depend_on_the_truths_symmetric_copy(cube_prediction):
    cube, _, pose, _, prediction = cube_prediction
    density = motion_product_density(prediction.motion_density, torch.Generator().manual_seed(0))
    truth_final = se3.Pose(prediction.final_pose.p.reshape(1, 3) + torch.tensor([0.01, 0.0, 0.0]),
                           prediction.final_pose.q.reshape(1, 4))
    start = prediction.condition.object_pose
    base = nll(density, truth_final, start, start, cube.symmetry)
    for s in cube.symmetry.discrete[1:6]:  # the same truth, its final body frame turned by a symmetry
        turned = se3.compose(truth_final, se3.Pose(torch.zeros(3), s))
        torch.testing.assert_close(nll(density, turned, start, start, cube.symmetry), base, atol=1e-3, rtol=0)
        started = se3.compose(start, se3.Pose(torch.zeros(3), s))  # ... or its start's
        torch.testing.assert_close(nll(density, truth_final, started, start, cube.symmetry), base, atol=1e-3,
                                   rtol=0)


def test_nll_does_not_depend_on_the_frame_the_estimate_is_expressed_in(cube_prediction):
    """The same predicted displacement from two estimated frames related by a symmetry S of the training
    object (``B̂0 ∘ S``, every kernel at ``B̂1 ∘ S``) scores the same."""
    cube, _, pose, _, prediction = cube_prediction
    start = prediction.condition.object_pose
    truths = se3.Pose(prediction.final_pose.p.reshape(1, 3) + torch.tensor([[0.01, 0.0, 0.0], [0.0, -0.02, 0.0]]),
                      prediction.final_pose.q.reshape(1, 4).expand(2, 4))
    means, log_weights = prediction.motion_density.shared_kernels()
    bandwidth = prediction.motion_density.experts.bandwidth
    rounds = prediction.motion_density.experts.trial_rounds[0]
    scores = []
    for s in cube.symmetry.discrete[:4]:
        turn = se3.Pose(torch.zeros(3), s)
        density = product_density(se3.compose(means, turn), log_weights, bandwidth.p_std, bandwidth.rot_std,
                                  rounds, generator=torch.Generator().manual_seed(0),
                                  centres=se3.compose(prediction.candidates, turn))
        scores.append(nll(density, truths, pose, se3.compose(start, turn), cube.symmetry))
        point = point_density(se3.compose(prediction.final_pose, turn), 0.01, 0.05)
        scores.append(nll(point, truths, pose, se3.compose(start, turn), cube.symmetry))
    for k in range(2, len(scores)):  # importance sampling leaves hundredths of a nat, float32 kernels 1e-4
        torch.testing.assert_close(scores[k], scores[k % 2], atol=0.1 if k % 2 == 0 else 1e-3, rtol=0)


def test_a_continuous_symmetry_is_scored_at_the_nearest_turn():
    cylinder = load_object("cylinder")
    density = point_density(cylinder.resting_pose(0.2, 0.1, 0.4), 0.01, 0.05)
    start = cylinder.resting_pose()
    turns = torch.linspace(0.0, 2 * math.pi, 17)[:-1] + 0.013  # off the 3° grid
    finals = se3.Pose.stack([cylinder.resting_pose(0.2, 0.1, 0.4 + float(t)) for t in turns])
    values = nll(density, finals, start, start, cylinder.symmetry)
    assert float(values.max() - values.min()) < 0.02
    assert float(values.mean()) == pytest.approx(-21.66, abs=0.05)
    # the copies nll takes the best of, as one set: what scores a truth under many densities at once
    copies = truth_copies(density, finals, start, start, cylinder.symmetry)
    assert copies.p.shape[:1] == (16,)
    torch.testing.assert_close(-density.log_prob(copies.vector()).amax(-1), values)


# -- baselines on equal information ------------------------------------------------------------------


def test_nearest_push_replays_one_training_motion(cube_prediction):
    _, model, _, _, prediction = cube_prediction
    condition = prediction.condition
    motion = model.motions[2]
    final = nearest_push_prediction(motion, condition.manipulator_frame, condition.robot_start,
                                    condition.object_pose, contact_bandwidth(model.settings),
                                    condition.contact_patch)
    replayed = se3.compose(se3.compose(condition.robot_start, motion.manipulator.m),
                           se3.compose(se3.inverse(condition.robot_start), condition.object_pose))
    gaps = (replayed.p - final.p).norm(dim=-1)
    assert float(gaps.min()) < 1e-5


def test_the_cloud_body_is_the_visible_cube_swept_down_and_pushes_like_the_cube(cube_prediction):
    cube, _, pose, cloud, prediction = cube_prediction
    features = compute_surface_features(cloud)
    body, start = cloud_body(features.p, prediction.condition.object_pose)
    # the camera sees the top and the -x faces: the swept hull is nearly the whole cube
    assert 0.8 * cube.mesh.volume < body.mesh.volume <= 1.02 * cube.mesh.volume
    assert float(start.p[2]) == pytest.approx(body.rest_height, abs=1e-6)
    action = prediction.action
    robot_start = prediction.condition.robot_start
    cloud_start, cloud_final = physics_from_cloud_prediction(features.p, prediction.condition.object_pose,
                                                             robot_start, action, 0.5, 0.3)
    oracle = oracle_physics_prediction(cube, robot_start, pose, action, 0.5, 0.3)
    moved = se3.compose(se3.compose(cloud_final, se3.inverse(cloud_start)), pose)
    gap = float((moved.p - oracle.p).norm())
    print(f"\nphysics from the cloud vs the oracle on the cube: {100 * gap:.2f} cm apart; "
          f"oracle moved {100 * float((oracle.p - pose.p).norm()):.1f} cm")
    assert gap < 0.05


@pytest.mark.filterwarnings("error")  # refused with the error alone, not a numpy warning from trimesh first
def test_a_flat_cloud_cannot_make_a_body():
    flat = torch.rand(50, 3)
    flat[:, 2] = 0.0
    with pytest.raises(ModelError, match="spans no volume"):
        cloud_body(flat, se3.identity())


@given(st.integers(2, 30), st.integers(1, 12), st.integers(0, 2**31 - 1), st.floats(0.0, 4.0))
def test_a_calibrated_choice_keeps_the_tied_setting_nearest_its_level(pushes, settings, seed, margin):
    """Whatever the scores, the kept setting is within ``margin`` paired SE of the likeliest (always a candidate).
    Without region thresholds it is the one whose coverage is nearest the level (the likelier on a tie); with
    them and groups, the sharpest of those within their miscalibration's SE of the least miscalibrated."""
    generator = torch.Generator().manual_seed(seed)
    rows = torch.randn(pushes, settings, generator=generator, dtype=torch.float64) \
        + 3.0 * torch.rand(settings, generator=generator, dtype=torch.float64)
    inside = torch.rand(pushes, settings, generator=generator) < torch.rand(settings, generator=generator)
    asked = []
    chosen, report = calibrated_choice(rows, lambda c: asked.append(c) or inside[:, c], 0.9, margin)
    mean = rows.mean(0)
    likeliest = int(mean.argmin())
    differences = rows - rows[:, likeliest:likeliest + 1]
    se = [float(np.clip(d, *np.quantile(d, [0.05, 0.95])).std(ddof=1)) / math.sqrt(pushes)
          for d in differences.T.numpy()]  # winsorised: a few pushes far worse tie with nothing
    surely, maybe = ({c for c in range(settings) if mean[c] - mean[likeliest] <= margin * se[c] + slack} | {likeliest}
                     for slack in (-1e-9, 1e-9))  # the two computations may differ in the last digits at the edge
    tied = report["candidates"]
    assert surely <= set(tied) <= maybe and sorted(tied) == sorted(asked) and tied[0] == likeliest
    share = inside.double().mean(0)
    assert chosen == min(tied, key=lambda c: (abs(float(share[c]) - 0.9), float(mean[c])))  # no sharpness given
    assert report["coverage"] == pytest.approx([float(share[c]) for c in report["candidates"]])
    labels = torch.randint(0, 3, (pushes,), generator=generator).tolist()  # each group counted once, not pooled
    edge = torch.randn(pushes, settings, generator=generator, dtype=torch.float64)  # each region's threshold
    chosen, report = calibrated_choice(rows, lambda c: (inside[:, c], edge[:, c]), 0.9, margin, groups=labels)

    def off(c):
        members = [[inside[k, c] for k in range(pushes) if labels[k] == g] for g in dict.fromkeys(labels)]
        return sum(abs(sum(map(float, m)) / len(m) - 0.9) for m in members) / len(members)
    assert report["candidates"] == tied and report["groups"] == [str(g) for g in dict.fromkeys(labels)]
    assert report["miscalibration"] == pytest.approx([off(c) for c in tied])
    assert report["sharpness"] == pytest.approx([float(edge[:, c].mean()) for c in tied])
    least = min(tied, key=lambda c: (round(off(c), 9), float(mean[c])))
    spread = dict(zip(tied, report["miscalibration_se"], strict=True))
    alike = [c for c in tied if off(c) - off(least) <= spread[c] + 1e-8]
    assert spread[least] == 0.0 and all(v >= 0.0 for v in spread.values())
    assert least in report["calibrated_alike"] and set(report["calibrated_alike"]) <= set(alike)
    assert chosen in alike and all(float(edge[:, chosen].mean()) >= float(edge[:, c].mean()) - 1e-8
                                   for c in report["calibrated_alike"])  # the sharpest of those calibrated alike
    with pytest.raises(InvalidParameterError, match="nll rows"):
        calibrated_choice(rows[:1], lambda c: inside[:1, c])
    with pytest.raises(InvalidParameterError, match="NaN"):
        calibrated_choice(torch.where(rows == rows[0, 0], math.nan, rows), lambda c: inside[:, c])


def test_a_tie_goes_to_the_setting_calibrated_in_every_group_not_in_their_pool():
    """Two settings alike in likelihood over two groups of 10 pushes: one holds 1.0 of the first group's truths
    and 0.8 of the second's (0.9 pooled), the other 0.9 and 0.8 (0.85 pooled). Pooled, the first is nearer 90 %;
    group by group, the second is (0.05 off on average against 0.1)."""
    rows = torch.zeros(20, 2, dtype=torch.float64)
    inside = torch.ones(20, 2, dtype=torch.bool)
    inside[[10, 11], 0] = False  # the second group: 8 of 10 inside for both settings
    inside[[10, 11, 0], 1] = False  # and the first 9 of 10 for the second setting
    assert calibrated_choice(rows, lambda c: inside[:, c])[0] == 0
    chosen, report = calibrated_choice(rows, lambda c: inside[:, c], groups=["a"] * 10 + ["b"] * 10)
    assert chosen == 1 and report["group_coverage"] == [pytest.approx([1.0, 0.8]), pytest.approx([0.9, 0.8])]
    with pytest.raises(InvalidParameterError, match="one label per push"):
        calibrated_choice(rows, lambda c: inside[:, c], groups=["a"] * 19)


def test_of_settings_calibrated_alike_the_sharper_is_kept_and_a_sharp_miscalibrated_one_is_not():
    """Three settings alike in likelihood over 40 pushes: the first's regions hold 36 truths (0.9) and are the
    widest, the second's 37 (0.925: within the noise of 40 pushes, SE 0.03) and are sharper, the third's 20 (0.5)
    and are the sharpest. The second is kept: as well calibrated as 40 pushes can tell, and it says more."""
    rows = torch.zeros(40, 3, dtype=torch.float64)
    inside = torch.ones(40, 3, dtype=torch.bool)
    inside[:4, 0], inside[:3, 1], inside[:20, 2] = False, False, False
    edge = torch.tensor([-8.0, -6.0, -2.0], dtype=torch.float64).expand(40, 3)
    chosen, report = calibrated_choice(rows, lambda c: (inside[:, c], edge[:, c]))
    assert chosen == 1 and report["calibrated_alike"] == [0, 1]
    assert report["miscalibration"] == pytest.approx([0.0, 0.025, 0.4])
    assert 0.025 < report["miscalibration_se"][1] < 0.06 and report["miscalibration_se"][0] == 0.0
    assert calibrated_choice(rows, lambda c: inside[:, c])[0] == 0  # without thresholds: the least miscalibrated


def test_a_setting_far_worse_on_a_few_pushes_ties_with_nothing():
    """Two settings alike on 57 pushes, one 3,000 nats worse on 3: its mean is 150 nats worse, within 2 plain
    paired SE (85), and its better coverage would choose it."""
    rows = torch.zeros(60, 2, dtype=torch.float64)
    rows[:, 0] = torch.linspace(-1.0, 1.0, 60, dtype=torch.float64)
    rows[:, 1] = rows[:, 0] + 0.01 * torch.linspace(-1.0, 1.0, 60, dtype=torch.float64).flip(0)
    rows[:3, 1] += 3000.0
    inside = torch.stack([torch.zeros(60, dtype=torch.bool), torch.ones(60, dtype=torch.bool)], 1)
    difference = rows[:, 1] - rows[:, 0]
    assert float(difference.mean()) < 2.0 * float(difference.std() / math.sqrt(60))  # tied by the plain SE
    chosen, report = calibrated_choice(rows, lambda c: inside[:, c])
    assert chosen == 0 and report["candidates"] == [0]
    rows[5, 1] = math.inf  # a setting that gives a truth no density is never tied, the likeliest always kept
    assert calibrated_choice(rows, lambda c: inside[:, c])[1]["candidates"] == [0]
