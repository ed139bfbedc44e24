"""The transferable push model on real pybullet records (pushtorch.models, pushtorch.predict).

Small sizes keep this fast; the predictor's settings are scaled down from the paper's (kernels,
candidates, steps) but nothing is mocked: real pushes, real meshes, real clouds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, PushtorchError, RecordFormatError
from pushtorch.evaluation import metrics
from pushtorch.evaluation.baselines import mean_motion_prediction, no_motion_prediction
from pushtorch.features import compute_surface_features
from pushtorch.models.contact import (
    bumper_contact_patch,
    environment_feature_weights,
    floor_relations,
    sample_environment_contacts,
)
from pushtorch.models.library import ModelLibrary
from pushtorch.models.model import load_model
from pushtorch.models.motion import local_motions, motion_frames
from pushtorch.models.position import (
    centroid_pose,
    fit_position_model,
    grid_fit_scores,
    surface_fit_scores,
    verify_pose_candidates,
)
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_full_cloud, capture_partial_cloud
from pushtorch.prediction import estimate_pose, predict
from pushtorch.robot import backed_off
from pushtorch.sim.plan import Placement, plan_training_pushes
from pushtorch.sim.priors import Normal
from pushtorch.sim.push import make_actions, place_robot_against
from pushtorch.sim.records import load_records
from pushtorch.sim.runner import run_plan, simulate_pushes
from pushtorch.sim.settings import object_spec

FAST = ModelSettings(query_kernels=1000, anneal_candidates=150, anneal_steps=40, position_frames=2000)
MASS, FRICTION = Normal(0.5, 0.025), Normal(0.3, 0.05)  # the paper's experiment defaults


# The bumper (0.4 m) is wider than the cube (0.2 m): the contact model cannot tell where along it the cube
# sits, so predicted placements spread ~±5 cm laterally; training over that spread lets K^c's contact
# position condition the motion (docs/method.md, "Training placement").
SPREAD_PLACEMENTS = Placement(lateral_jitter=0.05)


def _records(obj, samples_per_action, folder, seed=0, placement=None):
    plan = plan_training_pushes(obj, make_actions(3), samples_per_action, MASS, FRICTION, seed=seed,
                                placement=placement)
    run_plan(object_spec(obj), plan, folder, workers=2, progress=False)
    return load_records(folder)


@pytest.fixture(scope="module")
def cube_records(tmp_path_factory):
    return _records(load_object("cube"), 100, tmp_path_factory.mktemp("cube_pushes"), placement=SPREAD_PLACEMENTS)


@pytest.fixture(scope="module")
def cube_model(cube_records):
    return train_push_model(load_object("cube"), cube_records, FAST, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def cylinder_model(tmp_path_factory):
    cylinder = load_object("cylinder")
    records = _records(cylinder, 10, tmp_path_factory.mktemp("cylinder_pushes"))
    return train_push_model(cylinder, records, FAST, generator=torch.Generator().manual_seed(0))


# -- building blocks ---------------------------------------------------------------------------


def test_environment_weights_prefer_low_extreme_points_and_avoid_chosen_ones():
    g = torch.Generator().manual_seed(0)
    points = torch.rand(500, 3, generator=g) * 0.2
    points = torch.cat([points, torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.1, 0.16]])])  # a low corner, a high middle
    low_far, high_near = 500, 501
    w = environment_feature_weights(points)
    assert w[low_far] > w[high_near]
    chosen = points[low_far].reshape(1, 3)
    assert environment_feature_weights(points, chosen)[low_far] == 0  # w_AG vanishes at a chosen contact
    idx = sample_environment_contacts(points.expand(4, 502, 3), 10, g)
    assert idx.shape == (4, 10)
    assert all(len(set(row.tolist())) == 10 for row in idx)  # never the same feature twice in a push


def test_floor_relation_points_to_the_floor_below():
    g = torch.Generator().manual_seed(1)
    v = se3.Pose(torch.rand(20, 3, generator=g), se3.random_quaternion((20,), g))
    floor = se3.compose(v, floor_relations(v))
    torch.testing.assert_close(floor.p[:, :2], v.p[:, :2])
    assert floor.p[:, 2].abs().max() < 1e-6
    assert se3.quat_distance(floor.q, torch.tensor([1.0, 0, 0, 0])).max() < 1e-6


def test_local_motion_of_a_rigid_frame_reproduces_the_object_motion():
    g = torch.Generator().manual_seed(2)
    b0 = se3.from_xy_yaw(0.3, -0.1, 0.4, z=0.1)
    b1 = se3.from_xy_yaw(0.6, 0.05, 0.9, z=0.1)
    robot = se3.from_xy_yaw(0.0, -0.1, 0.3)
    points = se3.apply(b0, torch.rand(10, 3, generator=g) * 0.1)  # points on the object at b0
    w0 = motion_frames(points, robot)
    m = local_motions(w0, se3.compose(b1, se3.inverse(b0)))
    # the frame carried rigidly by the object ends where the object's motion takes it
    w1 = se3.compose(w0, m)
    expected = se3.compose(b1, se3.relative(b0, w0))
    torch.testing.assert_close(w1.p, expected.p, atol=1e-5, rtol=0)
    assert se3.quat_distance(w1.q, expected.q).max() < 1e-6
    # and shifting back by h = w0^-1 ∘ b0 recovers the object's final pose from any frame
    final = se3.compose(w1, se3.relative(w0, b0))
    torch.testing.assert_close(final.p, b1.p.expand(10, 3), atol=1e-5, rtol=0)


def test_contact_model_frames_touch_the_bumper_and_face_it(cube_model):
    frames = cube_model.contact.frames
    assert len(frames) > 100
    assert (frames.weight > 0).all() and (frames.weight <= 1).all()
    # stored in the object frame: the contacts lie on the face towards the robot (-x), 0.1 m from the centre
    assert (frames.v.p[:, 0] < -0.09).all()
    robot = frames.entity  # v ∘ u, the robot pose each frame implies (object frame)
    assert (robot.p - robot.p[:1]).norm(dim=-1).max() < 1e-4  # all agree on one robot pose


@pytest.mark.parametrize("lateral,skew", [(-0.06, 0.0), (0.0, 0.0), (0.08, 0.0), (0.02, 0.06), (0.0, -0.04)])
def test_contact_patch_says_where_and_how_the_cube_sits_on_the_bumper(lateral, skew):
    """From the single-shot cloud: the patch is the cube's 0.2 m face, centred where the cube sits (the
    bumper passing ``lateral`` m to the cube's left puts the cube at −lateral in the robot frame), at the
    heading of the face relative to the plate (turned ``skew`` rad from square, the robot sees the face's left
    end ahead by tan(skew) per metre: heading +skew), and a
    start backed off along the approach sees the same patch."""
    cube = load_object("cube")
    pose = cube.resting_pose(yaw=0.3)
    cloud = compute_surface_features(capture_partial_cloud(cube, pose))
    start = place_robot_against(cube.mesh, pose, 0.3 + skew, lateral)
    patch = bumper_contact_patch(se3.apply(se3.inverse(start), cloud.p))
    if skew == 0:  # a skewed plate meets a corner first: the patch is the part of the face within 1 cm
        assert float(patch[1] - patch[0]) == pytest.approx(0.2, abs=0.012)
        assert float(patch[:2].mean()) == pytest.approx(-lateral, abs=0.006)
    assert float(patch[2]) == pytest.approx(skew, abs=0.01)
    away = backed_off(start, torch.tensor(0.05))
    torch.testing.assert_close(bumper_contact_patch(se3.apply(se3.inverse(away), cloud.p)), patch, atol=1e-5, rtol=0)


def test_bandwidths_are_chosen_by_held_out_likelihood_and_kept_in_the_model_file(cube_model, tmp_path):
    search = cube_model.meta["bandwidths"]
    assert search["folds"] == 5 and search["held_out"] >= 100
    # the search never keeps a worse set (the configured stds may leave too few pushes: no score, None)
    assert search["score_chosen"] is not None
    assert search["score_start"] is None or search["score_chosen"] > search["score_start"]
    for name, value in search["chosen"].items():
        assert getattr(cube_model.settings, name) == pytest.approx(value)
    # the configured motion stds are floors (the mode must not become one push); the contact kernel is free
    assert cube_model.settings.motion_p_std >= ModelSettings().motion_p_std
    assert cube_model.settings.motion_rot_std >= ModelSettings().motion_rot_std
    assert search["chosen"] != search["start"]
    loaded = load_model(cube_model.save(tmp_path / "cube.npz"))
    assert loaded.settings == cube_model.settings and loaded.meta["bandwidths"] == search


@pytest.mark.slow  # 30 s: trains past the search's bounds
def test_above_its_bounds_the_bandwidth_search_keeps_a_seeded_subsample_of_whole_pushes_and_says_so(
        cube_model, monkeypatch, caplog):
    """Bandwidths chosen at any size: over its memory bounds the search keeps whole pushes (each kept push can be
    held out), so it chooses from data with as many held-out pushes as the bounds allow, and the log says so;
    below them nothing is drawn and every kernel counts. The bounds are lowered here to this model's size (the
    search's own code, on 100 real pushes per action instead of 2,000)."""
    import logging

    import pushtorch.models.bandwidth as bandwidth

    motions = cube_model.motions  # trained in this process: its kernels know their pushes
    g = torch.Generator().manual_seed(0)
    _, full = bandwidth.select_bandwidths(FAST, motions, 5, g)
    assert full.held_out >= 3 * 80 and torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())
    monkeypatch.setattr(bandwidth, "MAX_MANIPULATOR_PUSHES", 40)
    monkeypatch.setattr(bandwidth, "MAX_ENVIRONMENT_KERNELS", 300)  # 30 pushes of 10 environment frames
    with caplog.at_level(logging.INFO, logger="pushtorch.models.bandwidth"):
        _, thin = bandwidth.select_bandwidths(FAST, motions, 5, torch.Generator().manual_seed(0))
    assert thin.held_out == 3 * 30 and thin.score_chosen is not None
    assert caplog.text.count("seeded subsample") == 3 and "kernels of 40 of 100 pushes" in caplog.text
    # the pushes of which no kernel was kept are scored after the search, at the configured and the chosen stds
    assert full.unseen == 0 and full.unseen_start is full.unseen_chosen is None  # every push kept: none unseen
    assert 0 < thin.unseen <= 3 * 60 and thin.unseen_chosen is not None and math.isfinite(thin.unseen_chosen)
    assert caplog.text.count("pushes it never saw") == 1
    _, again = bandwidth.select_bandwidths(FAST, motions, 5, torch.Generator().manual_seed(0))
    assert again.chosen == thin.chosen  # seeded


