"""Deprecated path of :mod:`pushtorch.apps.predict`, kept for one release (``python -m pushtorch.predict_cli``
runs the app as before, without a warning)."""

if __name__ == "__main__":
    from pushtorch.apps.predict import main

    main()
else:
    from pushtorch.deprecation import alias_module

    alias_module(__name__, "pushtorch.apps.predict")
