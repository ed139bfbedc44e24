"""The fast prediction path against the dense reference (kde fast path, anneal, query, motion, predict).

The fused functions run eagerly here (``PUSHTORCH_COMPILE=0``) so the checks stay fast; the compiled
path runs the same functions and is checked by the slow test at the end and by tools/bench_predict.py.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

from pushtorch import se3
from pushtorch.anneal import AnnealSchedule, anneal, initial_candidates
from pushtorch.errors import InvalidParameterError
from pushtorch.kde import (
    FAST_DENSE_KERNELS,
    AnnealInputs,
    DrawnSteps,
    KernelBandwidth,
    PoseKDE,
    ProductOfExperts,
    SharedKernelProduct,
    fused_function,
)
from pushtorch.kde.annealing import anneal_chains
from pushtorch.kde.fast_index import FastIndex
from pushtorch.models.frames import embed_descriptors
from pushtorch.models.query import (
    _fast_kernel_draws,
    _group_weight_sums,
    feature_distance_heuristic,
    neighbourhood_log_weights,
)
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict, predict_many


@pytest.fixture(autouse=True)
def _eager(monkeypatch):
    monkeypatch.setenv("PUSHTORCH_COMPILE", "0")


def _random_kde(n, batch=(), seed=0, dtype=torch.float64, spread=0.05, rot_spread=0.3, bandwidth=None,
                rounds=None):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(*batch, n, 3, generator=g, dtype=dtype) * spread
    axis = torch.randn(*batch, n, 3, generator=g, dtype=dtype) * rot_spread
    q = pose_quaternion(axis)
    log_w = torch.randn(*batch, n, generator=g, dtype=dtype)
    bw = bandwidth or KernelBandwidth(p_std=0.01, rot_std=0.1)
    return PoseKDE(se3.Pose(p, q), bw, log_w, trial_rounds=rounds)


def pose_quaternion(rotvec):
    """Unit quaternions (w ≥ 0) of rotation vectors ``(..., 3)``."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    axis = rotvec / angle.clamp_min(1e-12)
    return torch.cat([torch.cos(angle / 2), torch.sin(angle / 2) * axis], -1)


def _queries_near(kde, m, seed, scale=1.0):
    """Queries around the kernels: perturbed copies of random kernel means (some inside, some outside)."""
    g = torch.Generator().manual_seed(seed)
    means = kde.kernel_means(kde.sample_kernels(m, g))
    p = means.p + torch.randn(means.p.shape, generator=g, dtype=means.p.dtype) * 0.02 * scale
    turn = pose_quaternion(torch.randn(means.p.shape, generator=g, dtype=p.dtype) * 0.15 * scale)
    return se3.Pose(p, se3.compose(means, se3.Pose(torch.zeros_like(p), turn)).q)


@pytest.mark.parametrize("n", [300, FAST_DENSE_KERNELS + 700])  # dense fused layout, then leaf blocks
@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_fast_log_prob_equals_dense(n, batch):
    rounds = torch.randint(0, 3, (*batch, 3), generator=torch.Generator().manual_seed(1)) if batch else None
    kde = _random_kde(n, batch, seed=n + len(batch), rounds=rounds)
    queries = _queries_near(kde, 200, seed=2)
    dense = kde.log_prob(queries)
    fast = FastIndex(kde).log_prob(queries.p, queries.q)
    assert (FastIndex(kde).blocks) == (n > FAST_DENSE_KERNELS)
    finite = torch.isfinite(dense)
    assert 0.2 < finite.double().mean() < 1.0  # both supported and cut-off queries are exercised
    assert torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)


def test_fast_log_prob_broadcasts_queries_like_dense():
    kde = _random_kde(FAST_DENSE_KERNELS + 100, (3,), seed=4)
    single = _queries_near(_random_kde(50, (), seed=5), 40, seed=6, scale=0.5)  # (M,) against (3,)
    per_problem = _queries_near(kde, 40, seed=7)  # (3, M)
    for queries in (single, se3.Pose(per_problem.p[:1], per_problem.q[:1]), per_problem):
        dense = kde.log_prob(queries)
        fast = kde.log_prob(queries, method="fast")
        finite = torch.isfinite(dense)
        assert dense.shape == fast.shape
        assert torch.equal(finite, torch.isfinite(fast))
        assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])  # the fixture only sets an env var
@given(
    n=st.integers(1, 60),
    c_p=st.sampled_from([1.0, 3.0, math.inf]),
    c_q=st.sampled_from([0.5, 3.0, math.inf]),
    leaf=st.sampled_from([1, 4, 16]),
    seed=st.integers(0, 10_000),
)
def test_block_pruning_never_skips_a_live_kernel(n, c_p, c_q, leaf, seed):
    """Queries put just inside (and just outside) a kernel's cut-offs get the dense values."""
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1, cutoff_std=(c_p, c_q, 5.0))
    kde = _random_kde(n, (), seed=seed, bandwidth=bw, spread=0.03)
    g = torch.Generator().manual_seed(seed + 1)
    k = torch.randint(n, (64,), generator=g)
    reach_p = 0.01 * min(c_p, 6.0)  # |Δp| at the cut-off: β d_p = |Δp|²/(2 std²) = c²/2
    reach_q = 0.1 * min(c_q, 6.0)  # small-angle rotation reach
    factor = torch.rand(64, 1, generator=g, dtype=torch.float64) * 1.1  # up to 10 % beyond the cut-off
    direction = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    p = kde.means.p[k] + direction * reach_p * factor
    axis = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    turn = pose_quaternion(axis * reach_q * factor)
    zero = torch.zeros_like(p)
    queries = se3.Pose(p, se3.compose(se3.Pose(zero, kde.means.q[k]), se3.Pose(zero, turn)).q)
    dense = kde.log_prob(queries)
    out = FastIndex(kde, leaf=leaf, blocks=True).log_prob(queries.p, queries.q)
    finite = torch.isfinite(dense)
    assert torch.equal(finite, torch.isfinite(out))
    assert torch.allclose(out[finite], dense[finite], atol=1e-9, rtol=0)