def test_the_density_takes_its_own_calibrated_width_and_the_mode_keeps_the_floored_one(cube_model):
    """Two widths: the density's motion stds are chosen below the mode's floor by held-out likelihood; the
    returned density uses them, the annealed mode is the one the mode's stds give."""
    settings, search = cube_model.settings, cube_model.meta["bandwidths"]
    assert 0 < settings.density_p_std <= settings.motion_p_std
    assert 0 < settings.density_rot_std <= settings.motion_rot_std
    assert settings.density_p_std < settings.motion_p_std or settings.density_rot_std < settings.motion_rot_std
    assert search["score_density"] >= search["score_chosen"]  # the held-out score it was chosen by, no worse
    cube = load_object("cube")
    start = cube.resting_pose(yaw=0.2)
    cloud = capture_partial_cloud(cube, start)
    g = torch.Generator().manual_seed(4)
    prediction = predict(cube_model, cloud, cube_model.actions[1], g)
    assert prediction.density.bandwidth.p_std == pytest.approx(settings.density_p_std)
    assert prediction.density.bandwidth.rot_std == pytest.approx(settings.density_rot_std)
    # a model whose density stds are its motion stds (a model file from before them): the same mode, wider
    wide = replace(cube_model, settings=replace(settings, density_p_std=0.0, density_rot_std=0.0))
    same = predict(wide, cloud, cube_model.actions[1], torch.Generator().manual_seed(4))
    torch.testing.assert_close(same.final_pose.vector(), prediction.final_pose.vector(), rtol=0, atol=0)
    assert same.density.bandwidth.p_std == pytest.approx(settings.motion_p_std)
    mode = prediction.final_pose.vector()
    assert torch.isfinite(prediction.density.log_prob(mode))  # the mode lies inside the narrower cut-offs
    assert prediction.density.log_prob(mode) > same.density.log_prob(mode)  # narrower: more mass at the mode


