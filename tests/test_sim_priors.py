"""Physical-parameter priors: the paper's values from the config group, batched sampling, clipping."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml
from hypothesis import given
from hypothesis import strategies as st

from pushtorch.errors import InvalidParameterError
from pushtorch.objects import load_object
from pushtorch.sim import (
    Fixed,
    Normal,
    Placement,
    Uniform,
    make_actions,
    plan_training_pushes,
    prior_from_config,
)

CONF = Path(__file__).resolve().parents[1] / "conf"

PAPER = {
    ("friction", "general"): ("uniform", 0.085, 0.805),
    ("friction", "low"): ("normal", 0.1, 0.005),
    ("friction", "medium"): ("normal", 0.4, 0.02),
    ("friction", "high"): ("normal", 0.7, 0.035),
    ("friction", "paper_default"): ("normal", 0.3, 0.05),
    ("mass", "general"): ("uniform", 0.085, 5.75),
    ("mass", "low"): ("normal", 0.1, 0.005),
    ("mass", "medium"): ("normal", 1.0, 0.05),
    ("mass", "high"): ("normal", 5.0, 0.25),
    ("mass", "paper_default"): ("normal", 0.5, 0.025),
}


@pytest.mark.parametrize(("group", "name"), sorted(PAPER))
def test_config_group_holds_the_papers_priors_and_samples_them(group, name):
    prior = prior_from_config(yaml.safe_load((CONF / group / f"{name}.yaml").read_text()))
    kind, a, b = PAPER[(group, name)]
    n = 40_000
    x = prior.sample((n,), torch.Generator().manual_seed(0))
    assert x.shape == (n,) and (x > 0).all()
    if kind == "uniform":
        assert isinstance(prior, Uniform) and (prior.low, prior.high) == (a, b)
        assert a <= float(x.min()) and float(x.max()) <= b
        mean, std = (a + b) / 2, (b - a) / math.sqrt(12)
    else:
        assert isinstance(prior, Normal) and (prior.loc, prior.std) == (a, b)
        mean, std = a, b
    # sample moments within 5 standard errors
    assert abs(float(x.mean()) - mean) < 5 * std / math.sqrt(n)
    assert abs(float(x.std()) - std) < 5 * std * math.sqrt(2 / n) + 1e-12


def test_general_mass_covers_the_low_condition():
    general = prior_from_config(yaml.safe_load((CONF / "mass" / "general.yaml").read_text()))
    assert general.low <= 0.1 - 3 * 0.005


def test_fixed_priors():
    for group in ("friction", "mass"):
        prior = prior_from_config(yaml.safe_load((CONF / group / "fixed.yaml").read_text()))
        assert isinstance(prior, Fixed)
        assert torch.equal(prior.sample((4,)), torch.full((4,), prior.value, dtype=torch.float64))


@given(
    loc=st.floats(0.001, 10.0),
    std=st.floats(0.001, 20.0),
    minimum=st.floats(1e-4, 1e-2),
    seed=st.integers(0, 2**31 - 1),
)
def test_samples_never_fall_below_the_physical_minimum(loc, std, minimum, seed):
    loc = max(loc, minimum)
    x = Normal(loc, std, minimum).sample((2, 50), torch.Generator().manual_seed(seed))
    assert x.shape == (2, 50) and bool((x >= minimum).all()) and bool(torch.isfinite(x).all())


def test_same_generator_seed_same_samples():
    prior = Uniform(0.085, 0.805)
    a = prior.sample((100,), torch.Generator().manual_seed(7))
    b = prior.sample((100,), torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


@pytest.mark.parametrize(
    "config",
    [
        {"kind": "uniform", "low": 1.0, "high": 0.5},
        {"kind": "normal", "mean": 0.3, "std": 0.0},
        {"kind": "normal", "mean": -1.0, "std": 0.1},
        {"kind": "fixed", "value": 0.0},
        {"kind": "fixed", "value": float("nan")},
        {"kind": "normal", "mean": 0.3},
        {"kind": "gamma", "a": 1},
    ],
)
def test_invalid_prior_configs_raise(config):
    with pytest.raises(InvalidParameterError):
        prior_from_config(config)


def test_plan_is_a_pure_function_of_the_seed():
    cube = load_object("cube")
    args = (cube, make_actions(3), 4, Uniform(0.085, 5.75), Normal(0.3, 0.05))
    placement = Placement(lateral_jitter=0.02, yaw_jitter_deg=5.0)
    a = plan_training_pushes(*args, seed=11, placement=placement)
    b = plan_training_pushes(*args, seed=11, placement=placement)
    c = plan_training_pushes(*args, seed=12, placement=placement)
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()
    assert len(a) == 12 and a.action_index.tolist() == [0] * 4 + [1] * 4 + [2] * 4
    assert torch.equal(a.action, make_actions(3).double()[a.action_index])
    # jitter spreads the robot's start but keeps it behind the object, heading roughly +x
    assert float(a.robot_start.p[:, 1].std()) > 0.005
    assert (a.robot_start.p[:, 0] < -0.3).all()