def test_block_layout_pads_leaves_and_keeps_batches_apart():
    kde = _random_kde(40, (2,), seed=3)
    index = FastIndex(kde, leaf=4, blocks=True)
    assert index.blocks and index.num_blocks == 16
    queries = _queries_near(kde, 50, seed=8)
    dense, fast = kde.log_prob(queries), index.log_prob(queries.p, queries.q)
    finite = torch.isfinite(dense)
    assert torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)


def test_padding_and_extreme_weights_keep_the_dense_values():
    small, large = _random_kde(30, (), seed=1), _random_kde(FAST_DENSE_KERNELS + 50, (), seed=2)
    stacked = PoseKDE.stack([small, large])  # the small one is padded with -inf weights
    queries = _queries_near(stacked, 60, seed=3)
    dense, fast = stacked.log_prob(queries), stacked.log_prob(queries, method="fast")
    finite = torch.isfinite(dense)
    assert torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)
    # weights spanning e^300 cannot be summed linearly in float32: the fast method must fall back
    log_w = torch.zeros(FAST_DENSE_KERNELS + 10)
    log_w[::2] = -300.0
    kde32 = PoseKDE(_random_kde(FAST_DENSE_KERNELS + 10, (), seed=4, dtype=torch.float32).means,
                    KernelBandwidth(0.01, 0.1), log_w)
    assert not kde32.fast_index().linear
    q32 = _queries_near(kde32, 60, seed=5)
    assert torch.equal(kde32.log_prob(q32), kde32.log_prob(q32, method="fast"))


@pytest.mark.parametrize("exponents,mode", [((1.0, 1.0), 0.01), ((3.0, 1.0), 0.005), ((0.25, 0.75), 0.015)])
def test_expert_exponents_move_the_mode_and_mean_shift_finds_it(exponents, mode):
    """Two experts of one kernel each, 2 cm apart: the product of Gaussians raised to γ_A, γ_B peaks at
    γ_B / (γ_A + γ_B) of the way (a log w^P added instead would move nothing)."""
    bandwidth = KernelBandwidth(p_std=0.01, rot_std=0.05)
    means = se3.Pose(torch.tensor([[0.0, 0, 0], [0.02, 0, 0]], dtype=torch.float64),
                     torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64))
    log_w = torch.tensor([[0.0, -math.inf], [-math.inf, 0.0]], dtype=torch.float64)
    product = SharedKernelProduct(means, log_w, bandwidth, expert_exponent=torch.tensor(exponents))
    pose = se3.Pose(torch.tensor([[0.003, 0.001, 0.0]], dtype=torch.float64),
                    torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64))
    for _ in range(60):
        pose = product.mean_shift(pose)
    assert float(pose.p[0, 0]) == pytest.approx(mode, abs=2e-4)
    along = torch.zeros(201, 3, dtype=torch.float64)
    along[:, 0] = torch.linspace(0, 0.02, 201, dtype=torch.float64)
    line = se3.Pose(along, torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(201, 4))
    dense = ProductOfExperts(PoseKDE.stack([PoseKDE(means.take(torch.tensor([i])), bandwidth) for i in (0, 1)]),
                             expert_exponent=torch.tensor(exponents, dtype=torch.float64))
    assert float(line.p[int(dense.log_prob(line).argmax()), 0]) == pytest.approx(mode, abs=1e-4)
    with pytest.raises(InvalidParameterError, match="expert_exponent"):
        SharedKernelProduct(means, log_w, bandwidth, expert_exponent=torch.tensor([1.0, -1.0]))


def test_product_of_experts_fast_equals_dense():
    experts = PoseKDE.stack([_random_kde(n, (2,), seed=n) for n in (20, 90, 400)])  # (E=3, B=2)
    poe = ProductOfExperts(experts, torch.tensor([0.5, 0.0, -1.0]), torch.tensor([True, True, False]))
    queries = _queries_near(_random_kde(50, (2,), seed=9), 80, seed=10, scale=0.3)
    dense, fast = poe.log_prob(queries), poe.log_prob(queries, method="fast")
    finite = torch.isfinite(dense)
    assert finite.any() and torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)


@pytest.mark.parametrize("rounds,exponent", [(0, None), (2, None), (0, (0.5, 2.0, 1.0, 0.3))])
def test_shared_kernel_product_equals_the_product_of_its_experts(rounds, exponent):
    """Experts weighing one kernel set differently (as the motion model's environment experts do):
    one evaluation of the shared kernels gives the same product as each expert on its own."""
    shared = _random_kde(300, (2,), seed=21)  # B = 2 problems, K = 300 shared kernels
    g = torch.Generator().manual_seed(22)
    log_w = torch.randn(4, 2, 300, generator=g, dtype=torch.float64)
    log_w[torch.rand(4, 2, 300, generator=g) < 0.6] = -math.inf  # each expert keeps its own subset
    log_w[3, 1] = -math.inf  # a padding expert of problem 1: masked out
    mask = torch.ones(4, 2, dtype=torch.bool)
    mask[3, 1] = False
    log_wp = torch.tensor([0.7, 0.0, 0.0, -0.4], dtype=torch.float64)
    trial = torch.tensor([rounds, rounds, 0])
    gamma = None if exponent is None else torch.tensor(exponent, dtype=torch.float64)
    product = SharedKernelProduct(shared.means, log_w, shared.bandwidth, trial, log_wp, mask, expert_exponent=gamma)
    keep = torch.isfinite(log_w)
    keep[3, 1, 0] = True  # the masked-out expert gets a dummy kernel: a PoseKDE needs one
    log_w_own = torch.where(keep, torch.nan_to_num(log_w, neginf=0.0), log_w)
    experts = PoseKDE.stack([
        PoseKDE.stack([PoseKDE(shared.means.take((b, keep[e, b])), shared.bandwidth, log_w_own[e, b, keep[e, b]],
                               trial_rounds=trial) for b in range(2)])
        for e in range(4)
    ])  # (E=4, B=2), each expert on its own kernels
    reference = ProductOfExperts(experts, log_wp, mask, expert_exponent=gamma)
    queries = _queries_near(shared, 120, seed=23, scale=0.3)  # (2, 120)
    want, got = reference.log_prob(queries), product.log_prob(queries)
    finite = torch.isfinite(want)
    assert finite.any() and (~finite).any()
    assert torch.equal(finite, torch.isfinite(got))
    assert torch.allclose(got[finite], want[finite], atol=1e-9, rtol=0)


