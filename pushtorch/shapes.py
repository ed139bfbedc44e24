"""Deprecated path of :mod:`pushtorch.objects.shapes` (random convex shapes), kept for one release."""

from pushtorch.deprecation import alias_module

alias_module(__name__, "pushtorch.objects.shapes")
