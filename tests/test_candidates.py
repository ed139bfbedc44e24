"""A planner's candidates (pushtorch.prediction.predict_candidates): many robot starts and actions of one real
cloud in one call, its per-cloud work done once, bad starts flagged rather than failing the call, and one batched
density that scores a goal for every candidate with gradients."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.distribution import FinalPoseDistribution
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import SharedKernelProduct
from pushtorch.models.conditioning import Observation
from pushtorch.models.experts import MotionDensity, candidate_products
from pushtorch.models.frames import ContactFrames
from pushtorch.models.library import ModelLibrary
from pushtorch.models.motion import contact_log_weights
from pushtorch.models.push_condition import candidate_conditions, features_for
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict_candidates
from pushtorch.sim.push import place_robot_against
from pushtorch.sim.runner import simulate_pushes


@pytest.fixture(scope="module")
def scene():
    cube = load_object("cube")
    pose = cube.resting_pose(yaw=0.2)
    base = place_robot_against(cube.mesh, pose)
    starts = [se3.compose(base, se3.from_xy_yaw(0.0, -0.04 + 0.02 * k, 0.0)) for k in range(5)]
    far, inside = se3.from_xy_yaw(5.0, 5.0, 0.0), se3.from_xy_yaw(0.0, 0.0, 0.0)
    return capture_partial_cloud(cube, pose), starts, far, inside


def test_candidates_of_one_cloud_share_its_estimate_and_flag_starts_that_are_not_pushes(small_model, scene):
    model = small_model("cube")
    cloud, starts, far, inside = scene
    actions = torch.stack([model.actions[k % 3] for k in range(7)])
    result = predict_candidates(model, cloud, [*starts[:3], far, *starts[3:], inside], actions, chunk_size=2)
    assert result.valid.tolist() == [True, True, True, False, True, True, False]
    assert "touches none" in result.reasons[3] and "overlaps the observed object" in result.reasons[6]
    kept = [p for p in result.predictions if p is not None]
    # the cloud's work done once: one pose estimate, one set of environment frames per action
    assert all(p.condition.object_pose is kept[0].condition.object_pose for p in kept)
    for p in kept:
        same = [q for q in kept if torch.equal(q.action, p.action)]
        assert all(q.condition.environment_frames is p.condition.environment_frames for q in same)
    assert result.density.batch_shape == (5,) and result.density.kernels == "full"
    goal = kept[1].final_pose.vector().detach().clone().requires_grad_()
    scores = result.log_prob(goal)
    assert scores.shape == (7,) and math.isinf(float(scores[3].detach())) and math.isinf(float(scores[6].detach()))
    assert torch.isfinite(scores[result.valid]).all()
    scores[result.valid].sum().backward()
    assert torch.isfinite(goal.grad).all() and float(goal.grad.abs().sum()) > 0
    # each candidate's density is the one its own prediction carries
    index = int(result.valid.nonzero()[1])
    own = result.predictions[index].density.with_kernels("full").log_prob(goal.detach())
    assert abs(float(scores[index].detach()) - float(own)) < 1e-3


def test_a_library_chooses_its_model_once_per_cloud(small_model, scene):
    cloud, starts, _, _ = scene
    library = ModelLibrary([small_model("cube"), small_model("cylinder")])
    result = predict_candidates(library, cloud, se3.Pose.stack(starts), library.models[0].actions[1])
    names = {p.model_name for p in result.predictions}
    assert len(names) == 1 and names <= {m.name for m in library.models} and bool(result.valid.all())


def test_bad_candidate_inputs_are_refused_by_name(small_model, scene):
    model = small_model("cube")
    cloud, starts, _, _ = scene
    with pytest.raises(InvalidParameterError, match="at least one candidate"):
        predict_candidates(model, cloud, [], model.actions[0])
    with pytest.raises(InvalidParameterError, match="2 actions for 5"):
        predict_candidates(model, cloud, starts, model.actions[:2])
    with pytest.raises(InvalidParameterError, match="chunk_size"):
        predict_candidates(model, cloud, starts, model.actions[0], chunk_size=0)
    with pytest.raises(InvalidParameterError, match="normaliser_samples"):
        predict_candidates(model, cloud, starts, model.actions[0], normaliser_samples=0)
    bad = se3.Pose.unchecked(torch.tensor([math.nan, 0.0, 0.0]), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(InvalidPoseError):
        predict_candidates(model, cloud, [starts[0], bad], model.actions[0])
    with pytest.raises(InvalidParameterError):
        predict_candidates(model, cloud, starts, torch.tensor([0.1, 0.9]))  # not one of the model's actions
    widening = replace(model, settings=replace(model.settings, transfer_widening=2.0))  # a calibrated pooled model's
    with pytest.raises(ModelError, match="transfer_widening=2"):
        predict_candidates(widening, cloud, starts, model.actions[0])


def _final_poses(result) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.stack([p.final_pose.p for p in result.predictions]),
            torch.stack([p.final_pose.q for p in result.predictions]))


@pytest.fixture(scope="module")
def one_by_one(small_model, scene):
    model = small_model("cube")
    cloud, starts, _, _ = scene
    actions = torch.stack([model.actions[k % 3] for k in range(len(starts))])
    return _final_poses(predict_candidates(model, cloud, starts, actions, seed=3, chunk_size=1))


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(order=st.permutations(range(5)), chunk=st.integers(1, 6))
@example(order=[0, 2, 1, 3, 4], chunk=1)  # the actions met in another order (their environment frames' draws)
def test_no_order_or_chunk_size_changes_a_candidates_prediction(small_model, scene, one_by_one, order, chunk):
    """The counter-based stream: candidate i's draws are keyed by its index, so batched equals one by one within
    1e-4 m and 1e-4 rad (float rounding of padded products is all that differs)."""
    model = small_model("cube")
    cloud, starts, _, _ = scene
    actions = torch.stack([model.actions[k % 3] for k in range(len(starts))])
    p, q = _final_poses(predict_candidates(model, cloud, [starts[i] for i in order], actions[list(order)], seed=3,
                                           chunk_size=chunk))
    ref_p, ref_q = one_by_one
    back = torch.argsort(torch.tensor(order))  # candidate i's result sits at order.index(i)
    assert float((p[back] - ref_p).norm(dim=-1).max()) < 1e-4
    angle = 2 * torch.acos((q[back] * ref_q).sum(-1).abs().clamp(max=1.0))
    assert float(angle.max()) < 1e-4


def test_contact_weights_of_many_pushes_in_one_call_are_each_pushs_own(small_model, scene):
    """The batched contact weights a planner's candidates share one call for: frames (C, F), starts (C,) and
    patches (C, 3) give each candidate the weights (trial rounds included) it gets alone."""
    model = small_model("cube")
    cloud, starts, _, _ = scene
    features = features_for(cloud, model.settings, model.position)
    conditions, _ = candidate_conditions(model, features, starts, [1] * len(starts), torch.Generator().manual_seed(0))
    kernels, bandwidth = model.motions[1].environment, model.settings.contact_bandwidth
    env = conditions[0].environment_frames
    count = len(conditions)
    shared = env.expand(count)
    together = contact_log_weights(shared, kernels, se3.Pose.stack([c.robot_start for c in conditions]), bandwidth,
                                   torch.stack([c.contact_patch for c in conditions]))
    assert together.shape == (count, len(env), len(kernels))
    for c, batched in zip(conditions, together, strict=True):
        alone = contact_log_weights(env, kernels, c.robot_start, bandwidth, c.contact_patch)
        assert torch.equal(torch.isfinite(alone), torch.isfinite(batched))
        assert torch.allclose(alone[torch.isfinite(alone)], batched[torch.isfinite(batched)], atol=1e-5)


def test_products_built_at_once_are_each_candidates_own_product(small_model, scene):
    """The planner's batched construction (candidate_products, no density object per candidate) gives every
    candidate the product of experts its own MotionDensity is: the same log-density at poses drawn from it."""
    model = small_model("cube")
    cloud, starts, _, _ = scene
    features = features_for(cloud, model.settings, model.position)
    conditions, _ = candidate_conditions(model, features, starts, [2] * len(starts), torch.Generator().manual_seed(0))
    settings, motion = model.settings, model.motions[2]
    stacked = candidate_products(motion, ContactFrames.stack([c.manipulator_frame for c in conditions]),
                                 conditions[0].environment_frames, conditions[0].object_pose,
                                 se3.Pose.stack([c.robot_start for c in conditions]),
                                 torch.stack([c.contact_patch for c in conditions]), settings.contact_bandwidth,
                                 settings.motion_bandwidth)
    together = SharedKernelProduct(stacked.means, stacked.log_weights, stacked.bandwidth, stacked.trial_rounds,
                                   expert_exponent=stacked.exponent)
    alone = [MotionDensity(motion, c.manipulator_frame, c.environment_frames, c.object_pose, c.robot_start,
                           c.contact_patch, settings.contact_bandwidth, settings.motion_bandwidth) for c in conditions]
    queries = se3.Pose.stack([d.proposal(24, torch.Generator().manual_seed(k)) for k, d in enumerate(alone)])
    batched = together.log_prob(queries)
    each = torch.stack([d.log_prob(queries.take(k), "fast") for k, d in enumerate(alone)])
    assert torch.equal(torch.isfinite(batched), torch.isfinite(each)) and bool(torch.isfinite(each).any())
    finite = torch.isfinite(each)
    assert torch.allclose(batched[finite], each[finite], rtol=1e-4, atol=1e-3)
    assert stacked.means.batch_shape[1] == max(d.shared_kernels()[0].batch_shape[0] for d in alone)


def test_a_conditioned_model_and_one_over_its_kernel_budget_predict_candidates_each_as_alone(small_model, scene):
    """A conditioned model (its kernels re-weighted by an observed push) takes the batched construction; a model
    whose kernels exceed the prediction's budget (as a pooled model's do) builds each candidate's density alone
    from its nearest kernels. Both give each candidate the prediction it gets in a chunk of one."""
    model = small_model("cube")
    cloud, starts, _, _ = scene
    cube = load_object("cube")
    pose = cube.resting_pose(yaw=0.1)
    start = place_robot_against(cube.mesh, pose)
    pushed = simulate_pushes(cube, start, pose, model.actions[1], 0.5, 0.3)
    observed = Observation(capture_partial_cloud(cube, pose), model.actions[1], pose,
                           se3.Pose(pushed.object_final.p[0], pushed.object_final.q[0]), start)
    half = len(model.motions[0].environment) // 2
    budget = replace(model, settings=replace(model.settings, environment_kernels=half))
    actions = torch.stack([model.actions[k % 3] for k in range(len(starts))])
    for variant in (model.condition_on([observed]), budget):
        together = predict_candidates(variant, cloud, starts, actions, seed=1, chunk_size=5)
        alone = predict_candidates(variant, cloud, starts, actions, seed=1, chunk_size=1)
        assert bool(together.valid.all())
        gap = max(float((a.final_pose.p - b.final_pose.p).norm())
                  for a, b in zip(together.predictions, alone.predictions, strict=True))
        assert gap < 1e-4
        assert torch.isfinite(together.log_prob(together.predictions[0].final_pose.vector())).all()


def test_the_candidates_normalisers_are_made_at_once_each_from_its_own_draws(small_model, scene):
    """The planner's normalisers: all candidates' in one batched estimate, each from draws keyed by its candidate
    (the same value in the batch as in the candidate's own density), and each within the estimator's noise of the
    one-at-a-time estimate with 16 times the samples (the seed spread at 64 samples is about 0.012 nats)."""
    model = small_model("cube")
    cloud, starts, _, _ = scene
    actions = torch.stack([model.actions[k % 3] for k in range(len(starts))])
    result = predict_candidates(model, cloud, starts, actions, seed=2)
    batch = result.density
    together = batch.log_normaliser()
    alone = torch.stack([p.density.with_kernels("full").log_normaliser() for p in result.predictions])
    assert together.shape == (len(starts),) and torch.allclose(together, alone, atol=1e-9)
    reference = FinalPoseDistribution(batch.means, batch.log_weights, batch.bandwidth, batch.trial_rounds,
                                      batch.exponent, batch.mode, batch.method, batch.normaliser_centres,
                                      kernels=batch.kernels, normaliser_samples=1024).log_normaliser()
    assert float((together - reference).abs().max()) < 0.06
