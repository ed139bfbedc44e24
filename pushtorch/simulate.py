"""Deprecated path of :mod:`pushtorch.apps.simulate`, kept for one release (``python -m pushtorch.simulate`` runs
the app as before, without a warning)."""

if __name__ == "__main__":
    from pushtorch.apps.simulate import main

    main()
else:
    from pushtorch.deprecation import alias_module

    alias_module(__name__, "pushtorch.apps.simulate")
