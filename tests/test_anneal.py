"""Simulated annealing over SE(3), batched over candidates and problems (pushtorch.anneal)."""

import math

import pytest
import torch

from pushtorch import se3
from pushtorch.anneal import AnnealResult, AnnealSchedule, anneal, initial_candidates, polish_candidates
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import AnnealInputs, AnnealOutcome, KernelBandwidth, PoseKDE, ProductOfExperts
from pushtorch.kde.annealing import anneal_chains

BANDWIDTH = KernelBandwidth(p_std=0.01, rot_std=0.15, cutoff_std=(3.0, 3.0, 3.0))


def axis_angle(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float32)
    axis = axis / axis.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)]), math.sin(angle / 2) * axis])


def two_kernel_kde(mode, other, weights=(0.7, 0.3)):
    """Two kernels further apart than the cut-offs: the density's global mode is exactly ``mode``."""
    means = se3.Pose.stack([mode, other], dim=-1)
    return PoseKDE(means, BANDWIDTH, torch.tensor(weights).log().expand(means.batch_shape))


def scatter(pose: se3.Pose, p_std, rot_std, generator) -> se3.Pose:
    """Start points scattered around ``pose`` (inside the kernel's support, not on its mean)."""
    return se3.perturb(pose, p_std, 4.0 / rot_std**2, generator)


def test_annealing_finds_the_global_mode_of_a_bimodal_density():
    g = torch.Generator().manual_seed(0)
    mode = se3.Pose(torch.tensor([0.1, -0.05, 0.02]), axis_angle([0.2, 1.0, 0.3], 0.8))
    other = se3.Pose(torch.tensor([0.3, 0.1, 0.0]), axis_angle([1.0, 0.0, 0.0], 2.0))
    kde = two_kernel_kde(mode, other)
    start = initial_candidates(kde, 64, g)  # about 70 % at the mode's kernel, 30 % at the other
    init = scatter(start, 0.012, 0.15, g)
    result = anneal(kde, init, AnnealSchedule(steps=120, step_p_std=0.003, step_rot_std=0.05), g)
    assert isinstance(result, AnnealResult)
    assert result.best.p.shape == (3,) and result.best_log_prob.shape == ()
    assert (result.best.p - mode.p).norm() < 0.002  # 0.2 kernel std
    assert se3.angle_between(result.best.q, mode.q) < 0.03
    assert result.best_log_prob == pytest.approx(math.log(0.7), abs=0.05)
    # candidates keep their local modes: the chains started at the other kernel end there
    near_other = (result.candidates.p - other.p).norm(dim=-1) < 0.005
    assert near_other.any() and not near_other.all()


def test_annealing_improves_the_chains_and_never_loses_the_best():
    g = torch.Generator().manual_seed(1)
    mode = se3.Pose(torch.tensor([0.0, 0.0, 0.0]), axis_angle([0.0, 0.0, 1.0], 0.3))
    kde = PoseKDE(se3.Pose(mode.p[None], mode.q[None]), BANDWIDTH)
    init = scatter(mode.expand(200), 0.012, 0.2, g)
    init_lp = kde.log_prob(init)
    result = anneal(kde, init, AnnealSchedule(steps=100), g, record_history=True)
    assert result.history.p.shape == (101, 200, 3) and result.history_log_prob.shape == (101, 200)
    finite = torch.isfinite(init_lp)
    assert finite.float().mean() > 0.5
    assert (result.log_prob[finite] >= init_lp[finite]).all()  # per-candidate best never drops
    torch.testing.assert_close(result.log_prob, kde.log_prob(result.candidates))
    mean_lp = torch.stack([h[torch.isfinite(h)].mean() for h in result.history_log_prob])
    quarters = mean_lp[[0, 25, 50, 75, 100]]
    assert (quarters.diff() > -0.05).all(), quarters  # monotone up to Monte-Carlo noise
    assert mean_lp[-1] > mean_lp[0] + 1.0
    assert mean_lp[-1] > -0.2  # chains end close to the mode (log K(μ|μ) = 0)


