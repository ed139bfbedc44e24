"""The model library with selection by H_r (paper, §Model Selection).

A :class:`ModelLibrary` holds several trained models (one per training object and prior) and selects, for a
new cloud, the one whose manipulator contact model has the lowest feature-distance heuristic ``H_r``; a
:class:`ConditionedLibrary` selects by the models' posterior once observed pushes were accepted.
"""

from __future__ import annotations

import dataclasses

import torch

from pushtorch.errors import InvalidParameterError
from pushtorch.features import SurfaceFeatures
from pushtorch.models.conditioning import Observation, kernel_physics, observations_from_table, summarise
from pushtorch.models.evidence import common_evidence_kernels
from pushtorch.models.model import PushModel
from pushtorch.models.push_condition import features_for
from pushtorch.models.query import feature_distance_heuristic, heuristic_descriptors
from pushtorch.models.settings import as_generator
from pushtorch.sim.tables import PushTable

__all__ = [
    "ConditionedLibrary",
    "ModelLibrary",
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
        r = heuristic_descriptors(features)
        return torch.stack([feature_distance_heuristic(r, m.contact.frames.r) for m in self.models])

    def select(self, features: SurfaceFeatures) -> tuple[PushModel, torch.Tensor]:
        """The model with the lowest ``H_r`` and all models' ``H_r``."""
        h = self.feature_distances(features)
        return self.models[int(h.argmin())], h

    def condition_on(self, observations, seed: int | None = None) -> ConditionedLibrary:
        """Every model conditioned on the observed pushes (:meth:`PushModel.condition_on`), scored under the same
        kernels for all (the widest of the models' widths and their largest outlier share,
        :func:`~pushtorch.models.evidence.common_evidence_kernels`), and the library's posterior over its models
        by their evidence (:class:`ConditionedLibrary`)."""
        shared = self._with_features(observations)
        common = common_evidence_kernels(self.models)  # the models are compared under one set of kernels
        return ConditionedLibrary([m.condition_on(shared, seed, bandwidth=common) for m in self.models])

    def _with_features(self, observations):
        """``observations`` with each cloud's surface features computed once for every model, where the models
        share the feature radius, dtype and device (else as given: each model computes its own)."""
        first = self.models[0]
        same = all(m.settings.feature_radius == first.settings.feature_radius and m.dtype == first.dtype
                   and m.device == first.device for m in self.models)
        if isinstance(observations, PushTable):
            observations = observations_from_table(observations)
        listed = [observations] if isinstance(observations, Observation) else observations
        if not same or not isinstance(listed, list | tuple) or not all(isinstance(o, Observation) for o in listed):
            return observations  # condition_on refuses what is malformed, with its own message
        return [dataclasses.replace(o, cloud=features_for(o.cloud, first.settings, first.position)) for o in listed]


class ConditionedLibrary(ModelLibrary):
    """A library conditioned on observed pushes: each model conditioned, and a posterior over the models
    ``p(M | O) ∝ p_M(O)`` (uniform prior; :meth:`PhysicsPosterior.log_evidence
    <pushtorch.models.conditioning.PhysicsPosterior.log_evidence>`). :meth:`select` takes the model of highest
    posterior once some observation was accepted, and the lowest ``H_r`` before."""

    def __init__(self, models: list[PushModel]) -> None:
        super().__init__(models)
        if any(m.physics_posterior is None for m in self.models):
            raise InvalidParameterError("a conditioned library needs conditioned models (PushModel.condition_on)")

    @property
    def observed(self) -> int:
        return max(m.physics_posterior.observed for m in self.models)

    def model_log_posterior(self) -> torch.Tensor:
        """``(L,)`` float64 log ``p(M | O)`` of the models (uniform without accepted observations)."""
        evidence = torch.tensor([m.physics_posterior.log_evidence() for m in self.models], dtype=torch.float64)
        return torch.log_softmax(evidence, 0)

    def select(self, features: SurfaceFeatures) -> tuple[PushModel, torch.Tensor]:
        """The model of highest posterior (by ``H_r`` before any observation) and all models' ``H_r``."""
        h = self.feature_distances(features)
        if self.observed == 0:
            return self.models[int(h.argmin())], h
        return self.models[int(self.model_log_posterior().argmax())], h

    def posterior(self, n: int = 256, generator: torch.Generator | int | None = None):
        """The mixture of the models' posteriors by the models' posterior weights
        (:class:`~pushtorch.models.conditioning.PosteriorSummary` with ``model_weights``)."""
        thetas, weights = [], []
        log_post = self.model_log_posterior()
        for m, log_pm in zip(self.models, log_post, strict=True):
            theta = kernel_physics(m.motion_kernels)
            log_w, _ = m.physics_posterior.kernel_log_weights(theta)
            thetas.append(theta)
            weights.append(torch.log_softmax(log_w, 0) + log_pm)
        post = log_post.exp()
        return summarise(torch.cat(thetas), torch.cat(weights), n, as_generator(generator), self.observed,
                         max(m.physics_posterior.rejected for m in self.models),
                         model_weights={m.name: float(p) for m, p in zip(self.models, post, strict=True)})