def _seen_push(cube_model, yaw: float = 0.1):
    """One observed cube push (μ 0.3, 0.5 kg) of the model's second action."""
    from pushtorch.models.conditioning import Observation

    cube = load_object("cube")
    start = cube.resting_pose(yaw=yaw)
    cloud = capture_partial_cloud(cube, start)
    robot = place_robot_against(cube.mesh, start, yaw, 0.0, 0.002)
    final = simulate_pushes(cube, robot, start, cube_model.actions[1].double(), mass=0.5,
                            ground_friction=0.3).object_final.take(0)
    return Observation(cloud, cube_model.actions[1], start, final.to(torch.float32), robot)


def test_observations_are_weighed_by_the_density_width_not_the_mode_width(cube_model):
    seen = _seen_push(cube_model)

    def posterior_loglik(settings):
        model = replace(cube_model, settings=settings)
        return model.condition_on([seen], seed=0).physics_posterior.log_likelihood

    alone = replace(cube_model.settings, density_outlier=0.0)  # the density's kernels alone
    base = posterior_loglik(alone)
    mode_only = posterior_loglik(replace(alone, motion_p_std=2 * alone.motion_p_std))
    density = posterior_loglik(replace(alone, density_p_std=2 * alone.density_p_std))
    torch.testing.assert_close(mode_only, base)  # without an outlier share the mode's width does not enter
    assert not torch.allclose(density, base)
    # a library weighs every model's observations under its models' widest kernels and largest outlier share,
    # so a model does not win by narrower kernels alone
    from pushtorch.models.evidence import common_evidence_kernels

    own = cube_model.settings
    wider = replace(cube_model, name="wider", settings=replace(own, density_rot_std=3 * own.density_rot_std,
                                                               density_outlier=0.3))
    common = common_evidence_kernels([cube_model, wider])
    assert (common.density.p_std, common.density.rot_std) == (own.density_p_std, 3 * own.density_rot_std)
    assert (common.wide.p_std, common.outlier) == (own.motion_p_std, 0.3)
    conditioned = ModelLibrary([cube_model, wider]).condition_on([seen], seed=0)
    alone = cube_model.condition_on([seen], seed=0, bandwidth=common).physics_posterior.log_likelihood
    torch.testing.assert_close(conditioned.models[0].physics_posterior.log_likelihood, alone)
    torch.testing.assert_close(conditioned.models[1].physics_posterior.log_likelihood, alone)  # same kernels


