"""The residual model (pushtorch.models.residual, pushtorch.prediction.residual) on real pybullet pushes: the
residual of the simulator against itself is the identity, the density is normalised, the ensemble's batched
rollouts are its single rollouts, and a cloud without a body is refused."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import PushtorchError
from pushtorch.models.residual import DEFENSIVE_PARTS as DEFENSIVE_PARTS_GRID
from pushtorch.models.residual import corrected, residual_of, train_residual_model, with_ensemble
from pushtorch.objects import load_object
from pushtorch.perception import PointCloud, capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.prediction.residual import predict_residual
from pushtorch.sim import make_actions
from pushtorch.sim.bodies import cloud_body, rollout_ensemble
from pushtorch.sim.push import place_robot_against
from pushtorch.sim.settings import SimSettings


@pytest.fixture(scope="module")
def trained(small_cube_residual):
    """The cube, its pybullet pushes (6 per action) and a small model trained on them."""
    return small_cube_residual[:3]


def _observed_push(cube, model):
    """One real pybullet push of the cube (friction 0.2, mass 0.6, action 1) as an observation."""
    from pushtorch.models.conditioning import Observation
    from pushtorch.sim.runner import simulate_pushes

    pose = cube.resting_pose(yaw=0.1)
    robot = place_robot_against(cube.mesh, pose, 0.1, 0.0, 0.002)
    final = simulate_pushes(cube, robot, pose, model.actions[1].double(), mass=0.6, ground_friction=0.2).object_final
    return Observation(capture_partial_cloud(cube, pose), model.actions[1], pose, final.take(0).to(torch.float32),
                       robot)


@pytest.fixture(scope="module")
def residual(small_cube_residual):
    """The small model's residual model against pybullet on its training pushes' cloud bodies (4 rollouts)."""
    return small_cube_residual[3]


def test_the_residual_of_the_simulator_against_itself_is_the_identity(trained):
    """World = the model's simulator, body = the true mesh, physics = the push's own: nothing to correct."""
    cube, records, model = trained
    residual = train_residual_model(model, cube, records, SimSettings(), body_of=lambda obj, pose: (obj, pose))
    for kernels in residual.residuals:
        assert float(kernels.p.norm(dim=-1).max()) < 1e-4
        assert float(se3.angle_between(kernels.q, torch.tensor([1.0, 0.0, 0.0, 0.0]).expand_as(kernels.q)).max()) \
            < 1e-3
    assert residual.meta["training_rollouts"] == int(records.valid.sum())


finite = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)
quat_raw = st.tuples(finite, finite, finite, finite).filter(lambda v: sum(x * x for x in v) > 1e-2)


@st.composite
def poses(draw, n: int = 3) -> se3.Pose:
    p = torch.tensor([[draw(finite) for _ in range(3)] for _ in range(n)], dtype=torch.float64)
    q = torch.tensor([draw(quat_raw) for _ in range(n)], dtype=torch.float64)
    return se3.Pose.unchecked(p, q / q.norm(dim=-1, keepdim=True))


@given(poses(1), poses(), poses(), st.floats(-0.1, 0.1), st.floats(-math.pi, math.pi))
def test_a_residual_carries_a_rollout_to_the_world_and_depends_on_no_frame_but_the_robots(robot, sim, world, slide,
                                                                                         heading):
    """For any poses: corrected(residual_of(...)) is the world's pose; a slide along the robot's heading is a residual
    along its x; moving robot, rollout and world together by any yaw about the vertical leaves the residual."""
    d = residual_of(robot, sim, world)
    back = corrected(robot, sim, d)
    torch.testing.assert_close(back.p, world.p, atol=1e-9, rtol=0)
    assert float(se3.quat_distance(back.q, world.q).max()) < 1e-9
    along = se3.apply(se3.Pose.unchecked(torch.zeros(1, 3, dtype=torch.float64), robot.q),
                      torch.tensor([[slide, 0.0, 0.0]], dtype=torch.float64))
    slid = se3.Pose.unchecked(sim.p + along, sim.q)
    torch.testing.assert_close(residual_of(robot, sim, slid).p,
                               torch.tensor([slide, 0.0, 0.0], dtype=torch.float64).expand(3, 3), atol=1e-9, rtol=0)
    turn = se3.Pose.unchecked(torch.tensor([[0.3, -0.1, 0.0]], dtype=torch.float64),  # a yaw about the vertical
                              torch.tensor([[math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)]],
                                           dtype=torch.float64))
    moved = residual_of(se3.compose(turn, robot), se3.compose(turn, sim), se3.compose(turn, world))
    torch.testing.assert_close(moved.p, d.p, atol=1e-9, rtol=0)
    assert float(se3.quat_distance(moved.q, d.q).max()) < 1e-9


@given(poses(1), poses(1), poses(1), st.floats(-math.pi, math.pi), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_a_rollouts_outcome_is_the_same_wherever_the_push_happened(robot, start, final, yaw, dx, dy):
    """For any poses: moving robot, start and end together by a planar motion leaves the outcome; the turn is
    wrapped into (−π, π]; an outcome resembles itself most."""
    from pushtorch.models.residual import outcome_log_affinity, rollout_outcome

    move = se3.from_xy_yaw(dx, dy, yaw).to(torch.float64)
    here = rollout_outcome(robot, start, final)
    there = rollout_outcome(se3.compose(move, robot), se3.compose(move, start), se3.compose(move, final))
    # (the move is made in float32: 1e-6 is its rounding)
    torch.testing.assert_close(there[..., :2], here[..., :2], atol=1e-6, rtol=0)
    turn = torch.atan2(torch.sin(there[..., 2] - here[..., 2]), torch.cos(there[..., 2] - here[..., 2]))
    assert float(turn.abs().max()) < 1e-6 and float(here[..., 2].abs().max()) <= math.pi
    many = torch.cat([here.reshape(-1, 3), here.reshape(-1, 3) + torch.tensor([[0.05, -0.02, 0.3]],
                                                                              dtype=torch.float64)])
    affinity = outcome_log_affinity(many, many, 0.5)
    assert torch.equal(affinity.argmax(1), torch.arange(2))
    assert torch.equal(outcome_log_affinity(many, many, math.inf), torch.zeros(2, 2, dtype=torch.float64))


def test_the_residual_density_is_normalised_with_its_mode_inside(trained, residual):
    cube, records, model = trained
    pose = cube.resting_pose(yaw=0.3)
    cloud = capture_partial_cloud(cube, pose)
    prediction = predict_residual(residual, cloud, model.actions[1], 0)
    assert prediction.rollouts.p.shape == (4, 3)
    density = prediction.density
    assert abs(float(density.log_normaliser())) < 0.05  # a mixture of normalised kernels integrates to one
    assert torch.isfinite(density.log_prob(prediction.final_pose.vector()))
    draws = density.sample((64,), torch.Generator().manual_seed(0))
    assert torch.isfinite(density.log_prob(draws)).all()
    # the object moved as pushed: forward, in the robot's start frame
    moved = se3.relative(prediction.condition.robot_start, prediction.final_pose).p[0] \
        - se3.relative(prediction.condition.robot_start, prediction.start).p[0]
    assert float(moved) > 0.05
    # the same seed, the same prediction
    again = predict_residual(residual, cloud, model.actions[1], 0)
    torch.testing.assert_close(again.final_pose.vector(), prediction.final_pose.vector(), rtol=0, atol=0)


def test_an_ensemble_rolled_out_in_one_call_is_its_single_rollouts():
    cube = load_object("cube")
    pose = cube.resting_pose(yaw=0.2).to(torch.float64)
    body, start = cloud_body(capture_partial_cloud(cube, pose).points, pose)
    robot = place_robot_against(cube.mesh, pose, 0.2, 0.0, 0.002)
    action = make_actions(3)[2]
    friction = torch.tensor([0.1, 0.4, 0.7], dtype=torch.float64)
    mass = torch.tensor([0.2, 0.5, 2.0], dtype=torch.float64)
    together = rollout_ensemble(body, start, robot, action, friction, mass).object_final
    for i in range(3):
        alone = rollout_ensemble(body, start, robot, action, friction[i:i + 1], mass[i:i + 1]).object_final
        torch.testing.assert_close(alone.p[0], together.p[i], rtol=0, atol=0)
        torch.testing.assert_close(alone.q[0], together.q[i], rtol=0, atol=0)


@pytest.mark.parametrize("engine", ["pybullet", "mujoco"])
def test_an_ensemble_split_over_a_rollout_pool_is_the_same_ensemble(engine):
    """Inside a RolloutPool, rollout_ensemble splits the ensemble over worker processes (a body per task): the
    same records in the same order, bit for bit, as one after another here; the pool is gone after the block."""
    from pushtorch.sim.bodies import RolloutPool, active_rollout_pool

    cylinder = load_object("cylinder")
    pose = cylinder.resting_pose(yaw=-0.3).to(torch.float64)
    body, start = cloud_body(capture_partial_cloud(cylinder, pose).points, pose)
    robot = place_robot_against(cylinder.mesh, pose, -0.1, 0.0, 0.002)
    action = make_actions(3)[0]
    friction = torch.tensor([0.15, 0.3, 0.45, 0.6, 0.9], dtype=torch.float64)
    mass = torch.tensor([0.3, 0.5, 0.8, 1.2, 2.0], dtype=torch.float64)
    settings = SimSettings(engine=engine)
    here = rollout_ensemble(body, start, robot, action, friction, mass, settings)
    with RolloutPool(2) as pool:
        assert active_rollout_pool() is pool
        split = rollout_ensemble(body, start, robot, action, friction, mass, settings)
    assert active_rollout_pool() is None
    for name in ("object_final", "robot_start", "object_initial"):
        torch.testing.assert_close(getattr(split, name).p, getattr(here, name).p, rtol=0, atol=0)
        torch.testing.assert_close(getattr(split, name).q, getattr(here, name).q, rtol=0, atol=0)
    assert torch.equal(split.touched, here.touched) and torch.equal(split.mass, here.mass)
    assert float((here.object_final.p - pose.p).norm(dim=-1).min()) > 0.05  # every rollout pushed the body


@pytest.mark.parametrize("engine", ["pybullet", "mujoco"])
def test_a_push_in_a_map_frame_far_from_the_origin_is_rolled_out_as_at_home(engine):
    """A body 2 km from the origin (beyond the simulated ground) is pushed as it is at home, the outcome moved with
    it: the simulator's ground is flat and alike everywhere."""
    cylinder = load_object("cylinder")
    pose = cylinder.resting_pose(yaw=0.2).to(torch.float64)
    body, start = cloud_body(capture_partial_cloud(cylinder, pose).points, pose)
    robot = place_robot_against(cylinder.mesh, pose, 0.2, 0.0, 0.002)
    friction = torch.tensor([0.2, 0.6], dtype=torch.float64)
    mass = torch.tensor([0.5, 1.5], dtype=torch.float64)
    settings = SimSettings(engine=engine)
    home = rollout_ensemble(body, start, robot, make_actions(3)[2], friction, mass, settings)
    shift = torch.tensor([1000.0, -2000.0, 0.0], dtype=torch.float64)
    far = rollout_ensemble(body, se3.Pose.unchecked(start.p + shift, start.q),
                           se3.Pose.unchecked(robot.p.double() + shift, robot.q), make_actions(3)[2], friction, mass,
                           settings)
    for name in ("object_final", "object_initial", "robot_start"):
        torch.testing.assert_close(getattr(far, name).p - shift, getattr(home, name).p, rtol=0, atol=1e-9)
        torch.testing.assert_close(getattr(far, name).q, getattr(home, name).q, rtol=0, atol=1e-9)
    assert float((home.object_final.p - start.p).norm(dim=-1).min()) > 0.05  # it was pushed


