"""Deprecated path of :mod:`pushtorch.apps.cli`, kept for one release."""

from pushtorch.deprecation import alias_module

alias_module(__name__, "pushtorch.apps.cli")
