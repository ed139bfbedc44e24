"""pushtorch's Hydra configs, installed as the package ``pushtorch.conf``.

The YAML files live in the repository's top-level ``conf/`` folder; ``pyproject.toml`` maps that folder to
the package ``pushtorch.conf`` (setuptools ``package-dir``), so a wheel carries them and every app finds
them as ``pkg://pushtorch.conf`` from any working directory, in a checkout or after ``pip install``.
Users add folders of their own with Hydra's search path (README, "Your own configs").
"""