def test_a_cloud_with_no_body_is_refused_with_a_clear_error(trained, residual):
    cube, records, model = trained
    g = torch.Generator().manual_seed(0)
    flat = torch.rand(400, 3, generator=g) * torch.tensor([0.1, 0.1, 0.0])  # on the floor: no volume
    with pytest.raises(PushtorchError):
        predict_residual(residual, PointCloud(flat), model.actions[0], 0)
    with pytest.raises(PushtorchError, match="volume"):
        cloud_body(flat, se3.identity())


def test_a_residual_model_file_round_trips_and_refuses_another_engine_version(trained, residual, tmp_path):
    import dataclasses

    from pushtorch.errors import RecordFormatError
    from pushtorch.models.model import load_model
    from pushtorch.models.residual_file import load_residual_model

    cube, records, model = trained
    residual = with_ensemble(residual, 3)
    path = residual.save(tmp_path / "cube_residual.npz")
    back = load_residual_model(path)
    assert (back.ensemble, back.sim, back.engine_version) == (3, residual.sim, residual.engine_version)
    assert back.outcome_width == residual.outcome_width
    assert all(torch.equal(a, b) for a, b in zip(back.outcomes, residual.outcomes, strict=True))
    for a, b in zip(back.residuals, residual.residuals, strict=True):
        torch.testing.assert_close(a.p, b.p, rtol=0, atol=0)
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=-0.2))
    one = predict_residual(residual, cloud, model.actions[0], 5)
    two = predict_residual(back, cloud, model.actions[0], 5)
    torch.testing.assert_close(one.final_pose.vector(), two.final_pose.vector(), rtol=0, atol=0)
    assert load_model(path).name == model.name  # the push model inside reads as one
    with pytest.raises(RecordFormatError, match="without residuals"):
        load_residual_model(model.save(tmp_path / "plain.npz"))
    other = dataclasses.replace(residual, engine_version="pybullet 0.0.1")
    other.save(tmp_path / "other.npz")
    with pytest.raises(RecordFormatError, match="other_engine"):
        load_residual_model(tmp_path / "other.npz")
    assert load_residual_model(tmp_path / "other.npz", other_engine=True).engine_version == "pybullet 0.0.1"


