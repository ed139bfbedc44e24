"""Deprecated path of :mod:`pushtorch.evaluation.likelihood`, kept for one release."""

from pushtorch.deprecation import alias_module

alias_module(__name__, "pushtorch.evaluation.likelihood")
