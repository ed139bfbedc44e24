"""Deprecated path of :mod:`pushtorch.prediction`, kept for one release; ``python -m pushtorch.predict`` runs
the prediction app (:mod:`pushtorch.apps.predict`) as before, without a warning."""

if __name__ == "__main__":
    from pushtorch.apps.predict import main

    main()
else:
    from pushtorch.deprecation import alias_module

    alias_module(__name__, "pushtorch.prediction")