def test_conditioned_on_observed_pushes_the_ensemble_draws_from_the_posterior(trained, residual):
    """condition_on conditions the push model inside; the ensemble's friction and mass are drawn by the kernels'
    posterior weights (here all weight on one kernel: every draw is its push's physics)."""
    import dataclasses

    cube, records, model = trained
    residual = with_ensemble(residual, 6)
    seen = _observed_push(cube, model)
    conditioned = residual.condition_on([seen], seed=0)
    assert conditioned.model.physics_posterior.observed == 1 and residual.model.physics_posterior is None
    motion = model.motions[1]
    weights = torch.full((len(motion.manipulator),), -60.0)
    weights[2] = 0.0
    one = dataclasses.replace(motion, manipulator=dataclasses.replace(motion.manipulator, log_weight=weights))
    focused = dataclasses.replace(residual, model=dataclasses.replace(model, motions=[model.motions[0], one,
                                                                                      model.motions[2]]))
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.0))
    drawn = predict_residual(focused, cloud, model.actions[1], 0).physics
    torch.testing.assert_close(drawn, motion.manipulator.physics[2].double().expand(6, 2))


def test_predict_predict_many_and_a_library_take_residual_models(trained, residual):
    """The library's interface works unchanged with residual models: predict and predict_many give each condition
    the residual prediction predict_residual gives it (predict_many's per-condition seeds as for push models), and
    a library of residual models selects, conditions and predicts with them."""
    from pushtorch.models.library import ConditionedLibrary, ModelLibrary
    from pushtorch.models.push_condition import features_for
    from pushtorch.prediction import ResidualPrediction, predict_many

    cube, records, model = trained
    clouds = [capture_partial_cloud(cube, cube.resting_pose(yaw=y)) for y in (0.25, -0.3)]
    alone = predict_residual(residual, clouds[0], model.actions[2], 3)
    through = predict(residual, clouds[0], model.actions[2], torch.Generator().manual_seed(3))
    assert isinstance(through, ResidualPrediction)
    torch.testing.assert_close(through.final_pose.vector(), alone.final_pose.vector(), rtol=0, atol=0)
    torch.testing.assert_close(through.rollouts.p, alone.rollouts.p, rtol=0, atol=0)
    many = predict_many(residual, clouds, model.actions[2], seed=7)
    for i, got in enumerate(many):
        want = predict_residual(residual, clouds[i], model.actions[2], 7 + i)
        torch.testing.assert_close(got.final_pose.vector(), want.final_pose.vector(), rtol=0, atol=0)
    two = with_ensemble(residual, 2)
    library = ModelLibrary([two, residual])
    features = features_for(clouds[1], model.settings, model.position)
    chosen, distances = library.select(features)
    assert chosen is two and distances.shape == (2,)  # equal H_r: the first
    assert len(predict(library, clouds[1], model.actions[0], torch.Generator().manual_seed(1)).rollouts.p) == 2
    seen = _observed_push(cube, model)
    conditioned = library.condition_on([seen], seed=0)
    assert isinstance(conditioned, ConditionedLibrary) and conditioned.observed == 1
    picked = predict(conditioned, clouds[1], model.actions[1], torch.Generator().manual_seed(2))
    assert isinstance(picked, ResidualPrediction)
    assert bool(torch.isfinite(picked.density.log_prob(picked.final_pose.vector())))