def test_a_padded_batch_of_products_equals_each_problems_own_product():
    """Products stacked as a batch pad every problem to the largest kernel count; each chunk of problems is
    evaluated up to its own last weighted kernel. Values and mean shift must equal each problem's product
    on its own kernels, across several chunks (500 queries of 1,200 kernels fill one chunk's budget)."""
    counts = [1200, 700, 1200, 310, 45]
    shared = _random_kde(1200, (len(counts),), seed=31)
    log_w = torch.randn(3, len(counts), 1200, generator=torch.Generator().manual_seed(32), dtype=torch.float64)
    for b, n in enumerate(counts):
        log_w[:, b, n:] = -math.inf  # padding past the problem's own kernels
    batch = SharedKernelProduct(shared.means, log_w, shared.bandwidth)
    assert batch.kernel_counts == counts
    assert any(max(counts[a:b]) < 1200 for a, b in batch.problem_chunks(500))  # a chunk is cut short
    queries = _queries_near(shared, 500, seed=33, scale=0.3)
    values, shifted = batch.log_prob(queries), batch.mean_shift(queries)
    for b, n in enumerate(counts):
        own = SharedKernelProduct(shared.means.take((b, slice(0, n))), log_w[:, b, :n], shared.bandwidth)
        query = queries.take(b)
        want = own.log_prob(query)
        finite = torch.isfinite(want)
        assert finite.any() and torch.equal(finite, torch.isfinite(values[b]))
        assert torch.allclose(values[b][finite], want[finite], atol=1e-9, rtol=0)
        moved = own.mean_shift(query)
        assert torch.allclose(shifted.p[b], moved.p, atol=1e-9) and torch.allclose(shifted.q[b], moved.q, atol=1e-9)


def test_shared_kernel_product_refuses_bad_layouts():
    shared = _random_kde(10, seed=24)
    with pytest.raises(InvalidParameterError, match="log_weights must have shape"):
        SharedKernelProduct(shared.means, torch.zeros(2, 9, dtype=torch.float64), shared.bandwidth)
    with pytest.raises(InvalidParameterError, match="no kernel with non-zero weight"):
        SharedKernelProduct(shared.means, torch.full((2, 10), -math.inf, dtype=torch.float64), shared.bandwidth)
    with pytest.raises(InvalidParameterError, match="NaN"):
        SharedKernelProduct(shared.means, torch.full((2, 10), math.nan, dtype=torch.float64), shared.bandwidth)
    with pytest.raises(InvalidParameterError, match="expert_mask"):
        SharedKernelProduct(shared.means, torch.zeros(2, 10, dtype=torch.float64), shared.bandwidth,
                            expert_mask=torch.ones(3, dtype=torch.bool))


def test_float32_fast_values_are_within_rounding_of_float64():
    kde = _random_kde(FAST_DENSE_KERNELS + 300, (2,), seed=11)
    queries = _queries_near(kde, 100, seed=12)
    reference = kde.log_prob(queries)
    fast32 = kde.to(torch.float32).log_prob(se3.Pose(queries.p.float(), queries.q.float()), method="fast")
    finite = torch.isfinite(reference) & torch.isfinite(fast32)
    assert finite.double().mean() > 0.2
    assert (fast32[finite].double() - reference[finite]).abs().max() < 2e-3


def test_unknown_method_is_refused():
    kde = _random_kde(10, (), seed=0)
    with pytest.raises(InvalidParameterError):
        kde.log_prob(_queries_near(kde, 3, seed=0), method="sparse")
    with pytest.raises(InvalidParameterError):
        anneal(kde.log_prob, initial_candidates(kde, 4), method="quick")
    with pytest.raises(InvalidParameterError):  # a per-problem planar mask needs the fast method
        anneal(kde.log_prob, initial_candidates(kde, 4), planar=torch.tensor(True))


# -- annealing ---------------------------------------------------------------------------------


def _two_mode_kde(dtype=torch.float64):
    """A heavy mode at (0.3, 0, 0) / yaw 0 and a light one at (−0.3, 0, 0) / yaw 1, 1,200 kernels."""
    g = torch.Generator().manual_seed(0)
    n = 1200
    heavy = torch.arange(n) < 700
    centre = torch.where(heavy.unsqueeze(-1), torch.tensor([0.3, 0.0, 0.0]), torch.tensor([-0.3, 0.0, 0.0]))
    p = centre.to(dtype) + torch.randn(n, 3, generator=g, dtype=dtype) * 0.01
    yaw = torch.where(heavy, 0.0, 1.0).to(dtype) + torch.randn(n, generator=g, dtype=dtype) * 0.05
    zero = torch.zeros_like(yaw)
    q = torch.stack([torch.cos(yaw / 2), zero, zero, torch.sin(yaw / 2)], -1)
    return PoseKDE(se3.Pose(p, q), KernelBandwidth(p_std=0.01, rot_std=0.1))


