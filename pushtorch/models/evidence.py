"""The evidence of observed pushes about friction and mass (paper, §Conclusions and future work: "comparing
observed movements of the pushed object with the PDRs already available in the system").

An observed push's contacts are placed as a prediction places them at a given robot start (the manipulator frame
the bumper touches, the environment frames, the contact patch; without a start, the model's own push condition);
its experts weigh the action's kernels by their contact weights. The observed world motion and each kernel's
carry the observed cloud's centroid (:func:`reference_pose`: no pose estimate, no object frame to agree on), and
the observed outcome is scored under each kernel, uncut and normalised (models of different bandwidths are
weighed against each other by it). Where the observation has the robot's own final pose (its odometry), the
robot's motion is scored too, under the kernels'
(:func:`~pushtorch.models.conditioning.odometry_log_likelihood`).
:func:`pushtorch.models.conditioning.cell_log_likelihood` pools that into the likelihood of every cell of
``(μ, log m)``; :func:`condition_model` is what
:meth:`PushModel.condition_on <pushtorch.models.model.PushModel.condition_on>` runs (and
:meth:`ModelLibrary.condition_on <pushtorch.models.library.ModelLibrary.condition_on>` for each of its models).
The push conditions come from :mod:`pushtorch.models.push_condition`, as a prediction's do. The method and its
likelihood are written down in :mod:`pushtorch.models.conditioning` and docs/method.md.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.kde import KernelBandwidth, PoseKDE
from pushtorch.kde.normaliser import NO_CUTOFF, log_kernel_normaliser
from pushtorch.models.conditioning import (
    OUTLIER_ANGLE,
    OUTLIER_DISTANCE,
    Observation,
    PhysicsPosterior,
    cell_log_likelihood,
    conditioned_model,
    kernel_physics,
    log_membership,
    new_posterior,
    observation_seed,
    observations_from_table,
    odometry_log_likelihood,
)
from pushtorch.models.contact import bumper_contact_patch
from pushtorch.models.motion import contact_log_weights, expert_exponents
from pushtorch.models.push_condition import features_for, given_start_frame, push_conditions
from pushtorch.sim.tables import PushTable

if TYPE_CHECKING:
    from pushtorch.models.model import PushModel

__all__ = [
    "EvidenceKernels",
    "common_evidence_kernels",
    "condition_model",
    "observation_evidence",
    "observed_outcome",
    "reference_pose",
    "robot_motion_of",
]

log = logging.getLogger(__name__)


def _as_list(observations) -> list[Observation]:
    if isinstance(observations, Observation):
        return [observations]
    if isinstance(observations, PushTable):  # a robot's own log of its first pushes
        return observations_from_table(observations)
    if isinstance(observations, str | bytes) or not isinstance(observations, Sequence):
        raise InvalidParameterError(f"observations must be an Observation or a list of them, got "
                                    f"{type(observations).__name__}")
    out = list(observations)
    for o in out:
        if not isinstance(o, Observation):
            raise InvalidParameterError(f"observations must be pushtorch Observations, got {type(o).__name__}")
    return out


def reference_pose(features) -> se3.Pose:
    """``()`` where an observed push's motions are compared: the observed cloud's centroid, unrotated. Kernels'
    and observed world motions alike carry it (``W ∘ B``), so no object frame has to agree with the model's."""
    p = features.p.reshape(-1, 3).mean(0)
    return se3.Pose.unchecked(p, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=p.dtype, device=p.device))


def observed_outcome(observation: Observation, reference: se3.Pose) -> se3.Pose:
    """The observed world motion applied to the reference pose: ``W ∘ B`` ``()``."""
    w = observation.displacement
    w = se3.Pose.unchecked(w.p.to(reference.p), w.q.to(reference.q))
    return se3.compose(w, se3.Pose.unchecked(reference.p.reshape(3), reference.q.reshape(4)))


def _contacts(model: PushModel, features, a: int, start: se3.Pose | None, generator):
    """The robot start, the manipulator and environment frames and the contact patch of an observed push: from
    its given start without any annealing, or the model's own push condition when the start is unknown."""
    if start is None:
        condition = push_conditions(model, [features], [a], generator, False, [None])[0]
        return condition.robot_start, condition.manipulator_frame, condition.environment_frames, \
            condition.contact_patch
    start = se3.Pose.unchecked(start.p.reshape(3).to(features.p), start.q.reshape(4).to(features.p))
    frame = given_start_frame(start, features, model)
    environment = model.motions[a].environment_frames(features, model.settings, generator)
    patch = bumper_contact_patch(se3.apply(se3.inverse(start), features.p), model.settings.contact_cutoff)
    return start, frame, environment, patch


