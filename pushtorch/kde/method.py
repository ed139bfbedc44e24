"""How a density is evaluated: :class:`Evaluation`, the dense reference or the fast path.

Paper, Background → Kernel Density Estimation: the densities are weighted kernel sums with hard cut-offs.
The package evaluates them two ways that give the same values up to float rounding: ``DENSE``, the
reference implementation (every query against every kernel), and ``FAST``, exact distances in fused,
optionally compiled passes over only the kernels the cut-offs let reach a query (module docstring of
:mod:`pushtorch.kde`). Every ``method=`` argument of the package — densities, annealing, the models,
prediction — takes an :class:`Evaluation` or its string, ``"dense"`` or ``"fast"``: a member *is* that
string (a :class:`~enum.StrEnum`), so code that compares ``method == "fast"`` accepts either.
"""

from __future__ import annotations

from enum import StrEnum

from pushtorch.errors import InvalidParameterError

__all__ = ["Evaluation"]


class Evaluation(StrEnum):
    """The evaluation of a density: ``Evaluation.DENSE`` (the reference) or ``Evaluation.FAST``; equal to
    the strings ``"dense"`` and ``"fast"``, which every ``method=`` still accepts."""

    DENSE = "dense"
    FAST = "fast"

    @classmethod
    def of(cls, method: Evaluation | str) -> Evaluation:
        """``method`` (an :class:`Evaluation` or its string) as an :class:`Evaluation`.

        Raises:
            InvalidParameterError: anything else.
        """
        try:
            return cls(method)
        except ValueError:
            raise InvalidParameterError(f"method must be 'dense' or 'fast', got {method!r}") from None
