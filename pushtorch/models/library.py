"""The model library with selection by H_r (paper, §Model Selection), and the models' one entry point.

A :class:`ModelLibrary` holds several trained models (one per training object and prior) and selects, for a
new cloud, the one whose manipulator contact model has the lowest feature-distance heuristic ``H_r``. This
module also gathers the names of :mod:`~pushtorch.models.settings`, :mod:`~pushtorch.models.model` (a trained
:class:`PushModel` and its file format) and :mod:`~pushtorch.models.training`, as it did before they were
modules of their own.
"""

from __future__ import annotations

import torch

from pushtorch.errors import InvalidParameterError
from pushtorch.features import SurfaceFeatures
from pushtorch.models.model import (  # noqa: F401  (re-exported: the models' one entry point)
    FORMAT,
    VERSION,
    PushModel,
    load_model,
)
from pushtorch.models.settings import (  # noqa: F401  (re-exported: the models' one entry point)
    DEFAULT_SEED,
    ModelSettings,
    as_generator,
    check_action,
)
from pushtorch.models.training import (  # noqa: F401  (re-exported: the models' one entry point)
    train_push_model,
    training_features,
)

__all__ = [
    "DEFAULT_SEED",
    "FORMAT",
    "ModelLibrary",
    "ModelSettings",
    "PushModel",
    "VERSION",
    "as_generator",
    "check_action",
    "load_model",
    "train_push_model",
    "training_features",
]


class ModelLibrary:
    """Several trained models; :meth:`select` picks one for a cloud by the lowest ``H_r``."""

    def __init__(self, models: list[PushModel]) -> None:
        if not models:
            raise InvalidParameterError("a model library needs at least one model")
        self.models = list(models)

    def __len__(self) -> int:
        return len(self.models)

    def feature_distances(self, features: SurfaceFeatures) -> torch.Tensor:
        """``H_r`` of every model's manipulator contact model on the cloud's features, ``(L,)``."""
        from pushtorch.models.query import feature_distance_heuristic, heuristic_descriptors

        r = heuristic_descriptors(features)
        return torch.stack([feature_distance_heuristic(r, m.contact.frames.r) for m in self.models])

    def select(self, features: SurfaceFeatures) -> tuple[PushModel, torch.Tensor]:
        """The model with the lowest ``H_r`` and all models' ``H_r``."""
        h = self.feature_distances(features)
        return self.models[int(h.argmin())], h