def observation_evidence(model: PushModel, observation: Observation, posterior: PhysicsPosterior,
                         generator: torch.Generator | None = None,
                         bandwidth: EvidenceKernels | KernelBandwidth | None = None) -> torch.Tensor | None:
    """``(G,)`` the cell log-likelihood of one observed push under ``model`` (its trained kernels), or None
    when no kernel its contacts reach explains the outcome (:data:`~pushtorch.models.conditioning.OUTLIER_DISTANCE`,
    :data:`~pushtorch.models.conditioning.OUTLIER_ANGLE`).

    Raises:
        InvalidParameterError: an action the model was not trained for.
        ModelError, InvalidPoseError: a robot start that does not touch the cloud, as ``predict`` refuses it.
    """
    settings = model.settings
    a = model.action_index(observation.action)
    features = features_for(observation.cloud, settings, model.position)
    start, manipulator_frame, environment_frames, patch = _contacts(model, features, a, observation.robot_start,
                                                                    generator)
    reference = reference_pose(features)
    y = observed_outcome(observation, reference)
    motion = model.motions[a]
    to_final = se3.relative(start, reference)
    # the calibrated kernels with their outlier share (a library's common kernels, where one compares its models)
    evidence_kernels = EvidenceKernels.of(bandwidth if bandwidth is not None else settings)
    memberships, weights, log_kernels, explained = [], [], [], False
    for frame, kernels in ((manipulator_frame, motion.manipulator), (environment_frames, motion.environment)):
        kernels = dataclasses.replace(kernels, log_weight=None)  # the trained kernels: the posterior is the prior
        log_w = contact_log_weights(frame, kernels, start, settings.contact_bandwidth, patch)  # (F, N)
        finals = se3.compose(se3.compose(start, kernels.m), to_final)  # (N,)
        log_k = evidence_kernels.log_kernels(finals, y)
        reached = torch.isfinite(log_w).any(0)
        distance = (finals.p - y.p.reshape(1, 3)).norm(dim=-1)
        angle = se3.angle_between(finals.q, y.q.reshape(1, 4).expand_as(finals.q))
        explained |= bool((reached & (distance <= OUTLIER_DISTANCE) & (angle <= OUTLIER_ANGLE)).any())
        memberships.append(log_membership(kernel_physics([kernels]), posterior.centres, posterior.scale))
        weights.append(log_w)
        log_kernels.append(log_k)
    if not explained:
        return None
    exponents = expert_exponents(len(motion.manipulator), len(motion.environment),
                                 int(weights[0].shape[0] + weights[1].shape[0]) - 1, settings.pool_sharpness,
                                 torch.float64)
    cells = cell_log_likelihood(memberships, weights, log_kernels, exponents)
    if observation.robot_final is not None and motion.manipulator.robot_motion is not None:
        cells = cells + odometry_log_likelihood(memberships[0], motion.manipulator.robot_motion,
                                                robot_motion_of(start, observation.robot_final))
    return cells