def test_fast_annealing_finds_the_same_mode_as_dense():
    kde = _two_mode_kde()
    schedule = AnnealSchedule(steps=40)
    init = initial_candidates(kde, 64, torch.Generator().manual_seed(1))
    dense = anneal(kde.log_prob, init, schedule, torch.Generator().manual_seed(2))
    fast = anneal(lambda x: kde.log_prob(x, method="fast"), init, schedule, torch.Generator().manual_seed(2),
                  method="fast")
    for result in (dense, fast):
        assert abs(float(result.best.p[0]) - 0.3) < 0.01 and abs(float(se3.yaw_of(result.best.q))) < 0.05
    assert abs(float(fast.best_log_prob - dense.best_log_prob)) < 0.05


def test_fast_annealing_mixes_planar_and_free_problems():
    kde = PoseKDE.stack([_two_mode_kde(), _two_mode_kde()])
    init = initial_candidates(kde, 32, torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(4)
    lifted = se3.Pose(init.p + torch.tensor([0.0, 0.0, 0.004], dtype=init.p.dtype), init.q)  # off the ground
    result = anneal(lambda x: kde.log_prob(x, method="fast"), lifted, AnnealSchedule(steps=20), g,
                    record_history=True, planar=torch.tensor([True, False]), method="fast")
    planar = result.history.p[:, 0, :, 2]
    assert torch.equal(planar, lifted.p[0, :, 2].expand_as(planar))  # z kept exactly on the planar problem
    roll_pitch = result.history.q[:, 0, :, 1:3]
    assert roll_pitch.abs().max() < 1e-6  # started level, stays level
    assert (result.history.p[:, 1, :, 2] != lifted.p[1, :, 2]).any()  # the free problem moves in z
    assert torch.isfinite(result.best_log_prob).all()


# -- query densities ---------------------------------------------------------------------------


def test_fast_query_draws_follow_the_dense_law():
    g = torch.Generator().manual_seed(0)
    frames_r = torch.randn(300, 2, generator=g) * 10.0
    weight = torch.rand(300, generator=g) + 0.1
    e_frames = embed_descriptors(frames_r)
    r_std = torch.full((2,), 0.5)
    # features: one far from every frame (never reachable), one near a cluster of frames
    e_features = torch.stack([torch.tensor([40.0, -40.0]), e_frames[7] + 0.1])
    n = 20_000
    pick, frame_idx, kernel_log_w = _fast_kernel_draws(e_features, e_frames, weight, r_std, 5.0, n, g)
    assert (pick == 1).all()  # the unreachable feature is always drawn again
    log_wn = neighbourhood_log_weights(e_features[1:], e_frames, weight, r_std, 5.0)[0]
    assert torch.allclose(kernel_log_w, torch.logsumexp(log_wn, -1).expand(n), atol=1e-5)
    expected = torch.softmax(log_wn, -1).double() * n
    counts = torch.bincount(frame_idx, minlength=300).double()
    assert (counts[~torch.isfinite(log_wn)] == 0).all()
    kept = expected > 5
    chi2 = (((counts - expected) ** 2) / expected)[kept].sum().item()
    assert stats.chi2.sf(chi2, int(kept.sum()) - 1) > 1e-3


def test_fast_heuristic_equals_dense():
    g = torch.Generator().manual_seed(1)
    r_features, r_frames = torch.randn(500, 2, generator=g) * 20, torch.randn(700, 2, generator=g) * 20
    dense = feature_distance_heuristic(r_features, r_frames)
    fast = feature_distance_heuristic(r_features, r_frames, method="fast")
    assert torch.allclose(dense, fast, rtol=1e-5)


# -- end to end --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_cube_model(small_model):
    return load_object("cube"), small_model("cube")


def _check_own_density(prediction):
    """The annealed candidates' log-likelihoods are those of the prediction's own density (dense
    reference), and the final pose is the best of them."""
    reference = prediction.motion_density.log_prob(prediction.candidates)
    finite = torch.isfinite(reference)
    assert finite.any() and torch.equal(finite, torch.isfinite(prediction.candidate_log_prob))
    assert torch.allclose(prediction.candidate_log_prob[finite], reference[finite], atol=1e-3)
    assert torch.isclose(prediction.log_prob, reference[finite].max(), atol=1e-3)


def test_fast_prediction_optimises_its_own_density(small_cube_model):
    cube, model = small_cube_model
    cloud = capture_partial_cloud(cube, cube.resting_pose(yaw=0.2))
    fast = predict(model, cloud, model.actions[1], torch.Generator().manual_seed(0))
    _check_own_density(fast)
    value_fast = fast.motion_density.log_prob(fast.candidates, method="fast")
    finite = torch.isfinite(value_fast)
    assert torch.allclose(value_fast[finite], fast.candidate_log_prob[finite], atol=1e-3)
    robot = fast.condition.robot_start  # planar annealing of the robot's query density
    assert float(robot.p[2]) == 0.0 and float(robot.q[1:3].abs().max()) < 1e-6
    assert fast.condition.robot_query.anneal.candidates.p.shape == (model.settings.anneal_candidates, 3)


def test_predict_many_batches_conditions_and_keeps_single_seeds(small_cube_model):
    cube, model = small_cube_model
    clouds = [capture_partial_cloud(cube, cube.resting_pose(yaw=y)) for y in (-0.3, 0.1, 0.4)]
    actions = model.actions[torch.tensor([0, 1, 2])]
    one_by_one = predict_many(model, clouds, actions, seed=5)
    single = predict(model, clouds[1], actions[1], torch.Generator().manual_seed(6))
    assert torch.equal(one_by_one[1].final_pose.p, single.final_pose.p)  # batch_size 1: predict's seeds
    batched = predict_many(model, clouds, actions, seed=5, batch_size=3, record_history=True)
    assert [p.action.tolist() for p in batched] == actions.tolist()
    for prediction in batched:  # annealed together, each still on its own density
        _check_own_density(prediction)
        # the initial candidates, every annealing step and the polished candidates
        sizes = model.settings
        assert prediction.anneal.history.p.shape == (sizes.fast_anneal_steps + 2, sizes.anneal_candidates, 3)
    with pytest.raises(InvalidParameterError):
        predict_many(model, clouds, actions, batch_size=0)
    with pytest.raises(InvalidParameterError):
        predict(model, clouds[0], actions[0], method="approximate")
    # one cloud given for every candidate (featured once) predicts as equal clouds given apart
    copies = [dataclasses.replace(clouds[1], points=clouds[1].points.clone()) for _ in range(3)]
    shared, apart = (predict_many(model, given, actions, seed=5, batch_size=3) for given in ([clouds[1]] * 3, copies))
    for one, other in zip(shared, apart, strict=True):
        assert torch.equal(one.final_pose.p, other.final_pose.p) and torch.equal(one.final_pose.q, other.final_pose.q)


def _shared_product_problem(problems, kernels, candidates, seed):
    """A shared-kernel product over ``problems`` and start candidates drawn from its kernels."""
    shared = _random_kde(kernels, (problems,), seed=seed, dtype=torch.float32)
    log_w = torch.randn(3, problems, kernels, generator=torch.Generator().manual_seed(seed + 1))
    product = SharedKernelProduct(shared.means, log_w, shared.bandwidth, validate_args=False)
    return product, initial_candidates(shared, candidates, torch.Generator().manual_seed(seed + 2))


def test_annealing_a_shared_kernel_product_in_fused_steps_follows_the_generic_loop():
    """Annealing a SharedKernelProduct itself runs each step as one fused call per chunk of problems; it
    draws the same proposals as the generic loop over its ``log_prob`` and must end where that loop ends
    (planar and free problems, several problem chunks: K · C fills the cache budget of one problem)."""
    product, init = _shared_product_problem(5, 1200, 500, seed=40)
    assert len(product.problem_chunks(500)) > 1
    schedule = AnnealSchedule(steps=8)
    for planar in (None, torch.tensor([True, False, True, False, True])):
        fused = anneal(product, init, schedule, torch.Generator().manual_seed(3), planar=planar, method="fast")
        generic = anneal(product.log_prob, init, schedule, torch.Generator().manual_seed(3), planar=planar,
                         method="fast")
        assert torch.equal(fused.candidates.p, generic.candidates.p)
        assert torch.equal(fused.candidates.q, generic.candidates.q)
        assert torch.equal(fused.log_prob, generic.log_prob)
        assert (fused.log_prob > product.log_prob(init)).any()  # the chains moved up


def _drawn_steps(shape, temperatures, planar, seed, dtype=torch.float32):
    """Steps drawn as the annealer draws them (:class:`DrawnSteps`, one chunk): free chains translate in 3-D
    and turn about their body axes, planar chains (``planar (*B, 1)``) move in x, y and turn about world z."""
    g = torch.Generator().manual_seed(seed)
    full = (len(temperatures), *shape)
    t = torch.tensor(temperatures, dtype=dtype).reshape(len(temperatures), *([1] * len(shape)), 1)
    step_p = torch.randn(*full, 3, generator=g, dtype=dtype) * 0.003 * t
    turn = pose_quaternion(torch.randn(*full, 3, generator=g, dtype=dtype) * 0.06 * t)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype).expand(*full, 4)
    yaw = se3.yaw_quaternion(torch.randn(full, generator=g, dtype=dtype) * 0.06 * t[..., 0])
    step_p = torch.where(planar.unsqueeze(-1) & torch.tensor([False, False, True]), 0.0, step_p)
    left = torch.where(planar.unsqueeze(-1), yaw, identity).contiguous()
    right = torch.where(planar.unsqueeze(-1), identity, turn).contiguous()
    return DrawnSteps(list(temperatures), step_p, left, right, torch.rand(full, generator=g, dtype=dtype))


