"""Deprecated path of :mod:`pushtorch.apps.train`, kept for one release (``python -m pushtorch.train`` runs the
app as before, without a warning)."""

if __name__ == "__main__":
    from pushtorch.apps.train import main

    main()
else:
    from pushtorch.deprecation import alias_module

    alias_module(__name__, "pushtorch.apps.train")