def test_a_planners_candidates_of_one_cloud_take_a_residual_model(trained, residual):
    """predict_candidates with a residual model (or a library that chooses one): one pose estimate for every
    candidate, each candidate's rollouts the same whatever its company and order (draws keyed by the candidate), a
    start that touches nothing flagged, log_prob(goal) each density at the goal's motion moved onto its body (−inf
    where not a push, with gradients), and a learned-point model's points the push model's candidate predictions."""
    import dataclasses

    from pushtorch.models.library import ModelLibrary
    from pushtorch.prediction import ResidualCandidates, predict_candidates
    from pushtorch.prediction.residual import learned_point

    cube, records, model = trained
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.25))
    own = predict(model, cloud, model.actions[1], torch.Generator().manual_seed(0)).condition
    starts = [se3.compose(own.robot_start, se3.from_xy_yaw(0.0, dy, 0.0)) for dy in (-0.01, 0.01)]
    far = se3.Pose.unchecked(torch.tensor([5.0, 5.0, 0.0]), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    result = predict_candidates(residual, cloud, [*starts, far], model.actions[1], seed=3)
    assert isinstance(result, ResidualCandidates) and result.valid.tolist() == [True, True, False]
    assert result.reasons[0] is None and "touches none" in result.reasons[2]
    first, second = result.predictions[:2]
    assert torch.equal(first.condition.object_pose.p, second.condition.object_pose.p)  # one estimate for all
    for other in (predict_candidates(residual, cloud, [far, starts[1]], model.actions[1], seed=3),
                  predict_candidates(ModelLibrary([residual]), cloud, [starts[1]], model.actions[1], seed=3)):
        torch.testing.assert_close(other.predictions[-1].rollouts.p, second.rollouts.p, rtol=0, atol=0)
    reseeded = predict_candidates(residual, cloud, starts, model.actions[1], seed=4).predictions[1]
    assert not torch.equal(reseeded.physics, second.physics)  # the call's seed draws the ensembles' physics too
    goal = result.estimate.vector().clone()
    goal[0] += 0.08
    goal.requires_grad_(True)
    scores = result.log_prob(goal)
    assert scores.shape == (3,) and bool(torch.isfinite(scores[:2]).all()) and scores[2] == -math.inf
    target = se3.Pose.unchecked(goal.detach()[:3], goal.detach()[3:])
    for score, made in zip(scores[:2], (first, second), strict=True):
        want = made.density.log_prob(learned_point((result.estimate, target), made.start).vector())
        torch.testing.assert_close(score.detach(), want.reshape(()).to(score), rtol=1e-5, atol=1e-5)
    scores[:2].sum().backward()
    assert bool(torch.isfinite(goal.grad).all()) and float(goal.grad.abs().sum()) > 0
    learned = predict_candidates(dataclasses.replace(residual, point="learned"), cloud, starts, model.actions[1],
                                 seed=3)
    for made, push in zip(learned.predictions, predict_candidates(model, cloud, starts, model.actions[1],
                                                                  seed=3).predictions, strict=True):
        moved = learned_point((push.condition.object_pose, push.final_pose), made.start)
        torch.testing.assert_close(made.final_pose.vector(), moved.vector(), rtol=0, atol=1e-6)


def test_the_predict_app_reads_a_residual_model_file_and_records_its_rollouts_beside_its_density(residual,
                                                                                                 tmp_path):
    """A residual model's file given to the predict app predicts as a residual model: its rollouts and their physics
    are in predictions.json, its displacement and nll are scored, and the recording (read back) draws the rollouts
    beside the density."""
    import json

    from pushtorch import viz
    from pushtorch.apps.predict import predict_from_config

    path = with_ensemble(residual, 3).save(tmp_path / "cube_residual.npz")
    cfg = {"models": [str(path)], "object": {"name": "cube"}, "yaw_deg": 15.0, "actions": [1], "truth_samples": 2,
           "friction": {"kind": "fixed", "value": 0.3}, "mass": {"kind": "fixed", "value": 0.5}, "recording": True}
    summary = predict_from_config(cfg, tmp_path / "p")
    entry = json.loads((tmp_path / "p" / "predictions.json").read_text())["predictions"][0]
    assert entry["model"] == residual.name and len(entry["rollouts"]) == 3 and len(entry["rollout_physics"]) == 3
    assert all(math.isfinite(v) for v in entry["nll"]) and 0 <= summary["hacc_mean"] < 0.5
    paths = viz.read_entity_paths(tmp_path / "p" / "recording.rrd")
    root = "/world/model/prediction/action_1"
    for entity in ("rollouts/finals", "rollouts/paths", "rollouts/start", "rollouts/point", "density/samples",
                   "final_true"):
        assert f"{root}/{entity}" in paths, entity
    assert f"{root}/motion/experts" not in paths


@pytest.mark.slow  # 17-20 s; the tiny quickstart's shape-transfer part trains a pooled residual in the default suite
def test_a_pooled_residual_takes_every_shapes_pushes_holds_one_out_and_widens_across_them(cube_pushes_of, tmp_path,
                                                                                         small_settings):
    """A residual model of a pooled model: each kernel's residual is its own shape's push (records given in another
    order are refused by their physics), a shape held out leaves only the other's kernels, the widening is chosen
    on held-out shapes' pushes, and the file keeps the shapes and the widening (the same prediction back)."""
    import dataclasses

    from pushtorch.errors import InvalidParameterError
    from pushtorch.evaluation.transfer import RESIDUAL_WIDENINGS, choose_residual_widening
    from pushtorch.models.pooled import train_pooled_model
    from pushtorch.models.residual import DEFENSIVE_PARTS, POINTS, UNCORRECTED_RATES
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.sim import Normal, load_records, object_spec, plan_training_pushes, run_plan

    cube, cube_records = cube_pushes_of(6, 1)
    cylinder = load_object("cylinder")
    plan = plan_training_pushes(cylinder, make_actions(3), 4, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=2)
    run_plan(object_spec(cylinder), plan, tmp_path / "cylinder", workers=1, progress=False)
    shapes, records = [cube, cylinder], [cube_records, load_records(tmp_path / "cylinder")]
    pooled = train_pooled_model(shapes, records, dataclasses.replace(small_settings, bandwidth_folds=0),
                                generator=torch.Generator().manual_seed(0))
    residual = train_residual_model(pooled, shapes, records, SimSettings(), ensemble=2)
    assert residual.shape_names == ["cube", "cylinder"]
    for of, kernels, motion in zip(residual.shapes, residual.residuals, pooled.motions, strict=True):
        assert of.shape == (len(kernels.p),) and set(of.tolist()) == {0, 1}
        assert len(motion.manipulator) == len(of)
    with pytest.raises(InvalidParameterError, match="friction and mass differ|kernels come from"):
        train_residual_model(pooled, shapes[::-1], records[::-1], SimSettings())
    held = residual.without_shape(0)
    for of, kernels, motion in zip(held.shapes, held.residuals, held.model.motions, strict=True):
        assert set(of.tolist()) == {1} and len(kernels.p) == len(motion.manipulator) == len(of)
    with pytest.raises(InvalidParameterError):
        residual.without_shape(2)
    widened = choose_residual_widening(residual, shapes, records, pushes_per_shape=1,
                                       generator=torch.Generator().manual_seed(0))
    assert widened.widening in RESIDUAL_WIDENINGS and widened.meta["widening"]["pushes"] > 0
    assert len(widened.meta["widening"]["nll"]) == len(RESIDUAL_WIDENINGS) * len(DEFENSIVE_PARTS) * len(
        UNCORRECTED_RATES)
    assert widened.defensive in DEFENSIVE_PARTS and widened.uncorrected in UNCORRECTED_RATES
    point = widened.meta["widening"]["point"]  # chosen on the held-out shapes' pushes, lowest mean H_acc
    assert point["points"] == list(POINTS) and point["pushes"] > 0
    assert widened.point == point["chosen"] == POINTS[min(range(len(POINTS)), key=point["hacc"].__getitem__)]
    back = load_residual_model(widened.save(tmp_path / "pooled_residual.npz"))
    assert (back.widening, back.shape_names, back.defensive, back.uncorrected, back.point) == (
        widened.widening, widened.shape_names, widened.defensive, widened.uncorrected, widened.point)
    assert all(torch.equal(a, b) for a, b in zip(back.shapes, widened.shapes, strict=True))
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.4))
    one, two = (predict(m, cloud, pooled.actions[1], torch.Generator().manual_seed(4)) for m in (widened, back))
    torch.testing.assert_close(one.final_pose.vector(), two.final_pose.vector(), rtol=0, atol=0)
    assert one.widened_by == pytest.approx(math.sqrt(1 + widened.widening * one.contact_distance2))
    with pytest.raises(InvalidParameterError):  # one object's residual has no shape to hold out
        choose_residual_widening(dataclasses.replace(residual, shapes=None), shapes, records)