def test_annealing_a_pruned_density_in_fused_steps_follows_the_generic_loop():
    """A density on leaf blocks anneals (compiled) in two fused calls per step around its (query, block)
    pairs; run eagerly here on a problem small enough for one pair chunk, over the same drawn steps it must
    end where the generic loop over ``log_prob(method="fast")`` ends: the same accepted moves, the same values
    up to the rounding of the queries ``log_prob`` normalises again (planar and free problems, two chunks)."""
    kde = _random_kde(FAST_DENSE_KERNELS + 700, (2,), seed=60, dtype=torch.float32)
    index = kde.fast_index()
    assert index.blocks
    init = initial_candidates(kde, 100, torch.Generator().manual_seed(61))
    init_lp = kde.log_prob(init, method="fast")
    temperatures = AnnealSchedule(steps=12).temperatures()
    for planar in (torch.tensor([[False], [False]]), torch.tensor([[True], [False]])):
        steps = [_drawn_steps(init.batch_shape, temperatures[:7], planar, seed=5),
                 _drawn_steps(init.batch_shape, temperatures[7:], planar, seed=6)]
        fused = index.anneal_blocks(AnnealInputs(init, iter(steps), 0.1), init_lp)
        generic = anneal_chains(partial(kde.log_prob, method="fast"), AnnealInputs(init, iter(steps), 0.1), init_lp)
        assert not fused.saw_nan and fused.history is None
        assert torch.equal(fused.best.p, generic.best.p)
        assert torch.allclose(fused.best.q, generic.best.q, atol=1e-7)
        # κ (1 − |<q, μ>|) scales the rounding of q by ~400
        assert torch.allclose(fused.best_log_prob, generic.best_log_prob, atol=1e-4)
        assert (fused.best_log_prob > init_lp).any()  # the chains moved up


