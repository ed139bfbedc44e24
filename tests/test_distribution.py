"""A prediction's density as a torch distribution (issue 23, item 1): shapes, normalisation, gradients,
batches, devices and dtypes, for both evaluation methods, on real predictions of models trained on real
pybullet pushes.

The Monte Carlo checks integrate the density against a proposal that shares nothing with the importance
sampler of its normaliser: a Gaussian in position and rotation vector around the mode, whose density on
SO(3) (uniform probability measure) is the Gaussian over the Haar density ``(1 − cos θ) / (4π² θ²)`` of
exponential coordinates.
"""

from __future__ import annotations

import math

import pytest
import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.distribution import FinalPoseDistribution
from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.kde import KernelBandwidth, PoseKDE

METHODS = ("fast", "dense")


@pytest.fixture(scope="module")
def predictions(small_model):
    from pushtorch import capture_partial_cloud, load_object
    from pushtorch.prediction import predict_many

    model = small_model("cube")
    prism = load_object("prism_thin")
    clouds = [capture_partial_cloud(prism, prism.resting_pose(yaw=yaw)) for yaw in (0.2, 0.9, -0.4)]
    return predict_many(model, clouds, model.actions[1])


def _monte_carlo_mass(density: FinalPoseDistribution, count: int, seed: int) -> tuple[float, float]:
    """``∫ density`` (and its standard error) by importance sampling from a Gaussian in ``(p, ω)`` — the
    position and the rotation vector relative to the mode — with twice the covariance of the density's
    own samples."""
    mode = density.mode.double()
    drawn = density.sample((4000,), generator=torch.Generator().manual_seed(seed + 1)).double()
    turn = pkt.quaternion_multiply(pkt.quaternion_invert(mode[3:]).expand(drawn.shape[0], 4), drawn[:, 3:])
    turn = torch.where(turn[:, :1] < 0, -turn, turn)
    spread = torch.cat([drawn[:, :3], pkt.quaternion_to_axis_angle(turn)], -1)
    centre = torch.cat([mode[:3], torch.zeros(3, dtype=torch.float64)])
    covariance = 2.0 * torch.cov(spread.T) + 1e-10 * torch.eye(6, dtype=torch.float64)
    proposal = torch.distributions.MultivariateNormal(centre, covariance)
    torch.manual_seed(seed)  # MultivariateNormal.sample takes no generator
    x = proposal.sample((count,))
    omega = x[:, 3:]
    theta = omega.norm(dim=-1)
    q = pkt.quaternion_raw_multiply(mode[3:].expand(count, 4), pkt.axis_angle_to_quaternion(omega))
    log_haar = torch.log((1.0 - torch.cos(theta)) / (4.0 * math.pi**2 * theta**2))
    log_q = proposal.log_prob(x) - log_haar
    ratio = torch.exp(density.log_prob(torch.cat([x[:, :3], q], -1).to(density.mode.dtype)).double() - log_q)
    ratio = torch.where(theta < math.pi, ratio, torch.zeros_like(ratio))  # each rotation once
    return float(ratio.mean()), float(ratio.std() / math.sqrt(count))


@pytest.mark.parametrize("method", METHODS)
def test_a_prediction_is_a_torch_distribution_with_gradients(predictions, method):
    density = predictions[0].density.with_method(method)
    assert isinstance(density, torch.distributions.Distribution)
    assert density.batch_shape == () and density.event_shape == (7,)
    drawn = density.sample((2, 3))
    assert drawn.shape == (2, 3, 7)
    value = drawn.clone().requires_grad_()
    log_prob = density.log_prob(value)
    assert log_prob.shape == (2, 3) and torch.isfinite(log_prob).all()
    log_prob.sum().backward()
    assert torch.isfinite(value.grad).all() and value.grad.abs().sum() > 0
    assert torch.equal(density.mode, predictions[0].final_pose.vector())
    assert torch.isfinite(density.log_prob(density.mode))


def test_both_methods_give_the_same_values(predictions):
    fast = predictions[1].density.with_method("fast")
    values = fast.sample((50,), generator=torch.Generator().manual_seed(4))
    dense = fast.with_method("dense")
    assert torch.allclose(fast.log_prob(values), dense.log_prob(values), atol=2e-3)