@dataclasses.dataclass(frozen=True)
class EvidenceKernels:
    """The motion kernels observed pushes are weighed under: each the scale mixture ``(1 − outlier) K_density +
    outlier · K_wide`` of two normalised, uncut kernels (docs/method.md, "The evidence's outlier share").

    Attributes:
        density: the calibrated kernels (``ModelSettings.density_bandwidth``).
        wide: the outlier component's kernels (the mode's, ``ModelSettings.motion_bandwidth``).
        outlier: its share ``ε`` in ``[0, 1)`` (``ModelSettings.density_outlier``); 0: the density alone.
    """

    density: KernelBandwidth
    wide: KernelBandwidth
    outlier: float = 0.0

    @staticmethod
    def of(source) -> EvidenceKernels:
        """The evidence kernels of model settings, or ``source`` itself: an :class:`EvidenceKernels`, or a
        :class:`~pushtorch.kde.KernelBandwidth` (those kernels alone, no outlier share)."""
        if isinstance(source, EvidenceKernels):
            return source
        if isinstance(source, KernelBandwidth):
            return EvidenceKernels(source, source, 0.0)
        if not hasattr(source, "density_outlier"):
            raise InvalidParameterError(f"evidence kernels come from EvidenceKernels, a KernelBandwidth or model "
                                        f"settings, got {type(source).__name__}")
        return EvidenceKernels(source.density_bandwidth, source.motion_bandwidth, float(source.density_outlier))

    def log_kernels(self, means: se3.Pose, y: se3.Pose) -> torch.Tensor:
        """``(N,)`` float64: each kernel's normalised log density at the one pose ``y``."""
        query = se3.Pose.unchecked(y.p.reshape(1, 3), y.q.reshape(1, 4))

        def normalised(bandwidth: KernelBandwidth) -> torch.Tensor:
            kde = PoseKDE(means, dataclasses.replace(bandwidth, cutoff_std=NO_CUTOFF), validate_args=False)
            # normalised kernels: models of different bandwidths are compared by their evidence
            return kde.log_kernels(query).reshape(-1).double() - log_kernel_normaliser(kde).reshape(())

        log_k = normalised(self.density)
        if self.outlier > 0:
            log_k = torch.logaddexp(log_k + math.log1p(-self.outlier), normalised(self.wide) + math.log(self.outlier))
        return log_k


def common_evidence_kernels(models) -> EvidenceKernels:
    """The kernels a library weighs observations with for all of its models: the widest of their density stds
    and of their mode stds, position and rotation apart, and the largest outlier share (docs/method.md, "Two
    widths: the mode and the density"). Each model's own width was chosen on its own training pushes; compared
    at them, a model trained on a narrower spread of outcomes would win by its narrower kernels alone on pushes
    it does not fit."""
    def widest(name: str) -> KernelBandwidth:
        first = getattr(models[0].settings, name)
        return dataclasses.replace(first, p_std=max(getattr(m.settings, name).p_std for m in models),
                                   rot_std=max(getattr(m.settings, name).rot_std for m in models))

    return EvidenceKernels(widest("density_bandwidth"), widest("motion_bandwidth"),
                           max(float(m.settings.density_outlier) for m in models))


def robot_motion_of(robot_start: se3.Pose, robot_final: se3.Pose) -> torch.Tensor:
    """``(3,)`` float64 the robot's final pose in its start frame: x, y (m) and yaw (rad)."""
    start = se3.Pose.unchecked(robot_start.p.reshape(3).double(), robot_start.q.reshape(4).double())
    final = se3.Pose.unchecked(robot_final.p.reshape(3).double(), robot_final.q.reshape(4).double())
    moved = se3.relative(start, final)
    return torch.stack([moved.p[0], moved.p[1], se3.yaw_of(moved.q)])


def condition_model(model: PushModel, observations, seed: int | None = None, prior: tuple | None = None,
                    bandwidth: EvidenceKernels | KernelBandwidth | None = None) -> PushModel:
    """:meth:`PushModel.condition_on <pushtorch.models.model.PushModel.condition_on>`; ``bandwidth``: the motion
    kernels the observations are scored under (default the model's :class:`EvidenceKernels`; a library passes
    the common kernels of its models, :func:`common_evidence_kernels`)."""
    observations = _as_list(observations)
    posterior = model.physics_posterior
    if posterior is None:
        posterior = new_posterior(model.motion_kernels, 0 if seed is None else seed, prior)
    elif prior is not None:
        raise InvalidParameterError("de-biasing (prior=...) applies to a model not yet conditioned")
    elif seed is not None and seed != posterior.seed:
        raise InvalidParameterError(f"this model was conditioned with seed {posterior.seed}; continue with that seed "
                                    f"(or None), not {seed}")
    for obs in observations:
        index = posterior.observed + posterior.rejected
        generator = torch.Generator().manual_seed(observation_seed(posterior.seed, index))
        cells = observation_evidence(model, obs, posterior, generator, bandwidth)
        if cells is None:
            log.warning("observation %d of model %s is explained by no kernel (farther than %.2f m or %.0f° from "
                        "every kernel its contacts reach: a thrown or misplaced object?): left out", index,
                        model.name, OUTLIER_DISTANCE, OUTLIER_ANGLE * 57.29577951308232)
        posterior = posterior.with_evidence(cells)
    return conditioned_model(model, posterior)