def test_rollouts_pair_with_the_kernels_whose_training_rollout_did_the_same(trained, residual):
    """Each kernel keeps what its training rollout did and the width that pairs a prediction's rollouts with them
    was chosen by leave-one-push-out likelihood (the score of the unpaired kernels is one of the candidates); an
    infinite width is the unpaired density, bit for bit, and a narrow one moves the weight onto the kernels whose
    rollout did what the prediction's did."""
    import dataclasses

    from pushtorch.models.residual import OUTCOME_LADDER

    cube, records, model = trained
    assert residual.outcome_width in OUTCOME_LADDER
    assert all(o.shape == (len(r.p), 3) for o, r in zip(residual.outcomes, residual.residuals, strict=True))
    chosen = residual.meta["bandwidth"]
    assert chosen["score"] >= chosen["score_unpaired"]
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=-0.25))
    unpaired = dataclasses.replace(residual, outcome_width=math.inf)
    one = predict_residual(unpaired, cloud, model.actions[0], 6)
    two = predict_residual(dataclasses.replace(residual, outcomes=None), cloud, model.actions[0], 6)
    torch.testing.assert_close(one.density.log_weights, two.density.log_weights, rtol=0, atol=0)
    narrow = predict_residual(dataclasses.replace(residual, outcome_width=0.25), cloud, model.actions[0], 6)
    assert not torch.equal(narrow.density.log_weights, one.density.log_weights)
    assert abs(float(narrow.density.log_weights.exp().sum()) - 1.0) < 1e-5