def test_batched_problems_are_solved_independently():
    g = torch.Generator().manual_seed(2)
    modes = se3.Pose(torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.2, -0.1]]),
                     torch.stack([axis_angle([0, 0, 1], 0.5), axis_angle([1, 1, 0], -1.0)]))
    others = se3.Pose(torch.tensor([[0.2, 0.0, 0.0], [0.5, -0.2, -0.1]]),
                      torch.stack([axis_angle([0, 1, 0], 2.0), axis_angle([0, 0, 1], 1.0)]))
    kde = two_kernel_kde(modes, others, weights=(0.6, 0.4))
    assert kde.batch_shape == (2,)
    init = scatter(initial_candidates(kde, 48, g), 0.01, 0.15, g)
    result = anneal(kde, init, AnnealSchedule(steps=100), g)
    assert result.best.p.shape == (2, 3) and result.candidates.p.shape == (2, 48, 3)
    assert ((result.best.p - modes.p).norm(dim=-1) < 0.003).all()
    assert (se3.angle_between(result.best.q, modes.q) < 0.04).all()
    # the same problem alone gives a solution of the same quality
    alone = anneal(PoseKDE(se3.Pose(kde.means.p[1], kde.means.q[1]), BANDWIDTH, kde.log_weights[1]),
                   se3.Pose(init.p[1], init.q[1]), AnnealSchedule(steps=100), g)
    assert (alone.best.p - modes.p[1]).norm() < 0.003


def test_product_of_experts_is_maximised_between_two_gaussian_experts():
    g = torch.Generator().manual_seed(3)
    q = axis_angle([0, 0, 1], 0.2)
    a = se3.Pose(torch.tensor([[0.0, 0.0, 0.0]]), q[None])
    b = se3.Pose(torch.tensor([[0.02, 0.0, 0.0]]), q[None])
    experts = PoseKDE.stack([PoseKDE(a, BANDWIDTH), PoseKDE(b, BANDWIDTH)])
    poe = ProductOfExperts(experts, torch.tensor([0.0, math.log(2.0)]))
    init = scatter(se3.Pose(torch.tensor([0.01, 0.0, 0.0]), q).expand(64), 0.008, 0.1, g)
    result = anneal(poe, init, AnnealSchedule(steps=100), g)
    # exp(−|p−a|²/σ) exp(−|p−b|²/σ) peaks at (a+b)/2 with value exp(−|a−b|²/(2σ)); w^P adds log 2
    assert (result.best.p - torch.tensor([0.01, 0.0, 0.0])).norm() < 0.002
    assert result.best_log_prob == pytest.approx(math.log(2.0) - 0.02**2 / (2 * BANDWIDTH.sigma_p), abs=0.05)


def test_planar_annealing_keeps_height_roll_and_pitch():
    g = torch.Generator().manual_seed(4)
    tilt = axis_angle([1.0, 0.3, 0.0], 0.4)
    mode = se3.Pose(torch.tensor([0.1, 0.2, 0.05]), tilt)
    kde = PoseKDE(se3.Pose(mode.p[None], mode.q[None]), BANDWIDTH)
    yawed = se3.compose(se3.from_xy_yaw(0.0, 0.0, 0.2), mode).q
    start = se3.Pose(mode.p + torch.tensor([0.01, -0.008, 0.0]), yawed)
    init = start.expand(32)
    result = anneal(kde, init, AnnealSchedule(steps=80, planar=True), g, record_history=True)
    # height and the world-z row of the rotation matrix (roll/pitch) never change
    torch.testing.assert_close(result.history.p[..., 2], torch.full((81, 32), 0.05), rtol=0, atol=1e-7)
    rows = se3.to_matrix(se3.Pose(result.history.p, result.history.q))[..., 2, :3]
    torch.testing.assert_close(rows, se3.to_matrix(mode)[2, :3].expand(81, 32, 3), rtol=0, atol=1e-5)
    # x, y and yaw did move to the mode
    assert (result.best.p[:2] - mode.p[:2]).norm() < 0.002
    assert se3.angle_between(result.best.q, mode.q) < 0.02