def test_the_evidence_outlier_share_is_chosen_by_held_out_likelihood_and_bounds_a_surprise(cube_model):
    """Each evidence kernel is (1 − ε) K_density + ε K_mode: ε is chosen on the training pushes (a share the
    held-out score prefers to none is kept only if it scores higher), and an observed push far from every kernel
    costs the model far less than under the density's kernels alone."""
    from pushtorch.models.bandwidth import OUTLIER_LADDER
    from pushtorch.models.evidence import EvidenceKernels

    settings, search = cube_model.settings, cube_model.meta["bandwidths"]
    assert settings.density_outlier in OUTLIER_LADDER
    if settings.density_outlier > 0:
        assert search["score_outlier"] > search["score_density"]
    else:
        assert search["score_outlier"] == search["score_density"]
    kernels = EvidenceKernels(settings.density_bandwidth, settings.motion_bandwidth, 0.1)
    means = se3.Pose.unchecked(torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    for miss in (0.0, 0.01, 0.05):  # m along x
        y = se3.Pose.unchecked(torch.tensor([miss, 0.0, 0.0]), torch.tensor([1.0, 0.0, 0.0, 0.0]))
        robust = float(kernels.log_kernels(means, y)[0])
        narrow = float(EvidenceKernels.of(settings.density_bandwidth).log_kernels(means, y)[0])
        wide = float(EvidenceKernels.of(settings.motion_bandwidth).log_kernels(means, y)[0])
        # a mixture of two normalised densities: between its parts' log densities, and above each part's weighted
        assert min(narrow, wide) - 1e-9 <= robust <= max(narrow, wide) + 1e-9
        assert robust >= max(narrow + math.log(0.9), wide + math.log(0.1)) - 1e-9
    assert narrow < robust - 10  # 5 cm off: tens of nats under the narrow kernels alone, not under the mixture
    with pytest.raises(InvalidParameterError, match="density_outlier"):
        ModelSettings(density_outlier=1.0)


def test_model_settings_reject_bad_values():
    with pytest.raises(InvalidParameterError, match="query_kernels"):
        ModelSettings(query_kernels=0)
    with pytest.raises(InvalidParameterError, match="unknown model settings"):
        ModelSettings.from_mapping({"query_kernel": 10})
    with pytest.raises(InvalidParameterError, match="fast_anneal_fraction"):
        ModelSettings(fast_anneal_fraction=1.5)
    with pytest.raises(InvalidParameterError, match="polish_steps"):
        ModelSettings(polish_steps=-1)
    with pytest.raises(InvalidParameterError, match="polish_steps"):
        ModelSettings(polish_steps=1.5)
    assert ModelSettings(polish_steps=0).polish_steps == 0  # no polish: the fast path only anneals
    assert ModelSettings().fast_anneal_steps == 30 and ModelSettings(anneal_steps=2).fast_anneal_steps == 1


# -- acceptance ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, yaws",
    [
        ("cube", (0.3, 1.2, 2.0)),
        pytest.param("cylinder", (0.0, 1.0, 2.0), marks=pytest.mark.slow),  # its turn is free: a check of position
        ("modified_cube", (math.pi, math.pi - 0.3, math.pi + 0.3)),
    ],
)
def test_position_model_beats_the_centroid_and_finds_the_orientation(name, yaws):
    obj = load_object(name)
    training_pose = obj.resting_pose()
    full = compute_surface_features(capture_full_cloud(obj, training_pose))
    keep = torch.randperm(len(full), generator=torch.Generator().manual_seed(0))[:3000]
    position = fit_position_model(full.select(keep), training_pose)
    settings = replace(FAST, query_kernels=2000, anneal_candidates=300, anneal_steps=60)
    ours, centroid, angles = [], [], []
    for i, yaw in enumerate(yaws):
        truth = obj.resting_pose(0.05 * i, -0.04 * i, yaw)
        cloud = capture_partial_cloud(obj, truth)
        est = estimate_pose(position, cloud, settings, torch.Generator().manual_seed(i)).pose
        acc = metrics.accuracy(est, truth, obj)
        ours.append(acc.linear_cm.item())
        angles.append(acc.angular_deg.item())
        centroid.append(metrics.linear_error_cm(centroid_pose(cloud.points), truth).item())
    assert sum(ours) / len(ours) < sum(centroid) / len(centroid), (ours, centroid)
    assert sum(angles) / len(angles) < 15.0, angles