def test_a_prediction_whose_rollouts_did_something_new_widens_by_its_novelty(trained, residual, tmp_path):
    """The novelty widening: a prediction's rollouts' median outcome novelty ``n`` adds a share ``ν·n / (1 + ν·n)``
    of the training outcomes' spread to the kernels' variances (0: as trained; never wider than the spread), the density
    stays normalised, ``ν`` is chosen across training objects from the grid, and the model file keeps it."""
    import dataclasses

    from pushtorch.errors import InvalidParameterError
    from pushtorch.evaluation.transfer import choose_novelty_widening
    from pushtorch.models.residual import (
        DEFENSIVE_PARTS,
        DISAGREEMENT_WEIGHTS,
        NOVELTY_WIDENINGS,
        UNCORRECTED_RATES,
        outcome_spread,
    )
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.prediction.residual import novelty_factors, rescaled

    cube, records, model = trained
    assert residual.novelty_widening == 0.0
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.35))
    plain = predict_residual(residual, cloud, model.actions[2], 3)
    assert plain.outcome_novelty > 0 and plain.widened_by == 1.0
    wide = dataclasses.replace(residual, novelty_widening=3.0)
    widened = predict_residual(wide, cloud, model.actions[2], 3)
    assert widened.outcome_novelty == plain.outcome_novelty  # the same rollouts
    share = 3.0 * plain.outcome_novelty / (1 + 3.0 * plain.outcome_novelty)
    spread_p, spread_r = outcome_spread(residual.outcomes[2])
    assert widened.outcome_spread == pytest.approx((spread_p, spread_r)) and spread_p > 0 and spread_r > 0
    assert widened.density.bandwidth.p_std == pytest.approx(math.sqrt(plain.density.bandwidth.p_std**2
                                                                      + share * spread_p**2))
    assert widened.density.bandwidth.rot_std == pytest.approx(math.sqrt(plain.density.bandwidth.rot_std**2
                                                                        + share * spread_r**2))
    assert widened.widened_by == pytest.approx(widened.density.bandwidth.p_std / residual.bandwidth.p_std)
    assert rescaled(plain, novelty_factors(plain, 3.0)).bandwidth.p_std == pytest.approx(
        widened.density.bandwidth.p_std)  # how a widening is scored from one prediction
    far = dataclasses.replace(residual, novelty_widening=1e9)  # saturated: the kernels' variance plus the spread's
    assert predict_residual(far, cloud, model.actions[2], 3).density.bandwidth.p_std == pytest.approx(
        math.sqrt(plain.density.bandwidth.p_std**2 + spread_p**2), rel=1e-6)
    assert abs(float(widened.density.log_normaliser())) < 0.05
    back = load_residual_model(wide.save(tmp_path / "widened.npz"))
    assert back.novelty_widening == 3.0
    again = predict_residual(back, cloud, model.actions[2], 3)
    torch.testing.assert_close(again.final_pose.vector(), widened.final_pose.vector(), rtol=0, atol=0)
    # each model's hedges on the pushes it predicted (here the cube's model twice: each scores the other's pushes)
    chosen = choose_novelty_widening([residual, residual], [cube, cube], [records, records], pushes_per_shape=2,
                                     generator=torch.Generator().manual_seed(0), shapes=[cube],
                                     shape_records=[records])  # and a shape no model was trained on
    assert all(m.novelty_widening in NOVELTY_WIDENINGS and m.defensive in DEFENSIVE_PARTS for m in chosen)
    meta = chosen[0].meta["novelty"]
    assert meta["pushes"] == 4 and meta["across"] == ["cube", "cube"] and meta["shapes"] == ["cube"]
    assert meta["own_pushes"] + meta["skipped"] == 6  # two of each action's own pushes, held out
    rates, parts, block = len(UNCORRECTED_RATES), len(DEFENSIVE_PARTS), len(meta["nll"]) // len(DISAGREEMENT_WEIGHTS)
    assert block == len(NOVELTY_WIDENINGS) * parts * rates and meta["disagreement"] == list(DISAGREEMENT_WEIGHTS)
    # of the combinations likelihood cannot tell apart, the sharpest of those whose 90 % regions hold the truths as
    # near 90 % as the nearest within its SE, group by group: the model on each other shape, and on its own
    # pushes (both models are the cube's here), each model on the pushes it predicted
    for model_chosen in chosen:
        meta = model_chosen.meta["novelty"]
        calibration = meta["calibration"]
        candidates, off = calibration["candidates"], calibration["miscalibration"]
        likeliest = min(range(len(meta["nll"])), key=meta["nll"].__getitem__)
        assert calibration["likeliest"] == likeliest == candidates[0] and calibration["level"] == 0.9
        assert all(meta["nll"][c] - meta["nll"][likeliest] <= 2 * se + 1e-12
                   for c, se in zip(candidates, calibration["se"], strict=True))
        assert calibration["groups"] == ["cube's model on cube", "cube's model on its own"]
        assert off == pytest.approx([sum(abs(g - 0.9) for g in gs) / 2 for gs in calibration["group_coverage"]])
        least = min(range(len(candidates)), key=lambda k: (off[k], meta["nll"][candidates[k]]))
        alike = calibration["calibrated_alike"]
        assert candidates[least] in alike and all(off[candidates.index(c)] - off[least] <= calibration[
            "miscalibration_se"][candidates.index(c)] + 1e-8 for c in alike)
        sharp = dict(zip(candidates, calibration["sharpness"], strict=True))
        best = max(alike, key=lambda c: (round(sharp[c], 9), -off[candidates.index(c)], -meta["nll"][c]))
        assert (model_chosen.disagreement, model_chosen.novelty_widening, model_chosen.defensive,
                model_chosen.uncorrected) == (
            DISAGREEMENT_WEIGHTS[best // block], NOVELTY_WIDENINGS[best % block // (parts * rates)],
            DEFENSIVE_PARTS[best // rates % parts], UNCORRECTED_RATES[best % rates])
    with pytest.raises(InvalidParameterError, match="trained in this session"):  # its own pushes cannot be held out
        choose_novelty_widening([load_residual_model(residual.save(tmp_path / "own.npz")), residual], [cube, cube],
                                [records, records], pushes_per_shape=1)
    with pytest.raises(InvalidParameterError, match="two models or more"):
        choose_novelty_widening([residual], [cube], [records])
    with pytest.raises(InvalidParameterError, match="one set per extra shape"):
        choose_novelty_widening([residual, residual], [cube, cube], [records, records], shapes=[cube])


def test_a_prediction_whose_push_model_disagrees_is_hedged_as_if_its_rollouts_were_newer(trained, residual,
                                                                                          tmp_path):
    """The disagreement hedge: ``δ²`` is how far the push model's own point lies from the corrected mode, in the
    training outcomes' stds; a model of weight ``ξ`` hedges with the novelty ``n + ξ·δ²`` (its kernels as a
    novelty ``n + ξ·δ²`` widens them, the mode where it was), through ``predict`` as through ``predict_residual``
    given the push model's prediction, and refuses to predict without it; the file keeps ``ξ``."""
    import dataclasses

    from pushtorch.errors import InvalidParameterError, RecordFormatError
    from pushtorch.models.residual import novelty_share, outcome_disagreement, outcome_spread, rollout_outcome
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.prediction.residual import learned_point

    cube, records, model = trained
    cloud, action = capture_partial_cloud(cube, cube.resting_pose(yaw=0.35)), model.actions[2]
    own = predict(model, cloud, action, torch.Generator().manual_seed(3))
    learned = (own.condition.object_pose, own.final_pose)
    plain = predict_residual(residual, cloud, action, 3, condition=own.condition, learned=learned)
    robot = own.condition.robot_start
    expected = outcome_disagreement(*(rollout_outcome(robot, plain.start, pose) for pose in (
        learned_point(learned, plain.start), plain.final_pose)), residual.outcomes[2])
    assert plain.disagreement == pytest.approx(expected, rel=1e-4) and plain.disagreement > 0
    widening = dataclasses.replace(residual, novelty_widening=3.0)
    hedge = dataclasses.replace(widening, disagreement=2.0)
    assert hedge.needs_learned and not widening.needs_learned
    hedged = predict_residual(hedge, cloud, action, 3, condition=own.condition, learned=learned)
    unhedged = predict_residual(widening, cloud, action, 3, condition=own.condition, learned=learned)
    n = plain.outcome_novelty + 2.0 * plain.disagreement
    assert hedged.outcome_novelty == pytest.approx(n) and hedged.disagreement == pytest.approx(plain.disagreement)
    spread_p, _ = outcome_spread(residual.outcomes[2])
    assert hedged.density.bandwidth.p_std == pytest.approx(math.sqrt(plain.density.bandwidth.p_std**2
                                                                      + novelty_share(3.0, n) * spread_p**2))
    assert hedged.density.bandwidth.p_std > unhedged.density.bandwidth.p_std
    torch.testing.assert_close(hedged.final_pose.vector(), unhedged.final_pose.vector(), rtol=0, atol=0)
    assert abs(float(hedged.density.log_normaliser())) < 0.05
    with pytest.raises(InvalidParameterError, match="hedges by its push model"):
        predict_residual(hedge, cloud, action, 3)
    through = predict(hedge, cloud, action, torch.Generator().manual_seed(3))
    assert through.disagreement > 0 and through.outcome_novelty > through.disagreement
    back = load_residual_model(hedge.save(tmp_path / "hedged.npz"))
    assert back.disagreement == 2.0
    with pytest.raises(RecordFormatError, match="disagreement weight"):
        load_residual_model(dataclasses.replace(hedge, disagreement=-1.0).save(tmp_path / "negative.npz"))


@given(st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3), st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3),
       st.integers(0, 2**16))
def test_a_disagreement_is_a_symmetric_squared_distance_in_the_outcomes_stds(a, b, seed):
    """``δ²(a, b) = δ²(b, a) ≥ 0``, 0 at ``a = b``, and ``δ²`` of outcomes apart by one std of one component is 1."""
    from pushtorch.models.residual import outcome_disagreement

    outcomes = torch.randn(6, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 0.05
    a, b = torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)
    assert outcome_disagreement(a, b, outcomes) == pytest.approx(outcome_disagreement(b, a, outcomes), abs=1e-9)
    assert outcome_disagreement(a, b, outcomes) >= 0 and outcome_disagreement(a, a, outcomes) == 0
    step = a.clone()
    step[0] += outcomes.std(0)[0]
    assert outcome_disagreement(a, step, outcomes) == pytest.approx(1.0)


def test_a_defensive_part_keeps_far_truths_likely_and_the_density_normalised(trained, residual, tmp_path):
    """A defensive part ``(ε0, λ, w)``: the density is ``(1 − ε)`` of the kernels and ``ε`` of the same kernels with
    ``w`` and ``w · DEFENSIVE_TURN`` added to their stds in quadrature (``ε = ε0 + (1 − ε0)·λn / (1 + λn)``),
    normalised, with the same mode and rollouts; a truth far from every kernel is likelier under it and one at the
    mode barely less; the draws come from both parts; it is scored from one prediction as predicted
    (``rescaled``); the file keeps it; a share outside (0, 1) is refused."""
    import dataclasses

    from pushtorch.distribution import DefensiveMixture
    from pushtorch.errors import InvalidParameterError
    from pushtorch.models.residual import DEFENSIVE_TURN
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.prediction.residual import defensive_factors, rescaled

    cube, records, model = trained
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=-0.2))
    plain = predict_residual(residual, cloud, model.actions[0], 5)
    guarded = dataclasses.replace(residual, defensive=(0.1, 0.0, 0.03))  # a share of 0.1 whatever the novelty
    prediction = predict_residual(guarded, cloud, model.actions[0], 5)
    density = prediction.density
    assert isinstance(density, DefensiveMixture) and density.share == 0.1
    torch.testing.assert_close(prediction.final_pose.vector(), plain.final_pose.vector(), rtol=0, atol=0)
    torch.testing.assert_close(density.mode, plain.density.mode, rtol=0, atol=0)
    narrow = density.narrow.bandwidth
    assert density.wide.bandwidth.p_std == pytest.approx(math.hypot(narrow.p_std, 0.03))
    assert density.wide.bandwidth.rot_std == pytest.approx(math.hypot(narrow.rot_std, 0.03 * DEFENSIVE_TURN))
    assert density.wide.bandwidth.p_std > 2 * narrow.p_std
    mode = prediction.final_pose.vector()
    far = mode.clone()
    far[:2] += 0.04  # a truth the corrections missed by 5.7 cm
    assert float(density.log_prob(far)) > float(plain.density.log_prob(far)) + 5.0
    assert float(plain.density.log_prob(mode)) - float(density.log_prob(mode)) < -math.log(0.9) + 1e-4
    # normalised: two normalised parts, weighed 1 − ε and ε
    assert abs(float(density.narrow.log_normaliser())) < 0.05 and abs(float(density.wide.log_normaliser())) < 0.05
    draws = density.wide.sample((64,), torch.Generator().manual_seed(1))
    torch.testing.assert_close(density.log_prob(draws), torch.logaddexp(
        density.narrow.log_prob(draws) + math.log(0.9), density.wide.log_prob(draws) + math.log(0.1)))
    samples = density.sample((2000,), torch.Generator().manual_seed(2))
    wide_ones = ((samples[:, :2] - mode[:2]).norm(dim=-1) > 4 * narrow.p_std).float().mean()
    assert 0.02 < float(wide_ones) < 0.2  # about ε of the draws from the wide part, beyond the narrow one's reach
    f = (1.0, 1.0)
    scored = rescaled(plain, f, (0.1, defensive_factors(plain, f, 0.03)))
    torch.testing.assert_close(scored.log_prob(far), density.log_prob(far))
    back = load_residual_model(guarded.save(tmp_path / "guarded.npz"))
    assert back.defensive == (0.1, 0.0, 0.03)
    with pytest.raises(InvalidParameterError, match="defensive share"):
        DefensiveMixture(density.narrow, density.wide, 1.0)
    # a share that grows with the rollouts' novelty n: λn / (1 + λn)
    n = prediction.outcome_novelty
    assert n > 0
    novel = predict_residual(dataclasses.replace(residual, defensive=(0.0, 0.5 / n, 0.03)), cloud, model.actions[0], 5)
    assert novel.density.share == pytest.approx(1 / 3)