def test_candidates_at_zero_density_move_to_any_finite_proposal_or_stay():
    g = torch.Generator().manual_seed(5)
    mode = se3.Pose(torch.zeros(3), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    kde = PoseKDE(se3.Pose(mode.p[None], mode.q[None]), BANDWIDTH)
    edge = torch.tensor([0.0305, 0.0, 0.0])  # just beyond the 3-std cut-off (0.03 m)
    far = torch.tensor([1.0, 0.0, 0.0])
    init = se3.Pose(torch.stack([edge] * 16 + [far] * 4), mode.q.expand(20, 4))
    assert (kde.log_prob(init) == -math.inf).all()
    result = anneal(kde, init, AnnealSchedule(steps=50), g)
    assert torch.isfinite(result.log_prob[:16]).all()  # they entered the support
    assert (result.log_prob[16:] == -math.inf).all()
    torch.testing.assert_close(result.candidates.p[16:], init.p[16:], rtol=0, atol=0)


def test_annealing_is_reproducible_with_a_seed():
    kde = PoseKDE(se3.Pose(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]])), BANDWIDTH)
    init = se3.Pose(torch.full((8, 3), 0.01), torch.tensor([[1.0, 0, 0, 0]]).expand(8, 4))
    runs = [anneal(kde, init, AnnealSchedule(steps=20), torch.Generator().manual_seed(9)) for _ in range(2)]
    assert torch.equal(runs[0].candidates.p, runs[1].candidates.p)
    assert torch.equal(runs[0].candidates.q, runs[1].candidates.q)


def test_initial_candidates_are_kernel_means_drawn_by_weight():
    g = torch.Generator().manual_seed(6)
    means = se3.Pose(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]),
                     se3.random_quaternion((3,), g))
    kde = PoseKDE(means, BANDWIDTH, torch.tensor([0.6, 0.4, 0.0]).log())
    init = initial_candidates(kde, 4000, g)
    assert init.p.shape == (4000, 3)
    index = init.p[:, 0].round().long()
    assert (index < 2).all()
    torch.testing.assert_close(init.q, means.q[index])
    assert abs((index == 0).float().mean().item() - 0.6) < 0.03