@pytest.mark.parametrize("method", METHODS)
def test_the_density_integrates_to_one(predictions, method):
    density = predictions[0].density.with_method(method)
    mass, error = _monte_carlo_mass(density, 40_000, seed=7)
    assert abs(mass - 1.0) < max(0.05, 3 * error), (mass, error)
    assert error < 0.03


def test_full_kernels_integrate_to_one_and_are_finite_with_gradients_everywhere(predictions):
    """``with_kernels("full")``: the kernels the cut-offs approximate, normalised anew; what a planner needs
    (a goal 1 m away still has a finite log density and gradient) and what nll scores."""
    cut = predictions[0].density
    full = cut.with_kernels("full")
    assert full.kernels == "full" and cut.kernels == "cut" and full.with_kernels("cut").kernels == "cut"
    mass, error = _monte_carlo_mass(full, 40_000, seed=11)
    assert abs(mass - 1.0) < max(0.05, 3 * error), (mass, error)
    goal = (cut.mode + torch.tensor([1.0, 0.5, 0, 0, 0, 0, 0])).requires_grad_(True)
    assert cut.log_prob(goal.detach()) == -math.inf
    value = full.log_prob(goal)
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(goal.grad).all() and goal.grad[:2].abs().sum() > 0
    near = cut.sample((64,), generator=torch.Generator().manual_seed(3))
    assert torch.isfinite(full.log_prob(near)).all()  # the full density covers the cut one's support
    with pytest.raises(InvalidParameterError, match="kernels"):
        cut.with_kernels("wide")


def test_one_cut_off_expert_integrates_to_one_without_the_importance_sampler():
    """A single expert of exponent 1 has log Z = 0 exactly: the check covers the cut-off kernels' own
    normalisers (Gaussian mass inside the cut-off, the folded vMF's inside its own)."""
    g = torch.Generator().manual_seed(0)
    p = 0.01 * torch.randn(12, 3, generator=g)
    q = se3.quat_normalize(torch.tensor([1.0, 0, 0, 0]) + 0.05 * torch.randn(12, 4, generator=g))
    bandwidth = KernelBandwidth(0.01, 0.05, cutoff_std=(2.0, 2.0, 5.0))
    density = FinalPoseDistribution(se3.Pose(p, q), torch.zeros(1, 12), bandwidth, torch.zeros(3, dtype=torch.long),
                                    torch.ones(1), torch.cat([p[0], q[0]]))
    assert float(density.log_normaliser()) == 0.0
    mass, error = _monte_carlo_mass(density, 40_000, seed=3)
    assert abs(mass - 1.0) < max(0.03, 3 * error), (mass, error)


@pytest.mark.parametrize("method", METHODS)
def test_gradcheck_in_float64(method):
    g = torch.Generator().manual_seed(1)
    p = 0.02 * torch.randn(10, 3, generator=g, dtype=torch.float64)
    q = se3.quat_normalize(torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
                           + 0.1 * torch.randn(10, 4, generator=g, dtype=torch.float64))
    log_w = torch.randn(3, 10, generator=g, dtype=torch.float64)
    log_w[1, :3] = -math.inf
    bandwidth = KernelBandwidth(0.05, 0.3, cutoff_std=(6.0, 6.0, 5.0))  # wide: no cut-off near the queries
    density = FinalPoseDistribution(se3.Pose(p, q), log_w, bandwidth, torch.zeros(3, dtype=torch.long),
                                    torch.full((3,), 1.0 / 3, dtype=torch.float64), torch.cat([p[0], q[0]]),
                                    method=method)
    value = density.sample((4,), generator=g).double().requires_grad_()
    density.log_normaliser()
    assert torch.autograd.gradcheck(lambda v: density.log_prob(v), (value,), eps=1e-6, atol=1e-5)


def test_a_batch_of_clouds_is_one_distribution(predictions):
    batch = FinalPoseDistribution.from_predictions(predictions)
    assert batch.batch_shape == (3,) and batch.event_shape == (7,)
    drawn = batch.sample((4,))
    assert drawn.shape == (4, 3, 7)
    joint = batch.log_prob(drawn)
    alone = torch.stack([p.density.log_prob(drawn[:, i]) for i, p in enumerate(predictions)], -1)
    assert joint.shape == (4, 3) and torch.allclose(joint, alone, atol=1e-3)  # padding changes nothing
    assert torch.equal(batch.mode[2], predictions[2].final_pose.vector())
    assert torch.allclose(batch.with_method("dense").log_prob(drawn), joint, atol=2e-3)
    for method in METHODS:  # a pose one prediction reaches and the others may not: finite gradients
        goal = drawn[0, 0].clone().requires_grad_()
        log_prob = batch.with_method(method).log_prob(goal)
        log_prob.max().backward()
        assert torch.isfinite(log_prob[0]) and torch.isfinite(goal.grad).all()
        far = torch.tensor([1.0, 2, 3, 1, 0, 0, 0], requires_grad=True)  # nothing reaches it
        batch.with_method(method).log_prob(far).sum().backward()
        assert torch.equal(far.grad, torch.zeros(7))