@given(st.sampled_from(DEFENSIVE_PARTS_GRID), st.floats(0.0, 1e12), st.floats(0.0, 1e12))
def test_a_defensive_share_lies_in_its_bounds_and_grows_with_novelty(part, n, more):
    from pushtorch.models.residual import MAX_DEFENSIVE_SHARE, defensive_share

    low, high = defensive_share(part, n), defensive_share(part, n + more)
    assert part[0] - 1e-12 <= low <= high <= MAX_DEFENSIVE_SHARE
    assert (low == 0.0) == (part[0] == 0.0 and (part[1] == 0.0 or n == 0.0))


def test_an_uncorrected_share_puts_the_rollouts_themselves_in_the_density_and_is_scored_as_predicted(
        trained, residual, tmp_path):
    """An uncorrected share ``τ``: a share ``ρ = τn / (1 + τn)`` of the density is the rollouts themselves (each
    ``ρ / N``, widened by the corrections' spread), the corrected kernels keep ``1 − ρ`` and the mode; the density
    stays normalised; a truth centimetres past a rollout gains, and the choice's scorer gives, from a prediction
    without the share, the nll of the prediction with it (the same rollouts), defensive part and novelty widening
    included; the file keeps ``τ``."""
    import dataclasses

    from pushtorch.distribution import DefensiveMixture
    from pushtorch.evaluation.likelihood import nll
    from pushtorch.evaluation.transfer import residual_nll_grid
    from pushtorch.models.residual import (
        DEFENSIVE_PARTS,
        NOVELTY_WIDENINGS,
        UNCORRECTED_RATES,
        correction_spread,
        uncorrected_share,
    )
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.prediction.residual import hedged_density, narrow_density, novelty_factors

    cube, records, model = trained
    pose = cube.resting_pose(yaw=0.3)
    cloud = capture_partial_cloud(cube, pose)
    plain = predict_residual(residual, cloud, model.actions[1], 7)
    n = plain.outcome_novelty
    assert n > 0 and plain.uncorrected_share == 0.0
    rate = 1.0 / n  # a share of one half
    mixed = predict_residual(dataclasses.replace(residual, uncorrected=rate), cloud, model.actions[1], 7)
    torch.testing.assert_close(mixed.rollouts.p, plain.rollouts.p, rtol=0, atol=0)  # the same rollouts
    assert mixed.uncorrected_share == pytest.approx(0.5) == uncorrected_share(rate, n)
    torch.testing.assert_close(mixed.final_pose.vector(), plain.final_pose.vector(), rtol=0, atol=0)  # a hedge
    density = mixed.density
    assert isinstance(density, DefensiveMixture) and density.share == pytest.approx(0.5)
    torch.testing.assert_close(density.narrow.means.p, plain.density.means.p, rtol=0, atol=0)  # the corrected
    torch.testing.assert_close(density.wide.means.p, plain.rollouts.p, rtol=0, atol=1e-6)  # and the rollouts
    spread = correction_spread(residual.residuals[1])
    assert mixed.correction_spread == pytest.approx(spread) and spread[0] > 0 and spread[1] > 0
    assert density.wide.bandwidth.p_std == pytest.approx(math.hypot(plain.density.bandwidth.p_std, spread[0]))
    assert density.wide.bandwidth.rot_std == pytest.approx(math.hypot(plain.density.bandwidth.rot_std, spread[1]))
    assert abs(float(density.narrow.log_normaliser())) < 0.05 and abs(float(density.wide.log_normaliser())) < 0.05
    draws = density.wide.sample((64,), torch.Generator().manual_seed(1))
    torch.testing.assert_close(density.log_prob(draws), torch.logaddexp(
        density.narrow.log_prob(draws) + math.log(0.5), density.wide.log_prob(draws) + math.log(0.5)))
    missed = se3.Pose.unchecked(plain.rollouts.p[0].double() + torch.tensor([0.03, 0.0, 0.0], dtype=torch.float64),
                                plain.rollouts.q[0].double())  # 3 cm past a rollout: the wider rollouts' kernels
    gain = nll(plain.density, missed, plain.start, plain.start, cube.symmetry) - nll(
        mixed.density, missed, plain.start, plain.start, cube.symmetry)
    assert float(gain) > 1.0
    # the choice's scorer, from the prediction without the share, scores the prediction with it
    truth = se3.Pose.unchecked(plain.final_pose.p.double() + torch.tensor([0.01, -0.005, 0.0], dtype=torch.float64),
                               plain.final_pose.q.double())
    nu, part = NOVELTY_WIDENINGS[4], (0.03, 1.0, 0.03)
    both = dataclasses.replace(residual, novelty_widening=nu, defensive=part, uncorrected=rate)
    predicted = predict_residual(both, cloud, model.actions[1], 7)
    want = float(nll(predicted.density, truth, plain.start, plain.start, cube.symmetry)[0])
    scores = residual_nll_grid(plain, truth, plain.start, cube, [novelty_factors(plain, nu)], [part], [rate])
    assert float(scores[0]) == pytest.approx(want, abs=1e-4)
    assert isinstance(predicted.density.wide, DefensiveMixture)  # the defensive part hedged alike
    torch.testing.assert_close(narrow_density(predicted).means.p, plain.density.means.p, rtol=0, atol=0)
    draws = predicted.density.sample((16,), torch.Generator().manual_seed(3))
    assert draws.shape == (16, 7) and bool(torch.isfinite(predicted.density.log_prob(draws)).all())
    # and the density a choice draws from to measure the hedges' calibration is the one the prediction makes
    rebuilt = hedged_density(plain, novelty_factors(plain, nu), part, rate)
    torch.testing.assert_close(rebuilt.log_prob(draws), predicted.density.log_prob(draws))
    grid = residual_nll_grid(plain, truth, plain.start, cube, [novelty_factors(plain, v) for v in NOVELTY_WIDENINGS])
    assert grid.shape == (len(NOVELTY_WIDENINGS) * len(DEFENSIVE_PARTS) * len(UNCORRECTED_RATES),)
    assert bool(torch.isfinite(grid).all())
    back = load_residual_model(both.save(tmp_path / "uncorrected.npz"))
    assert back.uncorrected == rate


