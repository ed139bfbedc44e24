"""Physical-parameter priors: the distributions a push's mass and friction are drawn from.

Paper, Biasing Transferable Push Manipulation Models: *generalising* draws a parameter from a uniform
distribution over a broad range, *biasing* from a narrow normal centred on the expected condition; the
Experimental Results section and its two parameter tables give the values (``conf/friction/*.yaml`` and
``conf/mass/*.yaml`` hold them as a Hydra config group):

    friction  general U(0.085, 0.805), low N(0.1, 0.005), medium N(0.4, 0.02), high N(0.7, 0.035),
              paper_default N(0.3, 0.05) (the mass experiment's ground friction)
    mass      general U(0.085, 5.75) kg, low N(0.1, 0.005), medium N(1.0, 0.05), high N(5.0, 0.25),
              paper_default N(0.5, 0.025) (the friction experiment's mass)

The mass ``general`` range: the paper's text says U(0.85, 5.75) kg and its table U(0.085, 5.75). The table's
range is used: a generalising prior should cover the conditions it is meant to generalise over, and the
text's range would exclude the "low" condition N(0.1, 0.005) kg entirely.

Samples are clipped to physical values (a normal can go negative): every prior has a ``minimum`` (default
1e-3), applied with ``clamp``. Sampling is batched and takes an explicit ``torch.Generator``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch

from pushtorch.errors import InvalidParameterError

__all__ = ["Fixed", "Normal", "Prior", "Uniform", "prior_from_config"]

#: Smallest value a sampled mass (kg) or friction coefficient may take.
PHYSICAL_MINIMUM = 1e-3


def _check_finite(**values: float) -> None:
    for name, value in values.items():
        if not (isinstance(value, int | float) and math.isfinite(value)):
            raise InvalidParameterError(f"prior parameter {name} must be a finite number, got {value!r}")


@dataclass(frozen=True)
class Fixed:
    """Every sample is ``value``."""

    value: float
    minimum: float = PHYSICAL_MINIMUM

    def __post_init__(self) -> None:
        _check_finite(value=self.value, minimum=self.minimum)
        if self.value < self.minimum:
            raise InvalidParameterError(
                f"fixed value {self.value} is below the physical minimum {self.minimum}"
            )

    @property
    def mean(self) -> float:
        return float(self.value)

    def sample(
        self,
        shape: tuple[int, ...],
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> torch.Tensor:
        """``shape`` copies of the value (the generator is not advanced)."""
        return torch.full(tuple(shape), float(self.value), dtype=dtype)


@dataclass(frozen=True)
class Uniform:
    """U(low, high), the paper's *generalising* prior."""

    low: float
    high: float
    minimum: float = PHYSICAL_MINIMUM

    def __post_init__(self) -> None:
        _check_finite(low=self.low, high=self.high, minimum=self.minimum)
        if not self.low < self.high:
            raise InvalidParameterError(f"uniform prior needs low < high, got [{self.low}, {self.high}]")
        if self.high < self.minimum:
            raise InvalidParameterError(f"uniform prior [{self.low}, {self.high}] lies below {self.minimum}")

    @property
    def mean(self) -> float:
        return 0.5 * (self.low + self.high)

    def sample(
        self,
        shape: tuple[int, ...],
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> torch.Tensor:
        """Samples of shape ``shape`` drawn with ``generator``, clipped at ``minimum``."""
        u = torch.rand(tuple(shape), generator=generator, dtype=torch.float64)
        return (self.low + (self.high - self.low) * u).clamp_min(self.minimum).to(dtype)


@dataclass(frozen=True)
class Normal:
    """N(mean, std), the paper's *biasing* prior (clipped at ``minimum``)."""

    loc: float
    std: float
    minimum: float = PHYSICAL_MINIMUM

    def __post_init__(self) -> None:
        _check_finite(mean=self.loc, std=self.std, minimum=self.minimum)
        if self.std <= 0:
            raise InvalidParameterError(f"normal prior needs std > 0, got {self.std}")
        if self.loc < self.minimum:
            raise InvalidParameterError(f"normal prior mean {self.loc} lies below the physical minimum")

    @property
    def mean(self) -> float:
        return float(self.loc)

    def sample(
        self,
        shape: tuple[int, ...],
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> torch.Tensor:
        """Samples of shape ``shape`` drawn with ``generator``, clipped at ``minimum``."""
        z = torch.randn(tuple(shape), generator=generator, dtype=torch.float64)
        return (self.loc + self.std * z).clamp_min(self.minimum).to(dtype)


Prior = Fixed | Uniform | Normal


def prior_from_config(config: Mapping[str, Any]) -> Prior:
    """A prior from a config mapping (a ``conf/friction`` or ``conf/mass`` entry).

    Accepted forms: ``{kind: uniform, low, high}``, ``{kind: normal, mean, std}``,
    ``{kind: fixed, value}``; each may add ``minimum``. Other keys (e.g. ``name``, ``description``) are
    ignored.

    Raises:
        InvalidParameterError: unknown kind, a missing key, or values outside their ranges.
    """
    kind = str(config.get("kind", "")).lower()
    minimum = float(config.get("minimum", PHYSICAL_MINIMUM))
    try:
        if kind == "uniform":
            return Uniform(float(config["low"]), float(config["high"]), minimum)
        if kind == "normal":
            return Normal(float(config["mean"]), float(config["std"]), minimum)
        if kind == "fixed":
            return Fixed(float(config["value"]), minimum)
    except KeyError as exc:
        raise InvalidParameterError(f"a {kind} prior needs the key {exc.args[0]!r}") from exc
    raise InvalidParameterError(f"unknown prior kind {config.get('kind')!r}: use uniform, normal or fixed")
