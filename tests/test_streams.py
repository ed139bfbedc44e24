"""Counter-based random streams (pushtorch.streams): a problem's draws are a function of its key, whatever else
shares the batch, in the library's own samplers too; the laws are the ones the samplers promise."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pushtorch import se3
from pushtorch.errors import PushtorchError
from pushtorch.kde.sampling import sample_rotation_offsets
from pushtorch.streams import KeyedStream

keys_lists = st.lists(st.integers(0, 10_000), min_size=1, max_size=6, unique=True)


@settings(max_examples=30, deadline=None)
@given(keys=keys_lists, seed=st.integers(0, 2**64 - 1), extra=st.integers(0, 4))
def test_a_problems_draws_do_not_depend_on_the_others(keys, seed, extra):
    together = KeyedStream(seed, torch.tensor(keys))
    alone = [KeyedStream(seed, torch.tensor(keys)).take(i) for i in range(len(keys))]
    for _ in range(extra):  # earlier calls advance every stream alike
        together.uniform((len(keys), 2))
        for s in alone:
            s.uniform((2,))
    u = together.uniform((len(keys), 3, 2))
    n = together.along(1).normal((5, len(keys), 4), torch.float64)
    for i, s in enumerate(alone):
        assert torch.equal(u[i], s.uniform((3, 2)))
        assert torch.equal(n[:, i], s.normal((5, 4), torch.float64))


def test_the_laws_are_uniform_and_normal_and_the_weights_are_drawn_in_proportion():
    stream = KeyedStream(7, torch.arange(4))
    u = stream.uniform((4, 50_000), torch.float64)
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    # 200,000 draws: the mean's standard error is 6.5e-4, the variance's 1.3e-4
    assert abs(float(u.mean()) - 0.5) < 4e-3 and abs(float(u.var()) - 1 / 12) < 1e-3
    n = stream.normal((4, 50_000))
    assert abs(float(n.mean())) < 0.012 and abs(float(n.std()) - 1.0) < 0.01
    assert abs(float((n.abs() < 1.0).double().mean()) - 0.6827) < 0.005
    weights = torch.tensor([[0.0, 1.0, 3.0, 0.0, 6.0]]).expand(4, 5)
    picks = stream.multinomial(weights, 20_000)
    share = torch.bincount(picks.reshape(-1), minlength=5).double() / picks.numel()
    assert share[0] == 0 and share[3] == 0
    assert torch.allclose(share[[1, 2, 4]], torch.tensor([0.1, 0.3, 0.6], dtype=torch.float64), atol=0.01)
    perm = KeyedStream(3, torch.tensor([0])).take(0).permutation(100)
    assert sorted(perm.tolist()) == list(range(100)) and perm.tolist() != list(range(100))


def test_phases_and_seeds_give_other_numbers():
    a, b = KeyedStream(0, torch.arange(3)), KeyedStream(1, torch.arange(3))
    assert not torch.equal(a.uniform((3, 8)), b.uniform((3, 8)))
    first, second = a.fork(), a.fork()
    assert not torch.equal(first.uniform((3, 8)), second.uniform((3, 8)))
    assert a.calls == 3  # one draw and two forks


@settings(max_examples=15, deadline=None)
@given(kappas=st.lists(st.sampled_from([0.5, 3.0, 40.0, 500.0]), min_size=2, max_size=5),
       delta=st.sampled_from([2.0, math.inf]))
def test_vmf_rows_are_their_own_whatever_their_neighbours_concentration(kappas, delta):
    """The rejection sampler and the inverse-CDF branch draw every row, so a row's rotation is the same in a batch
    of cheap and expensive neighbours as alone."""
    kappa = torch.tensor(kappas, dtype=torch.float64).unsqueeze(-1).expand(len(kappas), 16)
    together = se3.vmf_offsets(kappa, kappa.shape, KeyedStream(5, torch.arange(len(kappas))), torch.float64,
                               delta=delta)
    for i in range(len(kappas)):
        alone = se3.vmf_offsets(kappa[i], (16,), KeyedStream(5, torch.tensor([i])).take(0), torch.float64,
                                delta=delta)
        assert torch.equal(together[i], alone)
    assert torch.allclose(together.norm(dim=-1), torch.ones(()).double())


def test_keyed_vmf_draws_follow_the_law_of_the_generator_draws():
    """The same sampler under either stream: the mean of |w| agrees within its standard error."""
    kappa = torch.full((20_000,), 8.0, dtype=torch.float64)
    keyed = sample_rotation_offsets(kappa, 3.0, KeyedStream(0, torch.tensor([0])).take(0))
    plain = sample_rotation_offsets(kappa, 3.0, torch.Generator().manual_seed(0))
    a, b = keyed[:, 0].abs(), plain[:, 0].abs()
    se = math.sqrt(float(a.var()) / len(a) + float(b.var()) / len(b))
    assert abs(float(a.mean()) - float(b.mean())) < 5 * se
    assert bool((8.0 * (1 - a) < 3.0 + 1e-9).all())  # the cut-off holds


def test_bad_streams_are_refused_by_name():
    with pytest.raises(PushtorchError, match="seed"):
        KeyedStream(-1, torch.arange(2))
    with pytest.raises(PushtorchError, match="integer key"):
        KeyedStream(0, torch.zeros(0, dtype=torch.int64))
    with pytest.raises(PushtorchError, match="integer key"):
        KeyedStream(0, torch.tensor([0.5]))
    with pytest.raises(PushtorchError, match="3 problems"):
        KeyedStream(0, torch.arange(3)).uniform((4, 2))
    with pytest.raises(PushtorchError, match="replacement"):
        se3.multinomial(torch.ones(3, 4), 2, KeyedStream(0, torch.arange(3)), replacement=False)
