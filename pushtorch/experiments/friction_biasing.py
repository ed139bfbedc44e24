"""Friction biasing (paper, §Prediction Accuracy on Novel Contexts, friction table).

``python -m pushtorch experiment=friction_biasing``: general / low / medium / high friction models ×
low / medium / high friction test conditions × the six test objects; see :mod:`pushtorch.experiments.biasing`.
"""

from pushtorch.experiments.biasing import run

__all__ = ["run"]