def test_a_density_anneals_itself_or_declines_before_drawing():
    """``anneal(density, method="fast")`` hands the density the drawn steps: eagerly a PoseKDE runs the generic
    loop on its own fast evaluation (the same result, bit for bit, as given that evaluation); a
    SharedKernelProduct declines a history or poses not of its own batch without drawing a step, and the
    annealer's loop then draws the same stream."""
    kde = _random_kde(FAST_DENSE_KERNELS + 700, (2,), seed=60, dtype=torch.float32)
    init = initial_candidates(kde, 40, torch.Generator().manual_seed(61))
    schedule = AnnealSchedule(steps=25)  # two draw chunks
    for options in ({}, {"record_history": True}, {"planar": torch.tensor([True, False])}):
        itself = anneal(kde, init, schedule, torch.Generator().manual_seed(7), method="fast", **options)
        given = anneal(partial(kde.log_prob, method="fast"), init, schedule, torch.Generator().manual_seed(7),
                       method="fast", **options)
        assert torch.equal(itself.candidates.p, given.candidates.p) and torch.equal(itself.log_prob, given.log_prob)
        if options.get("record_history"):
            assert torch.equal(itself.history.q, given.history.q)
    product, start = _shared_product_problem(2, 300, 50, seed=70)
    untouched = iter([])
    for inputs in (AnnealInputs(start, untouched, 0.1, record_history=True),
                   AnnealInputs(se3.Pose(start.p[:1], start.q[:1]), untouched, 0.1)):
        assert product.fused_anneal(inputs) is None
    recorded = anneal(product, start, schedule, torch.Generator().manual_seed(8), record_history=True, method="fast")
    plain = anneal(product, start, schedule, torch.Generator().manual_seed(8), method="fast")
    assert torch.equal(recorded.candidates.p, plain.candidates.p) and torch.equal(recorded.log_prob, plain.log_prob)
    assert torch.equal(recorded.history.p[0], start.p)


@pytest.mark.slow
def test_compiled_fast_path_equals_dense(monkeypatch):
    """The torch.compile'd functions (first call compiles: tens of seconds on a cold cache): block and
    dense layouts, their mean shift, the shared-kernel product and its mean shift."""
    import shutil

    if not any(shutil.which(cc) for cc in ("g++", "c++", "clang++")):
        pytest.skip("no C++ compiler for torch.compile")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "1")
    for n in (300, FAST_DENSE_KERNELS + 700):
        kde = _random_kde(n, (3,), seed=n, dtype=torch.float32)
        queries = _queries_near(kde, 200, seed=2)
        dense, fast = kde.log_prob(queries), kde.log_prob(queries, method="fast")
        finite = torch.isfinite(dense)
        assert torch.equal(finite, torch.isfinite(fast))
        assert torch.allclose(fast[finite], dense[finite], atol=2e-3)
        moved, moved_fast = kde.mean_shift(queries), kde.mean_shift(queries, method="fast")
        assert torch.allclose(moved_fast.p, moved.p, atol=1e-4)
    # the compiled shared-kernel product and its mean shift against the experts one by one
    shared = _random_kde(300, seed=5, dtype=torch.float32)
    log_w = torch.randn(3, 300, generator=torch.Generator().manual_seed(6))
    log_w[1, ::2] = -math.inf
    product = SharedKernelProduct(shared.means, log_w, shared.bandwidth)
    experts = PoseKDE.stack([PoseKDE(shared.means.take(torch.isfinite(w)), shared.bandwidth, w[torch.isfinite(w)])
                             for w in log_w])
    queries = _queries_near(shared, 200, seed=7, scale=0.2)
    dense, fast = ProductOfExperts(experts).log_prob(queries), product.log_prob(queries)
    finite = torch.isfinite(dense)
    assert finite.any() and torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=2e-3)
    in_float64 = SharedKernelProduct(se3.Pose(shared.means.p.double(), shared.means.q.double()),
                                     log_w.double(), shared.bandwidth)
    assert torch.allclose(product.mean_shift(queries).p.double(),
                          in_float64.mean_shift(se3.Pose(queries.p.double(), queries.q.double())).p, atol=1e-4)
    # the compiled annealing step against a shared-kernel product (proposal, product, acceptance in one
    # call) against the eager generic loop
    product, init = _shared_product_problem(3, 400, 200, seed=50)
    schedule = AnnealSchedule(steps=8)
    fused = anneal(product, init, schedule, torch.Generator().manual_seed(4), method="fast")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "0")
    generic = anneal(product.log_prob, init, schedule, torch.Generator().manual_seed(4), method="fast")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "1")
    assert torch.allclose(fused.log_prob, generic.log_prob, atol=1e-4)
    assert torch.allclose(fused.candidates.p, generic.candidates.p, atol=1e-5)
    # the compiled fused steps against a pruned density against the eager generic loop
    kde = _random_kde(FAST_DENSE_KERNELS + 700, (2,), seed=60, dtype=torch.float32)
    init = initial_candidates(kde, 100, torch.Generator().manual_seed(61))
    fused = anneal(kde, init, schedule, torch.Generator().manual_seed(4), method="fast")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "0")
    generic = anneal(partial(kde.log_prob, method="fast"), init, schedule, torch.Generator().manual_seed(4),
                     method="fast")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "1")
    assert torch.allclose(fused.log_prob, generic.log_prob, atol=1e-4)
    assert torch.allclose(fused.candidates.p, generic.candidates.p, atol=1e-5)
    # the query density's group sums, fused into one loop by the compile options (nothing stored between)
    g = torch.Generator().manual_seed(8)
    rows, frames = torch.randn(500, 2, generator=g) * 2, torch.randn(2, 40, 64, generator=g) * 2
    log_w = -torch.rand(40, 64, generator=g) * 5
    log_w[-1, 30:] = -math.inf
    scale = torch.tensor([2.0, 0.5])
    compiled = fused_function("group_weight_sums", _group_weight_sums, "cpu")(rows, *frames, log_w, scale, 12.5)
    eager = _group_weight_sums(rows, *frames, log_w, scale, 12.5)
    assert (eager == 0).any() and torch.allclose(compiled, eager, rtol=1e-5, atol=1e-7)


