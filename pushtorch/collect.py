"""Deprecated path of :mod:`pushtorch.apps.collect`, kept for one release (``python -m pushtorch.collect`` runs
the app as before, without a warning)."""

if __name__ == "__main__":
    import sys

    from pushtorch.apps.collect import main

    sys.exit(main())
else:
    from pushtorch.deprecation import alias_module

    alias_module(__name__, "pushtorch.apps.collect")
