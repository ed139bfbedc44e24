"""A trained push model, its file format, and the model library with selection by H_r (paper, §TPMM, §Model Selection).

A :class:`PushModel` is what one training run produces (paper, Fig. pipeline, training): the manipulator
contact model and the position model of the training object (stage one) and one motion model per
action from the push records (stage two), with the settings used at prediction time. A
:class:`ModelLibrary` holds several (one per training object and prior) and selects, for a new cloud,
the one whose manipulator contact model has the lowest feature-distance heuristic ``H_r``.

Model files are ``.npz`` archives read with ``allow_pickle=False``: tensors plus one JSON header
(format name, version, settings, SHA-256 of every array), sealed by one SHA-256 over every byte of the
archive before it, kept as the archive's 64-character zip comment (:func:`pushtorch.io.sealed_archive`).
Any edited byte (an array, the header's action count or a setting, the zip structure) breaks the seal. A
file of another version, a corrupt, edited or malformed file, or one whose settings construction would
refuse is refused with :class:`~pushtorch.errors.RecordFormatError`. Saving is atomic; the temporaries a
killed save leaves are removed by the next save to the same path, under the folder's lock
(:func:`pushtorch.io.folder_lock`).
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