def test_fast_descriptor_log_prob_equals_dense():
    """The fused pass with descriptors (environment contacts are scored with it) against the reference."""
    g = torch.Generator().manual_seed(31)
    plain = _random_kde(700, seed=31)
    bandwidth = KernelBandwidth(0.02, 0.3, (0.5, 0.5), cutoff_std=(3, 3, 2))
    kde = PoseKDE(plain.means, bandwidth, plain.log_weights,
                  descriptors=torch.randn(700, 2, generator=g, dtype=torch.float64))
    queries = _queries_near(kde, 150, seed=32)
    descriptors = torch.randn(150, 2, generator=g, dtype=torch.float64)
    dense = kde.log_prob(queries, descriptors)
    fast = kde.log_prob(queries, descriptors, method="fast")
    finite = torch.isfinite(dense)
    assert finite.any() and (~finite).any()  # the descriptor cut-off removes some queries entirely
    assert torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], dense[finite], atol=1e-9, rtol=0)


@pytest.mark.parametrize("n", [300, FAST_DENSE_KERNELS + 700])  # responsibilities, then leaf-block moments
def test_mean_shift_fast_equals_dense_and_climbs(n):
    kde = _random_kde(n, (2,), seed=41)
    near = _queries_near(kde, 60, seed=42, scale=0.5)
    queries = se3.Pose(torch.cat([near.p, near.p[..., :10, :] + 1.0], -2), torch.cat([near.q, near.q[..., :10, :]], -2))
    dense = kde.mean_shift(queries)
    fast = kde.mean_shift(queries, method="fast")
    assert torch.allclose(fast.p, dense.p, atol=1e-9) and torch.allclose(fast.q, dense.q, atol=1e-9)
    before = kde.log_prob(queries)
    moved = queries
    for _ in range(30):
        moved = kde.mean_shift(moved)
    after = kde.log_prob(moved)
    alive = torch.isfinite(before)
    assert alive.any() and (~alive).any()
    # from a point of non-zero density the fixed-point iteration climbs to a mode; zero-density points stay
    assert bool((after[alive] >= before[alive] - 1e-9).all())
    assert torch.equal(moved.p[~alive], queries.p.expand_as(moved.p)[~alive])
    # one kernel: any point it reaches moves onto its mean in one step, and the mean is a fixed point
    single = PoseKDE(kde.means.take((0, slice(0, 1))), kde.bandwidth)
    offsets = torch.linspace(-1, 1, 5, dtype=torch.float64).unsqueeze(-1)
    turn = pose_quaternion(offsets * torch.tensor([0.1, 0.05, -0.1], dtype=torch.float64))
    turned = se3.compose(single.means, se3.Pose(torch.zeros(5, 3, dtype=torch.float64), turn))
    around = se3.Pose(single.means.p + 0.01 * offsets, turned.q)
    assert torch.isfinite(single.log_prob(around)).all()
    step = single.mean_shift(around)
    assert torch.allclose(step.p, single.means.p.expand(5, 3), atol=1e-12)
    assert torch.allclose(step.q.abs(), single.means.q.expand(5, 4).abs(), atol=1e-12)


def test_shared_kernel_product_mean_shift_is_the_products_fixed_point_step():
    """Against the step written out from the experts' responsibilities: kernel k weighs Σ_e w_ek K_k / P_e."""
    shared = _random_kde(200, seed=51)
    g = torch.Generator().manual_seed(52)
    log_w = torch.randn(3, 200, generator=g, dtype=torch.float64)
    log_w[torch.rand(3, 200, generator=g) < 0.5] = -math.inf
    product = SharedKernelProduct(shared.means, log_w, shared.bandwidth, expert_log_weight=torch.tensor([1.0, 0, 0]))
    queries = _queries_near(shared, 80, seed=53, scale=0.2)
    kernels = shared.log_kernels(queries).exp()  # (M, K)
    weights = torch.nan_to_num(log_w.exp())  # (E, K)
    per_expert = kernels @ weights.T  # (M, E)
    alive = (per_expert > 0).all(-1)
    a = kernels * ((1.0 / per_expert.clamp_min(1e-300)) @ weights)  # (M, K)
    want_p = (a @ shared.means.p) / a.sum(-1, keepdim=True)
    sign = torch.where(queries.q @ shared.means.q.T < 0, -1.0, 1.0).to(a)
    want_q = (a * sign) @ shared.means.q
    want_q = want_q / want_q.norm(dim=-1, keepdim=True)
    got = product.mean_shift(queries)
    assert alive.any() and (~alive).any()
    assert torch.allclose(got.p[alive], want_p[alive], atol=1e-9)
    assert torch.allclose(got.q[alive], want_q[alive], atol=1e-9)
    assert torch.equal(got.p[~alive], queries.p[~alive])  # zero product: the query stays