def _fresh_push_errors(model, obj, n_conditions, seed):
    """H_acc of pushtorch, no-motion and mean-motion on fresh pushes (ground truth from pybullet)."""
    g = torch.Generator().manual_seed(seed)
    actions = model.actions
    ours, still, mean = [], [], []
    for c in range(n_conditions):
        truth0 = obj.resting_pose(yaw=float(torch.rand((), generator=g)) * math.pi / 2 - math.pi / 4)
        cloud = compute_surface_features(capture_partial_cloud(obj, truth0))
        mass, friction = float(MASS.sample((), g)), float(FRICTION.sample((), g))
        for a, action in enumerate(actions):
            pred = predict(model, cloud, action, torch.Generator().manual_seed(seed * 1000 + c * 10 + a))
            gt = simulate_pushes(obj, pred.condition.robot_start, truth0, action, mass, friction)
            truth1 = se3.Pose(gt.object_final.p[0].float(), gt.object_final.q[0].float())
            estimate0 = pred.condition.object_pose
            ours.append(metrics.accuracy(pred.final_pose, truth1, obj).hacc.item())
            still.append(metrics.accuracy(no_motion_prediction(estimate0), truth1, obj).hacc.item())
            baseline = mean_motion_prediction(model.motions[a], pred.condition.robot_start, estimate0)
            mean.append(metrics.accuracy(baseline, truth1, obj).hacc.item())
    return [sum(x) / len(x) for x in (ours, still, mean)]


@pytest.mark.slow  # 30 fresh predictions and pushes, about 65 s: the default suite was past ten minutes on 2 cores
def test_cube_model_predicts_fresh_cube_pushes_better_than_no_motion(cube_model):
    ours, still, mean = _fresh_push_errors(cube_model, load_object("cube"), n_conditions=10, seed=3)
    assert ours < still, (ours, still)
    # the gain over the mean training motion comes from conditioning on where the cube sits along the
    # bumper (seeds 6–8, 90 pushes the test does not use: ours − mean = −0.0031 ± 0.0009; docs/method.md)
    assert ours < mean, (ours, mean)


