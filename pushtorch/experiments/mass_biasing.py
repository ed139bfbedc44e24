"""Mass biasing (paper, §Prediction Accuracy on Novel Contexts, mass table).

``python -m pushtorch experiment=mass_biasing``: general / low / medium / high mass models × low / medium /
high mass test conditions × the six test objects; see :mod:`pushtorch.experiments.biasing`.
"""

from pushtorch.experiments.biasing import run

__all__ = ["run"]