def test_bad_values_are_refused_by_torch_convention(predictions):
    density = predictions[0].density
    with pytest.raises(InvalidPoseError, match="7"):
        density.log_prob(torch.zeros(4, 6))
    with pytest.raises(InvalidPoseError, match="unit"):
        density.log_prob(torch.zeros(4, 7))
    with pytest.raises(ValueError):  # InvalidPoseError is a ValueError, as torch's validation raises
        density.log_prob(torch.full((7,), math.nan))
    assert isinstance(density.log_prob(torch.tensor([1.0, 2, 3, 1, 0, 0, 0])), torch.Tensor)  # far: -inf
    assert density.log_prob(torch.tensor([1.0, 2, 3, 1, 0, 0, 0])) == -math.inf


def test_bad_values_are_refused_after_torch_compile_turned_torchs_own_checks_off(small_model):
    """torch.compile turns torch.distributions' argument checks off for the whole process when it first runs; a
    density made after that still refuses a misshaped query by name instead of failing inside its arithmetic."""
    from pushtorch import capture_partial_cloud, load_object
    from pushtorch.prediction import predict

    before = torch.distributions.Distribution._validate_args
    try:
        torch.compile(lambda x: x * 2, backend="eager")(torch.ones(2))
        model = small_model("cube")
        cube = load_object("cube")
        density = predict(model, capture_partial_cloud(cube, cube.resting_pose(yaw=0.3)), model.actions[0], 0).density
        with pytest.raises(InvalidPoseError, match="7"):
            density.log_prob(torch.zeros(4, 6))
        with pytest.raises(InvalidPoseError, match="unit"):
            density.log_prob(torch.zeros(4, 7))
    finally:
        torch.distributions.Distribution.set_default_validate_args(before)


def test_sample_shapes_follow_torch_distributions(predictions):
    """An empty sample shape gives an empty tensor, a negative one is refused, and there is no rsample: as
    torch.distributions.Normal does."""
    density = predictions[0].density
    reference = torch.distributions.Normal(torch.zeros(7), torch.ones(7))
    for shape in [(0,), (3, 0), (0, 2)]:
        assert density.sample(shape).shape == reference.sample(shape).shape == (*shape, 7)
    assert density.sample((2, 3)).shape == (2, 3, 7)
    with pytest.raises(ValueError, match="negative"):
        density.sample((-1,))
    with pytest.raises(RuntimeError):  # torch refuses it too, with a RuntimeError from expand
        reference.sample((-1,))
    assert not density.has_rsample
    with pytest.raises(NotImplementedError):
        density.rsample((2,))


def test_a_distribution_moves_to_float64(predictions):
    density = predictions[0].density
    values = density.sample((20,))
    wide = density.to(dtype=torch.float64)
    assert wide.mode.dtype == torch.float64
    assert torch.allclose(wide.log_prob(values.double()).float(), density.log_prob(values), atol=1e-3)


def test_the_uncut_kernels_scored_by_nll_are_normalised_too():
    """The full kernels (kernels="full", what nll scores) use the same kernel normaliser without the cut-offs."""
    from pushtorch.evaluation.likelihood import log_kernel_normaliser

    kde = PoseKDE(se3.identity((1,)), KernelBandwidth(0.01, 0.05, cutoff_std=(math.inf, math.inf, math.inf)))
    cut = PoseKDE(se3.identity((1,)), KernelBandwidth(0.01, 0.05, cutoff_std=(3.0, 3.0, 5.0)))
    # the 3-std cut keeps P(3/2, 4.5) = 97.1 % of the Gaussian and ~97 % of the small-angle rotation mass
    ratio = float(torch.exp(log_kernel_normaliser(cut) - log_kernel_normaliser(kde)))
    assert 0.93 < ratio < 0.95