@given(st.sampled_from((0.0, 0.01, 0.1, 1.0, 10.0, 1e6)), st.floats(0.0, 1e12, allow_subnormal=False),
       st.floats(0.0, 1e12))
def test_an_uncorrected_share_lies_in_its_bounds_and_grows_with_novelty(rate, n, more):
    from pushtorch.models.residual import MAX_DEFENSIVE_SHARE, uncorrected_share

    low, high = uncorrected_share(rate, n), uncorrected_share(rate, n + more)
    assert 0.0 <= low <= high <= MAX_DEFENSIVE_SHARE
    assert (low == 0.0) == (rate == 0.0 or n == 0.0)


def test_the_kernels_scale_is_chosen_on_held_out_pushes_predicted_as_test_pushes_are(trained, residual, tmp_path):
    """``choose_residual_scale``: each held-out push's own kernels leave the model (``without_pushes``: its
    residuals and its manipulator kernels, no other), and the factor of lowest held-out nll scales the stds; a
    model made eight times too wide is pulled back narrower, one eight times too narrow wider, and a loaded model
    (its kernels no longer know their pushes) is refused with a clear error."""
    import dataclasses

    from pushtorch.errors import InvalidParameterError
    from pushtorch.evaluation.transfer import RESIDUAL_SCALES, choose_residual_scale
    from pushtorch.models.residual_file import load_residual_model

    cube, records, model = trained
    push = model.motions[1].manipulator.push
    without = residual.without_pushes(1, torch.tensor([int(push[0])]))
    dropped = int((push == push[0]).sum())
    assert without.residuals[1].p.shape[0] == residual.residuals[1].p.shape[0] - dropped
    assert len(without.model.motions[1].manipulator) == len(model.motions[1].manipulator) - dropped
    assert int(push[0]) not in without.model.motions[1].manipulator.push.tolist()
    assert [r.p.shape[0] for i, r in enumerate(without.residuals) if i != 1] == \
        [r.p.shape[0] for i, r in enumerate(residual.residuals) if i != 1]
    for factor, pulled in ((8.0, lambda f: f < 1.0), (1 / 8, lambda f: f > 1.0)):
        off = dataclasses.replace(residual, novelty_widening=0.3, bandwidth=dataclasses.replace(
            residual.bandwidth, p_std=residual.bandwidth.p_std * factor, rot_std=residual.bandwidth.rot_std * factor))
        chosen = choose_residual_scale(off, cube, records, 1, torch.Generator().manual_seed(0))
        meta = chosen.meta["scale"]
        assert meta["pushes"] == 3 and len(meta["nll"]) == len(RESIDUAL_SCALES)
        assert meta["chosen"] == RESIDUAL_SCALES[min(range(len(meta["nll"])), key=meta["nll"].__getitem__)]
        assert pulled(meta["chosen"]), (factor, meta)
        assert chosen.bandwidth.p_std == pytest.approx(off.bandwidth.p_std * meta["chosen"])
        assert chosen.novelty_widening == 0.3  # scored unwidened, returned as given
    with pytest.raises(InvalidParameterError, match="trained in this session"):
        choose_residual_scale(load_residual_model(residual.save(tmp_path / "r.npz")), cube, records, 2)