def test_cube_model_transfers_to_the_thin_prism(cube_model):
    ours, still, _ = _fresh_push_errors(cube_model, load_object("prism_thin"), n_conditions=2, seed=4)
    assert ours < still, (ours, still)


def test_selection_picks_the_model_of_the_matching_shape(cube_model, cylinder_model):
    library = ModelLibrary([cube_model, cylinder_model])
    expected = {"cube": "cube", "prism_thin": "cube", "prism_long": "cube",
                "cylinder": "cylinder", "cylinder_wide": "cylinder"}
    hits = total = 0
    for name, want in expected.items():
        obj = load_object(name)
        for yaw in (0.0, 0.4, 0.9, 1.3):
            features = compute_surface_features(capture_partial_cloud(obj, obj.resting_pose(yaw=yaw)))
            chosen, h_r = library.select(features)
            hits += chosen.object_name == want
            total += 1
    assert hits / total >= 0.9


def test_saved_model_predicts_identically_and_tampering_is_refused(cube_model, tmp_path):
    path = cube_model.save(tmp_path / "cube.npz")
    loaded = load_model(path)
    cube = load_object("cube")
    cloud = compute_surface_features(capture_partial_cloud(cube, cube.resting_pose(yaw=0.2)))
    action = cube_model.actions[0]
    a = predict(cube_model, cloud, action, torch.Generator().manual_seed(7))
    b = predict(loaded, cloud, action, torch.Generator().manual_seed(7))
    torch.testing.assert_close(a.final_pose.p, b.final_pose.p)
    torch.testing.assert_close(a.final_pose.q, b.final_pose.q)
    torch.testing.assert_close(a.condition.robot_start.p, b.condition.robot_start.p)

    import numpy as np

    with np.load(path, allow_pickle=False) as archive:
        arrays = {k: archive[k] for k in archive.files}
    arrays["contact.weight"] = arrays["contact.weight"] * 0.5
    tampered = tmp_path / "tampered.npz"
    np.savez(tampered, **arrays)
    with pytest.raises(RecordFormatError, match="checksum"):
        load_model(tampered)
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(RecordFormatError):
        load_model(tmp_path / "junk.npz")


def test_surface_fit_verification_prefers_the_pose_that_explains_the_cloud():
    """The notched cube seen with its notch in view: the true pose explains the cloud, a pose turned by
    90 degrees about z (a plain cube's symmetry, not this object's) does not, whatever the densities say."""
    obj = load_object("modified_cube")
    training_pose = obj.resting_pose()
    full = compute_surface_features(capture_full_cloud(obj, training_pose))
    keep = torch.randperm(len(full), generator=torch.Generator().manual_seed(0))[:3000]
    position = fit_position_model(full.select(keep), training_pose)
    truth = obj.resting_pose(0.02, -0.03, math.pi)
    observed = capture_partial_cloud(obj, truth).points
    turned = obj.resting_pose(0.02, -0.03, math.pi + math.pi / 2)
    candidates = se3.Pose(torch.stack([turned.p, truth.p]), torch.stack([turned.q, truth.q]))
    scores = surface_fit_scores(position, observed, candidates)
    assert scores[1] < 0.005 < scores[0], scores  # mm-level fit against points left unexplained
    # the density would prefer the turned pose; the fit overrules it, and a zero-density pose never wins
    chosen = verify_pose_candidates(position, observed, candidates, torch.tensor([0.0, -5.0]))
    assert int(chosen) == 1
    assert int(verify_pose_candidates(position, observed, candidates, torch.tensor([0.0, -math.inf]))) == 0
    with pytest.raises(PushtorchError):
        surface_fit_scores(position, observed[:0], candidates)
    with pytest.raises(PushtorchError):
        grid_fit_scores(position, observed[:0], candidates)
    # the screen's grid reads the same fit to within a fraction of the gap between the two poses
    many = se3.Pose(torch.cat([candidates.p, candidates.p + 0.01]), torch.cat([candidates.q, candidates.q]))
    exact, grid = surface_fit_scores(position, observed, many), grid_fit_scores(position, observed, many)
    assert (grid - exact).abs().max() < 0.2 * (scores[0] - scores[1]), (grid, exact)
    assert torch.equal(grid.argsort(), exact.argsort())
