"""``python -m pushtorch.predict``: the prediction stage app (:mod:`pushtorch.apps.predict`).

The package :mod:`pushtorch.predict` is the library's prediction; this entry point is an app above it, so the
library never imports the app (the import contracts in ``pyproject.toml`` list it with the apps).
"""

from pushtorch.apps.predict import main

if __name__ == "__main__":
    main()