@given(st.integers(0, 500), st.integers(1, 64))
def test_chunks_cover_the_rows_without_a_lone_row(n, step):
    """Fused functions see no size-1 chunk (the compiler would specialise and recompile for it)."""
    from pushtorch.kde.fused import chunk_bounds

    bounds = chunk_bounds(n, step)
    assert [a for a, _ in bounds] == ([0] if bounds else []) + [b for _, b in bounds[:-1]]
    assert not bounds or bounds[-1][1] == n
    sizes = [b - a for a, b in bounds]
    assert sum(sizes) == n and all(size <= step + 1 for size in sizes)
    if n >= 2 and step >= 2:
        assert min(sizes) >= 2


def test_a_warm_fused_function_does_not_recompile_for_other_sizes_strides_or_grad_mode(monkeypatch):
    """Compiled once, a fused function serves any data: sizes that vary with it (kernel counts, problems,
    candidates), strided views and the caller's grad mode meet no guard, so a warm process never recompiles
    (what differs between CPUs: a float path that prunes one kernel more meets sizes the warm-up never saw)."""
    import shutil

    from torch._dynamo.utils import counters

    from pushtorch.kde.kernel_sums import dense_sums

    if not any(shutil.which(cc) for cc in ("g++", "c++", "clang++")):
        pytest.skip("no C++ compiler for torch.compile")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "1")
    g = torch.Generator().manual_seed(0)

    def arguments(problems, queries, kernels, strided=False):
        x = torch.randn(problems, 7, queries, generator=g)
        table = torch.randn(problems, 8, 2 * kernels if strided else kernels, generator=g)
        return x, table[:, :, ::2] if strided else table, torch.rand(problems, 2, generator=g) + 1, 3.0, 2.0

    evaluate = fused_function("test_recompiles_dense_sums", dense_sums, "cpu")  # its own compiled function
    evaluate(*arguments(7, 40, 300))  # the warm-up: 7 problems, as many as a pose's rows
    graphs = counters["stats"]["unique_graphs"]
    for problems, queries, kernels, strided in [(3, 61, 317, False), (5, 33, 200, True), (2, 500, 900, False)]:
        args = arguments(problems, queries, kernels, strided)
        with torch.enable_grad():
            value = evaluate(*args)
        torch.testing.assert_close(value, dense_sums(*args), rtol=1e-5, atol=1e-6)
    assert counters["stats"]["unique_graphs"] == graphs


_LOAD_SHARED = """
import sys, torch
from torch._dynamo.utils import counters
import pushtorch.kde.fused as fused
from pushtorch.kde.kernel_sums import dense_sums
torch.set_num_threads(int(sys.argv[4]))  # as a task matches its submitter: the compiled code's guards hold it
fused.declare_long_run()
fused._shared_folder.append(__import__("pathlib").Path(sys.argv[1]))
fused.share_compiled()
args = torch.load(sys.argv[2])
evaluate = fused.fused_function("test_shared_dense_sums", dense_sums, "cpu")
value = evaluate(*args)
loaded = counters["stats"]["unique_graphs"]
wide = evaluate(*[a.double() if isinstance(a, torch.Tensor) else a for a in args])  # its guards refuse float64
torch.save({"value": value, "loaded_graphs": loaded, "graphs": counters["stats"]["unique_graphs"],
            "wide": wide}, sys.argv[3])
"""


def test_a_shared_compiled_function_loads_in_another_process_and_gives_the_same_values(tmp_path, monkeypatch):
    """share_compiled: a fused function compiled ahead of time and saved here is loaded by a fresh process,
    which traces nothing for it and gets the in-process compilation's values bit for bit; a call its guards
    refuse (float64) is compiled in that process and is right too."""
    import shutil
    import subprocess
    import sys

    import pushtorch.kde.fused as fused
    from pushtorch.kde.kernel_sums import dense_sums

    if not any(shutil.which(cc) for cc in ("g++", "c++", "clang++")):
        pytest.skip("no C++ compiler for torch.compile")
    monkeypatch.setenv("PUSHTORCH_COMPILE", "1")
    for name, empty in (("_shared", {}), ("_shared_variants", {}), ("_not_shared", set()),
                        ("_shared_folder", [tmp_path / "shared"]), ("_compiled_functions", {})):
        monkeypatch.setattr(fused, name, empty)
    g = torch.Generator().manual_seed(0)
    args = (torch.randn(3, 7, 41, generator=g), torch.randn(3, 8, 150, generator=g),
            torch.rand(3, 2, generator=g) + 1, 3.0, 2.0)
    assert fused.share_compiled(produce=True) == tmp_path / "shared"
    made = fused.fused_function("test_shared_dense_sums", dense_sums, "cpu")(*args)
    assert len(list((tmp_path / "shared").glob("test_shared_dense_sums.*.bin"))) == 1
    monkeypatch.setattr(fused, "_shared", {})  # this process compiles in-process again: the reference
    monkeypatch.setattr(fused, "_compiled_functions", {})
    reference = fused.fused_function("test_shared_dense_sums", dense_sums, "cpu")(*args)
    assert torch.equal(made, reference)
    torch.save(args, tmp_path / "args.pt")
    subprocess.run([sys.executable, "-c", _LOAD_SHARED, str(tmp_path / "shared"), str(tmp_path / "args.pt"),
                    str(tmp_path / "out.pt"), str(torch.get_num_threads())], check=True, timeout=300)
    out = torch.load(tmp_path / "out.pt")
    assert out["loaded_graphs"] == 0 and out["graphs"] == 1  # loaded, not traced; float64 traced there
    assert torch.equal(out["value"], reference)
    torch.testing.assert_close(out["wide"], dense_sums(*[a.double() if isinstance(a, torch.Tensor) else a
                                                         for a in args]))
