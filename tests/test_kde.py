"""Kernel density estimation over SE(3) × R^k: kernels, cut-offs, trial rounds, sampling (pushtorch.kde)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy import integrate, stats

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError, ModelError
from pushtorch.kde import (
    Evaluation,
    KernelBandwidth,
    PoseKDE,
    ProductOfExperts,
    TrialRounds,
    descriptor_distance,
    descriptor_distance_unscaled,
    product_log_prob,
    rotation_distance,
    straightforward_evaluation,
    translation_distance,
)

IDENTITY_Q = (1.0, 0.0, 0.0, 0.0)


def axis_angle_quaternion(axis, angle, dtype=torch.float64):
    axis = torch.as_tensor(axis, dtype=dtype)
    axis = axis / axis.norm()
    return torch.cat([torch.cos(torch.tensor([angle / 2], dtype=dtype)), math.sin(angle / 2) * axis])


def random_kde(batch, n, generator, dtype=torch.float32, descriptors=True, spread=0.05, bw=None):
    bw = bw or KernelBandwidth(p_std=0.02, rot_std=0.4, r_std=(5.0, 2.0) if descriptors else None)
    p = torch.randn(*batch, n, 3, generator=generator, dtype=dtype) * spread
    q = se3.random_quaternion((*batch, n), generator, dtype=dtype)
    r = torch.randn(*batch, n, 2, generator=generator, dtype=dtype) * 5 if descriptors else None
    log_w = torch.randn(*batch, n, generator=generator, dtype=dtype)
    return PoseKDE(se3.Pose(p, q), bw, log_w, r)


def queries_near(kde, m, generator, batch=None):
    """Queries near the kernel means (most kernels within cut-off of some query)."""
    pose, index = kde.sample(m, generator)
    r = None
    if kde.descriptors is not None:
        mu_r = torch.gather(kde.descriptors, -2, index.unsqueeze(-1).expand(*index.shape, kde.descriptor_dim))
        r = mu_r + torch.randn(mu_r.shape, generator=generator, dtype=mu_r.dtype) * 2
    return pose, r


def brute_force_log_prob(kde, pose, r=None):
    """Σ_i w_i Π_c [β_c d_c < δ_c] exp(−β_c d_c), from the exact distance helpers, one pair at a time."""
    bw = kde.bandwidth
    beta = kde.beta.unsqueeze(-2).unsqueeze(-2)  # (*B, 1, 1, 3)
    p = pose.p.unsqueeze(-2)
    q = pose.q.unsqueeze(-2)
    terms = [
        beta[..., 0] * translation_distance(p, kde.means.p.unsqueeze(-3), bw.sigma_p),
        beta[..., 1] * rotation_distance(q, kde.means.q.unsqueeze(-3), bw.sigma_q),
    ]
    if r is not None:
        d_r = descriptor_distance(r.unsqueeze(-2), kde.descriptors.unsqueeze(-3), bw.sigma_r)
        terms.append(beta[..., 2] * d_r)
    log_k = kde.log_weights.unsqueeze(-2)
    for term, delta in zip(terms, bw.delta, strict=False):
        log_k = torch.where(term < delta, log_k - term, torch.full_like(term, -math.inf))
    return torch.logsumexp(log_k, -1)


# --------------------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 2e-3)])
@pytest.mark.parametrize("rounds", [TrialRounds(), TrialRounds(1, 2, 3)])
def test_single_kernel_is_exp_minus_scaled_distance(dtype, tol, rounds):
    bw = KernelBandwidth(p_std=0.01, rot_std=0.2, r_std=(3.0, 0.5), cutoff_std=(math.inf,) * 3, alpha_t=1.7)
    mu_q = axis_angle_quaternion([0.3, -1.0, 0.5], 2.0, dtype)
    kde = PoseKDE(
        se3.Pose(torch.tensor([[0.4, -0.2, 0.9]], dtype=dtype), mu_q[None]),
        bw,
        descriptors=torch.tensor([[10.0, -4.0]], dtype=dtype),
        trial_rounds=rounds,
    )
    offset = torch.tensor([0.007, -0.011, 0.004], dtype=dtype)
    angle = 0.25
    turn = axis_angle_quaternion([1.0, 2.0, -0.5], angle, dtype)
    zero = torch.zeros(3, dtype=dtype)
    turned_q = se3.compose(se3.Pose(zero, mu_q), se3.Pose(zero, turn)).q
    query = se3.Pose((kde.means.p[0] + offset)[None], turned_q[None])
    dr = torch.tensor([1.5, -0.3], dtype=dtype)
    query_r = (kde.descriptors[0] + dr)[None]

    beta_p, beta_q, beta_r = rounds.beta(1.7)
    d_p = float((offset**2).sum()) / (2 * 0.01**2)
    d_q = (1 - math.cos(angle / 2)) / (0.2**2 / 4)
    d_r = 1.5**2 / (2 * 3.0**2) + 0.3**2 / (2 * 0.5**2)
    expected = -(beta_p * d_p + beta_q * d_q + beta_r * d_r)

    got = kde.log_prob(query, query_r)
    assert got.shape == (1,)
    assert got.item() == pytest.approx(expected, rel=tol, abs=tol)
    # without descriptors the r factor is omitted (marginal over descriptors)
    assert kde.log_prob(query).item() == pytest.approx(-(beta_p * d_p + beta_q * d_q), rel=tol, abs=tol)
    terms = kde.log_kernel_terms(query, query_r)[0, 0]
    torch.testing.assert_close(terms, torch.tensor([beta_p * d_p, beta_q * d_q, beta_r * d_r], dtype=dtype),
                               rtol=tol, atol=tol)
    # the small-angle reading of the units: d_q ≈ angle² / (2 rot_std²)
    assert d_q == pytest.approx(angle**2 / (2 * 0.2**2), rel=0.01)


def test_distance_helpers_match_the_paper():
    g = torch.Generator().manual_seed(1)
    p, mu = torch.randn(2, 4, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(translation_distance(p, mu, 0.5), ((p - mu) ** 2).sum(-1) / 0.5)
    q = se3.random_quaternion((4,), g, torch.float64)
    mq = se3.random_quaternion((4,), g, torch.float64)
    torch.testing.assert_close(rotation_distance(q, mq, 0.1), (1 - (q * mq).sum(-1).abs()) / 0.1)
    r, mr = torch.randn(2, 4, 2, generator=g, dtype=torch.float64)
    sigma = torch.tensor([0.5, 2.0], dtype=torch.float64)
    torch.testing.assert_close(descriptor_distance(r, mr, sigma), ((r - mr) ** 2 @ (1 / sigma)))
    torch.testing.assert_close(descriptor_distance_unscaled(r, mr), ((r - mr) ** 2).sum(-1))
    # broadcasting: all queries against all kernels
    assert translation_distance(p[:, None], mu[None], 0.5).shape == (4, 4)
    with pytest.raises(InvalidParameterError):
        translation_distance(p, mu, 0.0)
    with pytest.raises(InvalidParameterError):
        descriptor_distance(r, mr, [1.0, -1.0])


@pytest.mark.parametrize("component", ["p", "q", "r"])
def test_cutoff_is_exactly_at_delta(component):
    dtype = torch.float64
    bw = KernelBandwidth(p_std=0.01, rot_std=0.3, r_std=(2.0,), cutoff_std=(2.0, 2.5, 1.5))
    kde = PoseKDE(se3.Pose(torch.zeros(1, 3, dtype=dtype), torch.tensor([IDENTITY_Q], dtype=dtype)), bw,
                  descriptors=torch.zeros(1, 1, dtype=dtype), trial_rounds=TrialRounds(1, 1, 1))
    beta = 0.5
    index = "pqr".index(component)
    delta = bw.delta[index]
    values = []
    for factor in (1 - 1e-6, 1 + 1e-6):
        target = factor * delta / beta  # the unscaled distance d with β d = factor δ
        p = torch.zeros(1, 3, dtype=dtype)
        q = torch.tensor([IDENTITY_Q], dtype=dtype)
        r = torch.zeros(1, 1, dtype=dtype)
        if component == "p":
            p[0, 0] = math.sqrt(target * bw.sigma_p)
        elif component == "q":
            angle = 2 * math.acos(1 - target * bw.sigma_q)
            q = axis_angle_quaternion([0.0, 0.0, 1.0], angle, dtype)[None]
        else:
            r[0, 0] = math.sqrt(target * bw.sigma_r[0])
        values.append(kde.log_prob(se3.Pose(p, q), r).item())
    inside, outside = values
    assert inside == pytest.approx(-delta, rel=1e-5)  # exp(−β d) just before the cut-off
    assert outside == -math.inf  # and exactly zero at and beyond it


unit_interval = st.floats(-1.0, 1.0, allow_nan=False)
quat_raw = st.tuples(*[unit_interval] * 4).filter(lambda v: sum(x * x for x in v) > 1e-2)


@given(st.lists(quat_raw, min_size=3, max_size=3), st.lists(quat_raw, min_size=2, max_size=2),
       st.lists(st.booleans(), min_size=5, max_size=5))
def test_q_and_minus_q_give_the_same_density(kernel_q, query_q, flips):
    dtype = torch.float64
    kq = torch.tensor(kernel_q, dtype=dtype)
    kq = kq / kq.norm(dim=-1, keepdim=True)
    qq = torch.tensor(query_q, dtype=dtype)
    qq = qq / qq.norm(dim=-1, keepdim=True)
    sign = torch.tensor([-1.0 if f else 1.0 for f in flips], dtype=dtype)
    bw = KernelBandwidth(p_std=0.05, rot_std=1.0, cutoff_std=(3.0, 3.0, 3.0))
    kp = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=dtype)
    qp = torch.tensor([[0.01, 0.01, 0.0], [0.0, 0.0, 0.01]], dtype=dtype)
    plain = PoseKDE(se3.Pose(kp, kq), bw).log_prob(se3.Pose(qp, qq))
    flipped = PoseKDE(se3.Pose(kp, kq * sign[:3, None]), bw).log_prob(se3.Pose(qp, qq * sign[3:, None]))
    torch.testing.assert_close(plain, flipped, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_prob_matches_brute_force_and_normalises_weights(batch, dtype):
    g = torch.Generator().manual_seed(2)
    kde = random_kde(batch, 40, g, dtype)
    pose, r = queries_near(kde, 30, g)
    got = kde.log_prob(pose, r)
    assert got.shape == (*batch, 30)
    expected = brute_force_log_prob(kde, pose, r)
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    finite = torch.isfinite(expected)
    assert finite.float().mean() > 0.5  # the check is not vacuous
    assert torch.equal(finite, torch.isfinite(got))
    torch.testing.assert_close(got[finite], expected[finite], rtol=tol, atol=tol)
    # weights are normalised: scaling them all (a shift in log space) changes nothing
    shifted = PoseKDE(kde.means, kde.bandwidth, kde.log_weights + 7.5, kde.descriptors)
    torch.testing.assert_close(shifted.log_prob(pose, r), got, rtol=tol, atol=tol)
    assert torch.allclose(torch.logsumexp(kde.log_weights, -1), torch.zeros((), dtype=dtype), atol=1e-6)


@pytest.mark.parametrize("offset", [0.0, 10.0, 100.0])
@pytest.mark.parametrize("method", ["dense", "fast"])
def test_log_prob_of_the_kernel_mean_of_an_isolated_kernel_is_its_log_weight(offset, method):
    """At a kernel's own mean the density is that kernel's weight (the others are 1 m away, beyond their
    cut-offs), in float32, for kernels up to 100 m from the origin, on any CPU's float path (the position
    distance is an exact difference: 0 at the mean). What is left is the rotation term: float32 resolves
    1 − |<q, μ>| to ~1.2e-7, i.e. κ · 1.2e-7 ≈ 2e-4 in log for κ = 4 / rot_std² = 1600."""
    g = torch.Generator().manual_seed(3)
    bw = KernelBandwidth(p_std=0.001, rot_std=0.05)
    p = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]) + torch.tensor([offset, -offset, 0.5 * offset])
    kde = PoseKDE(se3.Pose(p, se3.random_quaternion((3,), g)), bw, torch.tensor([0.2, 0.3, 0.5]).log())
    expected = torch.tensor([0.2, 0.3, 0.5])
    torch.testing.assert_close(kde.log_prob(kde.means, method=method).exp(), expected, rtol=1e-3, atol=1e-6)


def test_padding_kernels_change_nothing():
    g = torch.Generator().manual_seed(4)
    kde = random_kde((2,), 20, g, torch.float64)
    junk = random_kde((2,), 7, g, torch.float64, spread=0.01)  # right on top of the queries
    padded = PoseKDE(
        se3.Pose.cat([kde.means, junk.means], dim=-1),
        kde.bandwidth,
        torch.cat([kde.log_weights, torch.full((2, 7), -math.inf, dtype=torch.float64)], -1),
        torch.cat([kde.descriptors, junk.descriptors], -2),
    )
    pose, r = queries_near(kde, 25, g)
    torch.testing.assert_close(padded.log_prob(pose, r), kde.log_prob(pose, r), rtol=1e-10, atol=1e-10)
    index = padded.sample_kernels(5000, g)
    assert index.max() < 20


def test_stack_pads_and_keeps_each_density():
    g = torch.Generator().manual_seed(5)
    bw = KernelBandwidth(p_std=0.02, rot_std=0.4, r_std=(5.0, 2.0))
    kdes = [random_kde((), n, g, torch.float64, bw=bw).with_trial_rounds(TrialRounds(n % 3, 0, 1))
            for n in (5, 12, 9)]
    stacked = PoseKDE.stack(kdes)
    assert stacked.batch_shape == (3,) and stacked.num_kernels == 12
    pose, r = queries_near(kdes[1], 10, g)
    each = torch.stack([k.log_prob(pose, r) for k in kdes])
    torch.testing.assert_close(stacked.log_prob(pose, r), each, rtol=1e-10, atol=1e-10)
    assert stacked.trial_rounds.tolist() == [[2, 0, 1], [0, 0, 1], [0, 0, 1]]
    with pytest.raises(InvalidParameterError):
        PoseKDE.stack([kdes[0], random_kde((), 4, g, torch.float64, descriptors=False)])


@pytest.mark.parametrize("descriptors", [True, False])
def test_straightforward_evaluation_is_the_dense_reference_written_plainly(descriptors):
    """The benchmark's baseline evaluates the same density: a stacked, padded, widened one with query
    batch dims that broadcast, against the pair-by-pair brute force."""
    g = torch.Generator().manual_seed(16)
    bw = KernelBandwidth(p_std=0.02, rot_std=0.4, r_std=(5.0, 2.0) if descriptors else None)
    kdes = [random_kde((), n, g, torch.float64, descriptors, bw=bw).with_trial_rounds(TrialRounds(n % 2, 1, 0))
            for n in (30, 11)]
    stacked = PoseKDE.stack(kdes)  # the second element holds 19 padding kernels
    pose, r = queries_near(kdes[0], 24, g)
    queries = se3.Pose(pose.p.expand(3, 2, 24, 3), pose.q.expand(3, 2, 24, 4))
    r = None if r is None else r.expand(3, 2, 24, 2)
    with straightforward_evaluation():
        got = stacked.log_prob(queries, r)
        empty = stacked.log_prob(se3.Pose(pose.p[:0], pose.q[:0]), None if r is None else r[0, 0, :0])
    expected = brute_force_log_prob(stacked, queries, r)
    assert got.shape == (3, 2, 24) and empty.shape == (2, 0)
    finite = torch.isfinite(expected)
    assert finite[:, 0].float().mean() > 0.5  # not vacuous
    assert torch.equal(finite, torch.isfinite(got))
    torch.testing.assert_close(got[finite], expected[finite], rtol=1e-9, atol=1e-9)
    # outside the block the dense reference is back, with the same values
    torch.testing.assert_close(stacked.log_prob(queries, r), got, rtol=1e-9, atol=1e-9)


def test_chunked_log_prob_equals_unchunked():
    g = torch.Generator().manual_seed(6)
    kde = random_kde((3,), 200, g)
    pose, r = queries_near(kde, 97, g)
    whole = kde.log_prob(pose, r, chunk_size=10_000)
    for chunk in (1, 7, 32, 96):
        torch.testing.assert_close(kde.log_prob(pose, r, chunk_size=chunk), whole)
    torch.testing.assert_close(kde.log_prob(pose, r), whole)
    with pytest.raises(InvalidParameterError):
        kde.log_prob(pose, r, chunk_size=0)


def test_query_batch_dims_broadcast_against_the_density():
    g = torch.Generator().manual_seed(7)
    kde = random_kde((2,), 30, g, torch.float64, descriptors=False)
    pose, _ = kde.sample(6, g)
    # one set of queries for both densities, and extra leading query dims
    shared = se3.Pose(pose.p[0], pose.q[0])
    out = kde.log_prob(shared)
    assert out.shape == (2, 6)
    torch.testing.assert_close(out[1], kde.log_prob(se3.Pose(pose.p[[0, 0]], pose.q[[0, 0]]))[1])
    more = se3.Pose(pose.p.expand(4, 2, 6, 3), pose.q.expand(4, 2, 6, 4))
    assert kde.log_prob(more).shape == (4, 2, 6)
    assert kde.log_prob(se3.Pose(pose.p[..., :0, :], pose.q[..., :0, :])).shape == (2, 0)


def test_to_changes_dtype_and_keeps_values():
    g = torch.Generator().manual_seed(8)
    kde = random_kde((), 50, g, torch.float64)
    pose, r = queries_near(kde, 20, g)
    low = kde.to(torch.float32)
    assert low.dtype == torch.float32 and low.means.q.dtype == torch.float32
    out = low.log_prob(pose, r)  # float64 queries are cast to the density's dtype
    assert out.dtype == torch.float32
    ref = kde.log_prob(pose, r)
    finite = torch.isfinite(ref) & torch.isfinite(out)
    assert finite.sum() > 10
    torch.testing.assert_close(out[finite].double(), ref[finite], rtol=1e-3, atol=1e-3)


# --------------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------------


def _single_kernel(p_std, rot_std, cutoff_std, rounds=None, dtype=torch.float64):
    mu = se3.Pose(torch.tensor([[0.3, -0.1, 0.2]], dtype=dtype),
                  axis_angle_quaternion([1.0, 1.0, 0.0], 1.0, dtype)[None])
    bw = KernelBandwidth(p_std=p_std, rot_std=rot_std, cutoff_std=cutoff_std)
    return PoseKDE(mu, bw, trial_rounds=rounds)


def test_sampled_translations_are_gaussian_with_the_kernel_std():
    g = torch.Generator().manual_seed(10)
    kde = _single_kernel(0.02, 0.1, (math.inf, math.inf, math.inf), TrialRounds(p=1))
    pose, index = kde.sample(20_000, g)
    assert pose.p.shape == (20_000, 3) and index.shape == (20_000,) and (index == 0).all()
    offsets = (pose.p - kde.means.p).numpy()
    std = 0.02 * math.sqrt(2.0)  # β_p = 1/2 widens the std by √2
    assert np.abs(offsets.mean(0)).max() < 4 * std / math.sqrt(20_000)
    np.testing.assert_allclose(offsets.std(0), std, rtol=0.03)
    # and each axis is normal (Kolmogorov–Smirnov against N(0, std))
    assert stats.kstest(offsets[:, 0] / std, "norm").pvalue > 1e-3


def test_sampled_translations_respect_the_cutoff_exactly():
    g = torch.Generator().manual_seed(11)
    c = 1.5
    kde = _single_kernel(0.01, 0.1, (c, math.inf, math.inf))
    pose, _ = kde.sample(20_000, g)
    z2 = (((pose.p - kde.means.p) / 0.01) ** 2).sum(-1).numpy()
    assert z2.max() < c * c
    # E[χ²_3 | χ²_3 < c²] from the closed-form density
    num = integrate.quad(lambda x: x * stats.chi2.pdf(x, 3), 0, c * c)[0]
    expected = num / stats.chi2.cdf(c * c, 3)
    assert z2.mean() == pytest.approx(expected, rel=0.02)
    assert torch.isfinite(kde.log_prob(pose)).all()


@pytest.mark.parametrize("rot_std,cutoff", [(0.15, math.inf), (0.15, 1.0), (1.2, math.inf), (3.0, 2.0)])
def test_sampled_rotations_follow_the_folded_vmf(rot_std, cutoff):
    g = torch.Generator().manual_seed(12)
    kde = _single_kernel(0.01, rot_std, (math.inf, cutoff, math.inf))
    pose, _ = kde.sample(20_000, g)
    s = (1 - (pose.q * kde.means.q).sum(-1).abs()).numpy()  # 1 − |<q, μ>|
    kappa = 1 / kde.bandwidth.sigma_q
    upper = min(1.0, kde.bandwidth.delta[1] / kappa)
    assert s.max() < upper + 1e-12
    # density of s on S^3 for the kernel exp(κ|t|): ∝ e^(−κ s) √(s (2 − s)) on [0, upper]
    density = lambda x: math.exp(-kappa * x) * math.sqrt(x * (2 - x))  # noqa: E731
    z = integrate.quad(density, 0, upper, limit=200)[0]
    mean = integrate.quad(lambda x: x * density(x), 0, upper, limit=200)[0] / z
    assert s.mean() == pytest.approx(mean, rel=0.03)
    assert torch.isfinite(kde.log_prob(pose)).all()


def test_sampled_rotations_match_scipys_vmf_for_a_concentrated_kernel():
    g = torch.Generator().manual_seed(13)
    kde = _single_kernel(0.01, 0.1, (math.inf, math.inf, math.inf), TrialRounds(q=2))
    pose, _ = kde.sample(8000, g)
    kappa = kde.beta[1].item() / kde.bandwidth.sigma_q
    mean = kde.means.q.reshape(4).double()
    reference = torch.from_numpy(stats.vonmises_fisher(mean.numpy(), kappa).rvs(8000, random_state=13))
    ours = se3.angle_between(pose.q, kde.means.q).numpy()
    theirs = se3.angle_between(reference, mean.expand(8000, 4)).numpy()
    assert stats.ks_2samp(ours, theirs).pvalue > 1e-3
    # and the per-axis rotation std is rot_std / sqrt(β_q) = 0.2 rad
    assert math.sqrt((ours**2).mean() / 3) == pytest.approx(0.1 * 2, rel=0.03)


def test_kernels_are_drawn_with_their_weights():
    g = torch.Generator().manual_seed(14)
    weights = torch.tensor([0.5, 0.1, 0.3, 0.1, 0.0])
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1)
    kde = PoseKDE(se3.Pose(torch.zeros(5, 3), torch.tensor([IDENTITY_Q]).expand(5, 4)), bw, weights.log())
    index = kde.sample_kernels(20_000, g)
    counts = torch.bincount(index, minlength=5).numpy()
    assert counts[4] == 0
    assert stats.chisquare(counts[:4], 20_000 * weights[:4].numpy()).pvalue > 1e-3


def test_batched_sampling_uses_each_elements_kernels_and_rounds():
    g = torch.Generator().manual_seed(15)
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1, cutoff_std=(math.inf, 3.0, 3.0))
    means = se3.Pose(torch.tensor([[[0.0, 0, 0]], [[1.0, 0, 0]]]), torch.tensor([IDENTITY_Q]).expand(2, 1, 4))
    kde = PoseKDE(means, bw, trial_rounds=torch.tensor([[0, 0, 0], [2, 0, 0]]))
    pose, _ = kde.sample(10_000, g)
    assert pose.p.shape == (2, 10_000, 3)
    np.testing.assert_allclose(pose.p[0].std(0).numpy(), 0.01, rtol=0.05)
    np.testing.assert_allclose(pose.p[1].std(0).numpy(), 0.02, rtol=0.05)
    assert (pose.p[1, :, 0].mean() - 1.0).abs() < 1e-3


# --------------------------------------------------------------------------------------------------
# Trial rounds
# --------------------------------------------------------------------------------------------------


def _rounds_needed(d, delta, alpha=2.0):
    """Smallest T with α^(−T) d < δ."""
    t = 0
    while alpha ** (-t) * d >= delta:
        t += 1
    return t


@pytest.mark.parametrize("component", ["p", "q", "r"])
def test_trial_rounds_widen_only_the_component_that_was_too_narrow(component):
    dtype = torch.float64
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1, r_std=(1.0,), cutoff_std=(3.0, 3.0, 3.0))
    g = torch.Generator().manual_seed(20)
    identity = torch.tensor([IDENTITY_Q], dtype=dtype).expand(10, 4)
    kernels = se3.Pose(torch.randn(10, 3, generator=g, dtype=dtype) * 0.001, identity)
    kde = PoseKDE(kernels, bw, descriptors=torch.zeros(10, 1, dtype=dtype))
    p = torch.zeros(4, 3, dtype=dtype)
    q = torch.tensor([IDENTITY_Q], dtype=dtype).expand(4, 4).clone()
    r = torch.zeros(4, 1, dtype=dtype)
    if component == "p":
        p[:, 2] = 0.1  # ~10 std away
    elif component == "q":
        q = axis_angle_quaternion([0.0, 1.0, 0.0], 1.2, dtype).expand(4, 4)  # 12 std away
    else:
        r[:, 0] = 9.0  # 9 std away
    queries = se3.Pose(p, q)
    assert (kde.log_prob(queries, r) == -math.inf).all()
    fitted = kde.fit_trial_rounds(queries, r)
    rounds = fitted.trial_rounds.tolist()
    index = "pqr".index(component)
    # the needed number of rounds for the closest (query, kernel) pair
    d = kde.log_kernel_terms(queries, r)[..., index].min().item()
    expected = [0, 0, 0]
    expected[index] = _rounds_needed(d, bw.delta[index])
    assert rounds == expected
    assert torch.isfinite(fitted.log_prob(queries, r)).any()
    # one round fewer would not do: the search stops at the first success
    fewer = torch.tensor(expected) - torch.nn.functional.one_hot(torch.tensor(index), 3)
    assert (kde.with_trial_rounds(fewer).log_prob(queries, r) == -math.inf).all()


def test_trial_rounds_raise_the_smallest_then_the_most_cutting_component():
    dtype = torch.float64
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1, cutoff_std=(3.0, 3.0, 3.0))
    kde = PoseKDE(se3.Pose(torch.zeros(1, 3, dtype=dtype), torch.tensor([IDENTITY_Q], dtype=dtype)), bw)
    ident = torch.tensor(IDENTITY_Q, dtype=dtype)
    turned = axis_angle_quaternion([1.0, 0.0, 0.0], 0.35, dtype)  # β d_q = 6.1 ≥ 4.5: one round fixes it
    far = torch.tensor([0.045, 0, 0], dtype=dtype)  # β d_p = 10.1: needs two rounds
    near = torch.zeros(3, dtype=dtype)

    # one query cut by both: tie at T=0 on rounds and counts → p (order); then q has the smaller T;
    # then only p still cuts.
    both = se3.Pose(far[None], turned[None])
    assert kde.fit_trial_rounds(both).trial_rounds.tolist() == [2, 1, 0]

    # queries cut by p only (1) and by q only (2): tie on rounds, q caused more cut-offs → q, which
    # already covers two queries.
    mixed = se3.Pose(torch.stack([far, near, near]), torch.stack([ident, turned, turned]))
    assert kde.fit_trial_rounds(mixed).trial_rounds.tolist() == [0, 1, 0]
    # p cut-offs (2) beat q (1) at T=0 → T=(1,0,0); p still cuts every far query, but the rounds rule
    # comes first: q has the smaller T → (1,1,0), which covers the third query.
    mixed_p = se3.Pose(torch.stack([far, far, near]), torch.stack([ident, ident, turned]))
    assert kde.fit_trial_rounds(mixed_p).trial_rounds.tolist() == [1, 1, 0]


def test_trial_rounds_are_fitted_per_batch_element():
    dtype = torch.float64
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1)
    means = se3.Pose(torch.tensor([[[0.0, 0, 0]], [[0.05, 0, 0]]], dtype=dtype),
                     torch.tensor([IDENTITY_Q], dtype=dtype).expand(2, 1, 4))
    kde = PoseKDE(means, bw)
    queries = se3.Pose(torch.zeros(3, 3, dtype=dtype), torch.tensor([IDENTITY_Q], dtype=dtype).expand(3, 4))
    fitted = kde.fit_trial_rounds(queries)
    assert fitted.trial_rounds.tolist() == [[0, 0, 0], [_rounds_needed(12.5, 4.5), 0, 0]]
    assert kde.fit_trial_rounds(se3.Pose(queries.p[:0], queries.q[:0])) is kde
    # fitted_log_kernels: the same rounds and kernels; a covered density is returned as it is
    fitted_again, log_k = kde.fitted_log_kernels(queries)
    assert torch.equal(fitted_again.trial_rounds, fitted.trial_rounds)
    assert torch.equal(log_k, fitted.log_kernels(queries))
    covered = PoseKDE(se3.Pose(means.p[:1], means.q[:1]), bw)
    same, log_k = covered.fitted_log_kernels(queries)
    assert same is covered and torch.equal(log_k, covered.log_kernels(queries))


def test_exceeding_max_trial_rounds_raises_model_error():
    dtype = torch.float64
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1, max_trial_rounds=2)
    kde = PoseKDE(se3.Pose(torch.zeros(1, 3, dtype=dtype), torch.tensor([IDENTITY_Q], dtype=dtype)), bw)
    queries = se3.Pose(torch.tensor([[0.2, 0.0, 0.0]], dtype=dtype), torch.tensor([IDENTITY_Q], dtype=dtype))
    with pytest.raises(ModelError, match="trial rounds"):
        kde.fit_trial_rounds(queries)


# --------------------------------------------------------------------------------------------------
# Product of experts
# --------------------------------------------------------------------------------------------------


def test_product_of_experts_sums_weighted_expert_log_densities():
    g = torch.Generator().manual_seed(30)
    bw = KernelBandwidth(p_std=0.03, rot_std=0.8)
    experts = [
        random_kde((2,), n, g, torch.float64, descriptors=False, bw=bw, spread=0.02) for n in (6, 11, 3)
    ]
    stacked = PoseKDE.stack(experts)
    pose, _ = experts[0].sample(9, g)
    log_w = torch.tensor([0.0, math.log(6 / 11), math.log(2.0)], dtype=torch.float64)
    each = torch.stack([k.log_prob(pose) for k in experts])  # (3, 2, 9)
    got = product_log_prob(stacked, pose, log_w)
    assert got.shape == (2, 9)
    finite = torch.isfinite(got)
    assert finite.any()
    torch.testing.assert_close(got[finite], (each + log_w[:, None, None]).sum(0)[finite])
    assert torch.equal(finite, torch.isfinite(each).all(0))  # any expert can veto
    # a masked expert contributes nothing; the object form agrees with the function
    mask = torch.tensor([True, False, True])
    poe = ProductOfExperts(stacked, log_w, mask)
    masked = poe(pose)
    torch.testing.assert_close(masked, each[0] + each[2] + log_w[0] + log_w[2])
    assert poe.batch_shape == (2,) and poe.num_experts == 3
    with pytest.raises(InvalidParameterError):
        product_log_prob(stacked, pose, torch.zeros(2, dtype=torch.float64))
    with pytest.raises(InvalidParameterError):
        product_log_prob(experts[0], pose)


# --------------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(p_std=0.0, rot_std=0.1),
        dict(p_std=float("nan"), rot_std=0.1),
        dict(p_std=0.01, rot_std=-1.0),
        dict(p_std=0.01, rot_std=math.inf),
        dict(p_std=0.01, rot_std=0.1, r_std=(1.0, 0.0)),
        dict(p_std=0.01, rot_std=0.1, r_std=()),
        dict(p_std=0.01, rot_std=0.1, cutoff_std=(3.0, 3.0)),
        dict(p_std=0.01, rot_std=0.1, cutoff_std=(3.0, float("nan"), 3.0)),
        dict(p_std=0.01, rot_std=0.1, alpha_t=1.0),
        dict(p_std=0.01, rot_std=0.1, max_trial_rounds=-1),
        dict(p_std=0.01, rot_std=0.1, max_trial_rounds=2.5),
    ],
)
def test_bad_bandwidth_is_refused(kwargs):
    with pytest.raises(InvalidParameterError):
        KernelBandwidth(**kwargs)


def test_bad_kernels_and_queries_are_refused():
    bw = KernelBandwidth(p_std=0.01, rot_std=0.1)
    p = torch.zeros(3, 3)
    q = torch.tensor([IDENTITY_Q]).expand(3, 4)
    with pytest.raises(InvalidPoseError):
        PoseKDE(se3.Pose(p, q * 2), bw)
    with pytest.raises(InvalidPoseError):
        PoseKDE(se3.Pose(torch.zeros(3, 2), q), bw)
    with pytest.raises(InvalidParameterError, match="zero"):
        PoseKDE(se3.Pose(p, q), bw, torch.full((3,), -math.inf))
    with pytest.raises(InvalidParameterError, match="NaN"):
        PoseKDE(se3.Pose(p, q), bw, torch.tensor([0.0, float("nan"), 0.0]))
    with pytest.raises(InvalidParameterError, match="descriptors"):
        PoseKDE(se3.Pose(p, q), bw, descriptors=torch.zeros(3, 2))
    with pytest.raises(InvalidParameterError):
        PoseKDE(se3.Pose(p, q), bw, trial_rounds=torch.tensor([0.5, 0, 0]))
    with pytest.raises(InvalidParameterError):
        TrialRounds(-1, 0, 0)
    kde = PoseKDE(se3.Pose(p, q), bw)
    with pytest.raises(InvalidPoseError):
        kde.log_prob(se3.Pose(torch.zeros(2, 3), torch.tensor([[1.0, 1.0, 0, 0]]).expand(2, 4)))
    with pytest.raises(InvalidPoseError):
        kde.log_prob(se3.Pose(torch.full((2, 3), float("nan")), q[:2]))
    with pytest.raises(InvalidParameterError):
        kde.log_prob(se3.Pose(p, q), torch.zeros(3, 2))
    batched = PoseKDE(se3.Pose(torch.zeros(2, 3, 3), q.expand(2, 3, 4)), bw)
    with pytest.raises(InvalidPoseError, match="broadcast"):
        batched.log_prob(se3.Pose(torch.zeros(5, 4, 3), torch.tensor([IDENTITY_Q]).expand(5, 4, 4)))


def test_an_evaluation_is_its_string_wherever_a_method_is_taken():
    """``Evaluation.DENSE`` / ``Evaluation.FAST`` name the dense reference and the fast path; each equals its
    string, so a ``method=`` takes either and gives the same values, and anything else is refused."""
    g = torch.Generator().manual_seed(0)
    kde = PoseKDE(se3.Pose(torch.randn(1500, 3, generator=g) * 0.05, torch.tensor([IDENTITY_Q]).expand(1500, 4)),
                  KernelBandwidth(p_std=0.01, rot_std=0.1))
    queries = se3.Pose(torch.randn(20, 3, generator=g) * 0.05, torch.tensor([IDENTITY_Q]).expand(20, 4))
    assert Evaluation.FAST == "fast" and Evaluation.of("dense") is Evaluation.DENSE
    for method in Evaluation:
        assert torch.equal(kde.log_prob(queries, method=method), kde.log_prob(queries, method=str(method)))
        assert torch.equal(kde.mean_shift(queries, method=method).p, kde.mean_shift(queries, method=method.value).p)
    for bad in ("approximate", None, "FAST"):
        with pytest.raises(InvalidParameterError, match="method"):
            Evaluation.of(bad)
        with pytest.raises(InvalidParameterError, match="method"):
            kde.log_prob(queries, method=bad)
