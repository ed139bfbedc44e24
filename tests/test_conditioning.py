"""Online adaptation (pushtorch.models.conditioning): real pybullet pushes at known friction move the posterior
towards it, conditioning is sequential, deterministic and survives save and load, and bad observations neither
move nor break it."""

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError, PushtorchError
from pushtorch.models.conditioning import Observation, PhysicsPosterior, ess_floor, new_posterior
from pushtorch.models.library import ModelLibrary
from pushtorch.models.model import load_model
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud

SETTINGS = ModelSettings(query_kernels=400, anneal_candidates=60, anneal_steps=15, position_frames=800,
                         environment_kernels=300, manipulator_kernels=40)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The cube, its actions, and models trained on real pushes: general friction U(0.085, 0.805), low N(0.1),
    high N(0.7) (mass N(0.5, 0.025) kg), and general mass U(0.085, 5.75) kg (friction N(0.3, 0.05))."""
    from pushtorch.sim import Normal, Uniform, load_records, make_actions, object_spec, plan_training_pushes, run_plan

    obj, actions = load_object("cube"), make_actions(3)
    models = {}
    for name, friction, mass, count in (("general", Uniform(0.085, 0.805), Normal(0.5, 0.025), 30),
                                        ("low", Normal(0.1, 0.005), Normal(0.5, 0.025), 12),
                                        ("high", Normal(0.7, 0.035), Normal(0.5, 0.025), 12),
                                        ("mass", Normal(0.3, 0.05), Uniform(0.085, 5.75), 30)):
        plan = plan_training_pushes(obj, actions, count, mass, friction, seed=1)
        folder = tmp_path_factory.mktemp(f"cube_{name}")
        run_plan(object_spec(obj), plan, folder, workers=2, progress=False)
        models[name] = train_push_model(obj, load_records(folder), SETTINGS, name=name,
                                        generator=torch.Generator().manual_seed(0))
    return obj, actions, models


def observe(obj, actions, mu: float, count: int, seed: int, mass: float = 0.5,
            odometry: bool = False) -> list[Observation]:
    """``count`` real pushes of the cube at ground friction ``mu`` and ``mass``, from the start its training pushes
    had, as observations (with the robot's own final pose where ``odometry``)."""
    from pushtorch.sim.push import place_robot_against
    from pushtorch.sim.runner import simulate_pushes

    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(count):
        yaw = float(torch.rand(1, generator=g)) * 1.2 - 0.6
        pose = obj.resting_pose(0.0, 0.0, yaw)
        action = actions[int(torch.randint(0, len(actions), (1,), generator=g))]
        start = place_robot_against(obj.mesh, pose, yaw, 0.0, 0.002)  # as the models' training pushes start
        pushed = simulate_pushes(obj, start, pose, action, mass, mu)
        final, robot = pushed.object_final, pushed.robot_trajectory
        cloud = capture_partial_cloud(obj, pose, voxel_size=SETTINGS.voxel_size)
        out.append(Observation(cloud, action, pose, se3.Pose(final.p[0], final.q[0]), start,
                               se3.Pose(robot.p[0, -1], robot.q[0, -1]) if odometry else None))
    return out


def kernel_weights(model) -> torch.Tensor:
    return torch.cat([k.log_weight for m in model.motions for k in (m.manipulator, m.environment)])


def test_observed_friction_moves_the_posterior_and_chooses_the_library_model(world):
    obj, actions, models = world
    low, high = observe(obj, actions, 0.1, 4, seed=3), observe(obj, actions, 0.7, 4, seed=3)
    prior = models["general"].posterior()
    after_low = models["general"].condition_on(low).posterior()
    after_high = models["general"].condition_on(high).posterior()
    assert after_low.observed == after_high.observed == 4 and after_low.rejected == 0
    assert after_low.mu_mean < prior.mu_mean < after_high.mu_mean  # each towards the friction it saw
    library = ModelLibrary([models["general"], models["low"], models["high"]])
    for observations, expected in ((low, "low"), (high, "high")):
        conditioned = library.condition_on(observations)
        chosen = conditioned.models[int(conditioned.model_log_posterior().argmax())]
        assert chosen.name == expected
        weights = conditioned.posterior().model_weights
        assert weights[expected] == max(weights.values())


def test_the_robots_odometry_tells_light_from_heavy(world):
    """A loaded robot falls behind its command: its own final pose is evidence about the mass."""
    obj, actions, models = world
    model = models["mass"]
    prior = model.posterior()
    light = model.condition_on(observe(obj, actions, 0.3, 3, seed=4, mass=0.1, odometry=True)).posterior()
    heavy = model.condition_on(observe(obj, actions, 0.3, 3, seed=4, mass=5.0, odometry=True)).posterior()
    assert light.log_mass_mean < prior.log_mass_mean < heavy.log_mass_mean
    # the same pushes without the odometry say less: the posterior stays wider
    blind = model.condition_on(observe(obj, actions, 0.3, 3, seed=4, mass=5.0)).posterior()
    assert heavy.log_mass_std < blind.log_mass_std


def test_conditioning_is_sequential_deterministic_and_survives_save_and_load(world, tmp_path):
    obj, actions, models = world
    model = models["general"]
    observations = observe(obj, actions, 0.1, 3, seed=5)
    batch = model.condition_on(observations, seed=7)
    one_by_one = model.condition_on(observations[:1], seed=7).condition_on(observations[1:2]).condition_on(
        observations[2:])
    torch.testing.assert_close(kernel_weights(one_by_one), kernel_weights(batch), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(kernel_weights(model.condition_on(observations, seed=7)), kernel_weights(batch),
                               rtol=0, atol=0)
    # conditioning commutes with saving and loading, either way round
    reloaded = load_model(model.save(tmp_path / "general.npz"))
    torch.testing.assert_close(kernel_weights(reloaded.condition_on(observations, seed=7)), kernel_weights(batch))
    saved = load_model(model.condition_on(observations[:2], seed=7).save(tmp_path / "conditioned.npz"))
    assert saved.physics_posterior.observed == 2
    torch.testing.assert_close(kernel_weights(saved.condition_on(observations[2:])), kernel_weights(batch),
                               rtol=1e-6, atol=1e-6)
    # a conditioned model predicts as a model does, with its density
    from pushtorch.prediction import predict

    cloud = capture_partial_cloud(obj, obj.resting_pose(0.0, 0.0, 0.2), voxel_size=SETTINGS.voxel_size)
    prediction = predict(batch, cloud, actions[0], generator=0)
    assert torch.isfinite(prediction.density.log_prob(prediction.density.mode)).all()


def test_bad_observations_leave_the_weights_unchanged_or_are_refused(world, caplog):
    obj, actions, models = world
    model = models["general"]
    good = observe(obj, actions, 0.4, 1, seed=9)[0]
    base = model.condition_on([good])
    far = Observation(good.cloud, good.action, good.initial_pose,
                      se3.Pose(good.final_pose.p + torch.tensor([1.0, 0.0, 0.0]), good.final_pose.q), good.robot_start)
    tipped_q = se3.from_xy_yaw(0.0, 0.0, 0.0).q.new_tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    thrown = Observation(good.cloud, good.action, good.initial_pose,
                         se3.Pose(good.final_pose.p + torch.tensor([0.0, 0.0, 0.3]), tipped_q), good.robot_start)
    with caplog.at_level("WARNING"):
        after = base.condition_on([far, thrown])
    assert "explained by no kernel" in caplog.text
    assert after.physics_posterior.rejected == 2 and after.physics_posterior.observed == 1
    torch.testing.assert_close(kernel_weights(after), kernel_weights(base))
    with pytest.raises(InvalidPoseError):
        Observation(good.cloud, good.action, good.initial_pose,
                    se3.Pose.unchecked(torch.tensor([math.nan, 0.0, 0.0]), good.final_pose.q))
    with pytest.raises(InvalidParameterError, match="action"):
        model.condition_on([Observation(good.cloud, [0.3, 0.0], good.initial_pose, good.final_pose, good.robot_start)])
    with pytest.raises(InvalidParameterError, match="Observation"):
        model.condition_on(["not an observation"])
    import dataclasses

    old = dataclasses.replace(model, motions=[dataclasses.replace(
        m, manipulator=dataclasses.replace(m.manipulator, physics=None)) for m in model.motions])
    with pytest.raises(ModelError, match="retrain"):
        old.condition_on([good])
    assert issubclass(ModelError, PushtorchError)


@given(st.lists(st.floats(-500.0, 0.0), min_size=16, max_size=16), st.integers(1, 40))
def test_kernel_weights_stay_finite_and_keep_the_effective_sample_size_floor(cells, spread):
    """Whatever the observations' log-likelihoods, the kernel weights are finite and their effective sample size
    stays at or above the stated floor."""
    theta = torch.stack([torch.linspace(0.1, 0.8, 40 * spread, dtype=torch.float64),
                         torch.full((40 * spread,), math.log(0.5), dtype=torch.float64)], -1)
    from pushtorch.models.motion import MotionKernels

    kernels = MotionKernels(torch.zeros(len(theta), 2), se3.identity((len(theta),)),
                            se3.identity((len(theta),)), torch.zeros(len(theta), 3), torch.zeros(len(theta), 3),
                            physics=torch.stack([theta[:, 0], theta[:, 1].exp()], -1).float())
    posterior: PhysicsPosterior = new_posterior([kernels])
    count = posterior.centres.shape[0]
    assert 10 <= count <= 16  # 0.7 of μ in cells of at least 0.05, one mass cell
    posterior = posterior.with_evidence(torch.tensor(cells[:count], dtype=torch.float64))
    log_w, tau = posterior.kernel_log_weights(theta)
    assert torch.isfinite(log_w).all() and 0.0 <= tau <= 1.0
    w = (log_w - log_w.max()).exp()
    assert float(w.sum() ** 2 / (w**2).sum()) >= ess_floor(len(theta)) * (1 - 1e-6)
