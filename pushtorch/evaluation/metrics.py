"""Prediction accuracy: the paper's measure H_acc (Eq. pam) and raw linear/angular errors, batched.

Paper, Prediction Accuracy Measure and Interpreting the Prediction Accuracy Measure:

    H_acc = ||(p_e - p_gt)^T D_S|| + min_{q_gt ∈ Q_gt} (1 - <q_e, q_gt>^2)

D_S is the diagonal of reciprocal object dimensions and Q_gt the object's visually identical
orientations (:class:`pushtorch.objects.Symmetry`, which also handles a cylinder's continuous symmetry
exactly). Decision (the paper is silent on the frame of D_S): the displacement is expressed in the
ground-truth object frame before scaling, so a prism's long side scales the error along the long side
whatever the object's yaw. For equal dimensions (cube, cylinder) the frame makes no difference.

Predictions are scored on the displacement they predict (:func:`displaced`): the predicted motion
``D̂ = B̂1 ∘ B̂0⁻¹`` applied to the true start pose, ``D̂ ∘ B0``, against the true final pose. The estimated
frame ``B̂0`` of a transferred model follows the training object's frame convention (a prism's centre 5 cm
behind its visible face, a yaw 90° off); a score of ``B̂1`` against the test object's own frame mixes that
convention into the motion error, while ``D̂`` does not depend on it: if ``B̂0 = B0' ∘ S`` and
``B̂1 = B1' ∘ S`` for any body-fixed ``S``, then ``D̂ = B1' ∘ B0'⁻¹``. The frame score remains available
as the secondary metric (``metric: frame`` records in results.json).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.objects import ObjectModel, Symmetry

__all__ = ["Accuracy", "accuracy", "angular_error_deg", "displaced", "hacc", "linear_error_cm"]


def _scaled_displacement(estimate: se3.Pose, truth: se3.Pose, dimensions: torch.Tensor) -> torch.Tensor:
    dims = torch.as_tensor(dimensions, dtype=estimate.p.dtype, device=estimate.p.device)
    if dims.shape != (3,) or not torch.isfinite(dims).all() or (dims <= 0).any():
        raise InvalidParameterError(f"object dimensions must be 3 positive finite lengths, got {dims.tolist()}")
    local = pkt.quaternion_apply(pkt.quaternion_invert(truth.q), estimate.p - truth.p)
    return (local / dims).norm(dim=-1)


def hacc(
    estimate: se3.Pose,
    truth: se3.Pose,
    dimensions: torch.Tensor,
    symmetry: Symmetry,
) -> torch.Tensor:
    """H_acc of Eq. pam for poses ``(...)`` (broadcast); 0 means a perfect prediction.

    Args:
        estimate: predicted poses (p (..., 3), q (..., 4) wxyz).
        truth: ground-truth poses, same broadcastable batch.
        dimensions: object extents ``(3,)`` in metres (D_S is their reciprocal).
        symmetry: the object's Q_gt.
    Returns:
        ``(...)`` tensor: linear term (object sizes) + angular term in [0, 1].
    """
    se3.check_unit_quaternion(estimate.q, name="estimate.q")
    se3.check_unit_quaternion(truth.q, name="truth.q")
    return _scaled_displacement(estimate, truth, dimensions) + symmetry.canonical_distance(estimate.q, truth.q)


@dataclass(frozen=True)
class Accuracy:
    """Per-prediction accuracy terms, each ``(...)``."""

    hacc: torch.Tensor
    linear: torch.Tensor  # ||(p_e - p_gt) D_S||, object sizes
    angular: torch.Tensor  # min over Q_gt of 1 - <q_e, q_gt>^2
    linear_cm: torch.Tensor
    angular_deg: torch.Tensor


def accuracy(estimate: se3.Pose, truth: se3.Pose, obj: ObjectModel) -> Accuracy:
    """H_acc with its two terms, and the raw linear (cm) and angular (deg, modulo symmetry) errors."""
    se3.check_unit_quaternion(estimate.q, name="estimate.q")
    se3.check_unit_quaternion(truth.q, name="truth.q")
    linear = _scaled_displacement(estimate, truth, obj.dimensions)
    angular = obj.symmetry.canonical_distance(estimate.q, truth.q)
    return Accuracy(
        hacc=linear + angular,
        linear=linear,
        angular=angular,
        linear_cm=linear_error_cm(estimate, truth),
        angular_deg=angular_error_deg(estimate, truth, obj.symmetry),
    )


def displaced(initial_estimate: se3.Pose, final_estimate: se3.Pose, truth_initial: se3.Pose) -> se3.Pose:
    """The predicted displacement applied to the true start pose: ``(B̂1 ∘ B̂0⁻¹) ∘ B0``, batched.

    Args:
        initial_estimate: the estimated start poses ``B̂0`` the predictions were made from, ``(...)``.
        final_estimate: the predicted final poses ``B̂1`` in the same frame, ``(...)``.
        truth_initial: the true start poses ``B0``, broadcastable to ``(...)``.

    Returns:
        Where the true object ends if it moves as predicted, ``(...)``: compare it with the true final
        pose (:func:`accuracy`).
    """
    motion = se3.compose(final_estimate, se3.inverse(initial_estimate))
    shape = torch.broadcast_shapes(motion.batch_shape, truth_initial.batch_shape)
    truth = se3.Pose.unchecked(truth_initial.p.to(motion.p).expand(*shape, 3),
                               truth_initial.q.to(motion.q).expand(*shape, 4))
    motion = se3.Pose.unchecked(motion.p.expand(*shape, 3), motion.q.expand(*shape, 4))
    moved = se3.compose(motion, truth)
    return se3.Pose.unchecked(moved.p, moved.q / moved.q.norm(dim=-1, keepdim=True))  # float32 products drift off unit


def linear_error_cm(estimate: se3.Pose, truth: se3.Pose) -> torch.Tensor:
    """Euclidean distance between positions, in centimetres (the paper's "raw linear error")."""
    return (estimate.p - truth.p).norm(dim=-1) * 100.0


def angular_error_deg(estimate: se3.Pose, truth: se3.Pose, symmetry: Symmetry | None = None) -> torch.Tensor:
    """Smallest rotation angle in degrees between the estimate and (any symmetric copy of) the truth."""
    if symmetry is None:
        return torch.rad2deg(se3.angle_between(estimate.q, truth.q))
    return torch.rad2deg(symmetry.angle(estimate.q, truth.q))