def test_schedule_and_inputs_are_validated():
    temperatures = AnnealSchedule(steps=5, t_start=1.0, t_end=0.2).temperatures()
    assert temperatures == pytest.approx([1.0, 0.8, 0.6, 0.4, 0.2])
    for bad in (dict(steps=-1), dict(t_end=0.0), dict(energy_scale=math.nan), dict(step_p_std=-0.1)):
        with pytest.raises(InvalidParameterError):
            AnnealSchedule(**bad)
    kde = PoseKDE(se3.Pose(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]])), BANDWIDTH)
    init = se3.Pose(torch.zeros(4, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(4, 4))
    with pytest.raises(ModelError, match="shape"):
        anneal(lambda pose: kde.log_prob(pose)[:2], init)
    with pytest.raises(ModelError, match="NaN"):
        anneal(lambda pose: torch.full(pose.p.shape[:-1], math.nan), init)
    with pytest.raises(InvalidPoseError):
        anneal(kde, se3.Pose(torch.zeros(3), torch.tensor([1.0, 0, 0, 0])))
    with pytest.raises(InvalidPoseError):
        anneal(kde, se3.Pose(torch.zeros(4, 3), torch.tensor([[2.0, 0, 0, 0]]).expand(4, 4)))


@pytest.mark.parametrize("bad_value, message", [(math.nan, "NaN"), (math.inf, r"\+inf")])
def test_fast_annealing_reports_a_density_that_goes_bad_after_the_start(bad_value, message):
    """The fast loop checks values once at the end: a NaN or +inf met at any step must still be raised."""
    init = se3.Pose(torch.zeros(8, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(8, 4))
    calls = []

    def density(pose):
        calls.append(1)
        values = -(pose.p**2).sum(-1)
        return values if len(calls) < 30 else torch.full_like(values, bad_value)

    with pytest.raises(ModelError, match=message):
        anneal(density, init, AnnealSchedule(steps=50), torch.Generator().manual_seed(0), method="fast")
    assert len(calls) == 51  # the initial evaluation and one per step: no early exit hides the check


def test_polish_moves_short_annealing_onto_the_mode_and_never_loses_likelihood():
    """Few annealing steps leave the chains scattered; the mean-shift polish takes each onto its local
    mode (here exactly a kernel mean), never lowers a candidate's likelihood, and is recorded as a step."""
    g = torch.Generator().manual_seed(3)
    mode = se3.Pose(torch.tensor([0.1, -0.05, 0.02]), axis_angle([0.2, 1.0, 0.3], 0.8))
    other = se3.Pose(torch.tensor([0.3, 0.1, 0.0]), axis_angle([1.0, 0.0, 0.0], 2.0))
    kde = two_kernel_kde(mode, other)
    init = scatter(initial_candidates(kde, 64, g), 0.012, 0.15, g)
    short = anneal(kde, init, AnnealSchedule(steps=3), g, record_history=True)
    assert (short.best.p - mode.p).norm() > 1e-4  # three steps do not reach the mode
    polished = polish_candidates(short, kde.mean_shift, kde.log_prob, steps=2)
    assert bool((polished.log_prob >= short.log_prob).all())
    assert (polished.best.p - mode.p).norm() < 1e-5  # one kernel in reach: its mean in one step
    assert polished.best_log_prob == pytest.approx(math.log(0.7), abs=1e-5)
    assert polished.history.p.shape[0] == short.history.p.shape[0] + 1
    assert torch.equal(polished.history.p[-1], polished.candidates.p)
    assert polish_candidates(short, kde.mean_shift, kde.log_prob, steps=0) is short
    with pytest.raises(InvalidParameterError):
        polish_candidates(short, kde.mean_shift, kde.log_prob, steps=-1)


def test_a_density_that_anneals_itself_is_handed_the_drawn_steps():
    """On the fast path the annealer hands the steps it drew to a density's ``fused_anneal`` (duck-typed): one
    that declines (None, nothing drawn) is annealed by the generic loop over its values, one that takes them
    reports its outcome — the same stream either way — and its start values are checked like any others."""
    mode = se3.Pose(torch.tensor([0.1, -0.05, 0.02]), axis_angle([0.2, 1.0, 0.3], 0.8))
    other = se3.Pose(torch.tensor([0.3, 0.1, 0.0]), axis_angle([1.0, 0.0, 0.0], 2.0))
    kde = two_kernel_kde(mode, other)
    init = scatter(initial_candidates(kde, 32, torch.Generator().manual_seed(1)), 0.01, 0.1,
                   torch.Generator().manual_seed(2))

    class Density:
        def __init__(self, takes: bool, start_value: float | None = None):
            self.takes, self.start_value, self.offers = takes, start_value, 0

        def __call__(self, pose):
            return kde.log_prob(pose)

        def fused_anneal(self, inputs: AnnealInputs) -> AnnealOutcome | None:
            self.offers += 1
            if not self.takes:
                return None
            start = kde.log_prob(inputs.start)
            if self.start_value is not None:
                start = torch.full_like(start, self.start_value)
            return anneal_chains(kde.log_prob, inputs, start)

    schedule = AnnealSchedule(steps=30)
    runs = {}
    for name, density in [("function", kde.log_prob), ("declines", Density(False)), ("takes", Density(True))]:
        runs[name] = anneal(density, init, schedule, torch.Generator().manual_seed(3), method="fast")
        assert getattr(density, "offers", 1) == 1
    for name in ("declines", "takes"):
        assert torch.equal(runs[name].candidates.p, runs["function"].candidates.p)
        assert torch.equal(runs[name].log_prob, runs["function"].log_prob)
    assert (runs["takes"].log_prob > kde.log_prob(init)).any()
    dense = Density(True)
    anneal(dense, init, schedule)
    assert dense.offers == 0  # the dense reference loop never hands its steps over
    with pytest.raises(ModelError, match="NaN"):
        anneal(Density(True, start_value=math.nan), init, schedule, method="fast")
