"""Collision-free starts: a push condition's robot start checked against the observed cloud and backed off
until the bumper and chassis clear it (no paper section: the query density knows nothing of the robot's
volume).

Collision-free starts: the robot's query density knows nothing of the robot's volume, so an
annealed start can put the bumper or the chassis inside the object, and the physics engine then throws the
object. Every push condition's start is therefore checked against the observed cloud before it is used
(:func:`clear_robot_start`): it is backed off straight along the approach (the robot's −x) until the
bumper and chassis boxes clear the observed surface by :data:`START_CLEARANCE`, by the exact distance
:func:`pushtorch.robot.backoff_distance` gives, and recorded in ``PushCondition.backoff``; no prediction
is made from an overlapping start. A start that needed more than :data:`MAX_BACKOFF` is no longer the
model's choice: its condition is marked invalid (``PushCondition.valid`` False, a warning is logged, and
:meth:`PushCondition.check_start` raises :class:`~pushtorch.errors.ModelError` for callers that refuse
it), while the start it carries is still the collision-free one. The check covers the observed surface only (the
single shot sees the side facing the camera): besides the observed points it takes the space just behind
them, :data:`OCCLUDED_DEPTH` along each point's inward normal, as occupied (:func:`clearance_points`),
which catches a bumper buried wholly behind the visible face; deeper hidden parts of the object are not
checked.
"""

from __future__ import annotations

import logging
import math

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.features import SurfaceFeatures
from pushtorch.robot import backed_off, backoff_distance

__all__ = [
    "GIVEN_START_OVERLAP",
    "MAX_BACKOFF",
    "OCCLUDED_DEPTH",
    "OCCLUDED_STEP",
    "START_CLEARANCE",
    "check_start",
    "clear_robot_start",
    "clearance_points",
    "overlap_message",
]

log = logging.getLogger(__name__)


#: Clearance (m) the robot's bumper and chassis keep from the observed cloud at a push's start: the 2 mm gap
#: of the training placement (:func:`pushtorch.sim.push.place_robot_against`).
START_CLEARANCE = 0.002


#: Largest back-off (m) along the approach that still counts as the start the model chose: 0.10 m is 1 s of
#: the paper's 0.1 m/s push, a quarter of its 0.4 m travel. A start that needs more sat deep in (or on) the
#: object: its condition is marked invalid (``PushCondition.valid``), though still backed off to a clear start.
MAX_BACKOFF = 0.10


#: Depth (m) behind each observed point, along its inward normal, taken as occupied by the object: deeper
#: than the 1.25 cm slot between the chassis and the bumper, so a bumper buried wholly behind the visible
#: face is caught, and shallower than half the thinnest catalogue object (0.1 m), so a robot flush against a
#: hidden face is not pushed away by it.
OCCLUDED_DEPTH = 0.02


#: Spacing (m) of the occluded samples: below the bumper's 0.02 m thickness, so it cannot slip between them.
OCCLUDED_STEP = 0.01


#: How far (m) a start the caller gives may sit inside the observed object (the cloud and its occluded layer):
#: a sensor's noise of a few mm on a bumper placed flush. Spread test starts placed 2 mm short on the catalogue
#: and 9 random shapes measured 0 m; a start more than this deep would push from inside the object.
GIVEN_START_OVERLAP = 0.005


def clearance_points(features: SurfaceFeatures, depth: float = OCCLUDED_DEPTH,
                     step: float = OCCLUDED_STEP) -> torch.Tensor:
    """The points a robot start must clear: the observed surface and the occluded space just behind it.

    Each feature's point ``p`` gives ``p − t·n`` for ``t = 0, step, …, depth`` (``n`` its outward normal),
    ``(K·N, 3)`` with ``K = ⌊depth/step⌋ + 1`` layers, surface first. The single-shot cloud shows only the
    side facing the camera; the layers stand for the object right behind that surface (for a convex object
    at least as thick as ``depth`` they lie inside it), so a bumper wholly behind the visible face still
    overlaps them. The object's hidden side further back is not represented.

    Raises:
        InvalidParameterError: a negative depth or a step that is not positive.
    """
    if not (math.isfinite(depth) and depth >= 0 and math.isfinite(step) and step > 0):
        raise InvalidParameterError(f"need depth >= 0 and step > 0 (m), got depth={depth!r}, step={step!r}")
    layers = torch.arange(int(round(depth / step, 9)) + 1, dtype=features.p.dtype, device=features.p.device)
    offsets = layers * step
    return (features.p.unsqueeze(0) - offsets[:, None, None] * features.normal.unsqueeze(0)).reshape(-1, 3)


def overlap_message(backoff: float, model_name: str | None) -> str:
    """Why a start backed off ``backoff`` m is no longer the model's choice (beyond :data:`MAX_BACKOFF`)."""
    who = f" of model {model_name!r}" if model_name else ""
    return (
        f"the predicted robot start{who} overlaps the observed object: its bumper or chassis stays within "
        f"{START_CLEARANCE * 1000:g} mm of the cloud (or of the {OCCLUDED_DEPTH * 100:g} cm behind its visible "
        f"surface) until backed off {backoff:.3f} m along the approach, beyond the {MAX_BACKOFF:.2f} m allowed"
    )


def clear_robot_start(robot_start: se3.Pose, features: SurfaceFeatures,
                      clearance: float = START_CLEARANCE) -> tuple[se3.Pose, float]:
    """A robot start pose ``()`` that clears the observed cloud, and how far it was backed off (m).

    The start is moved straight back along its own −x (the approach reversed) by
    :func:`pushtorch.robot.backoff_distance` against :func:`clearance_points`: the smallest distance after
    which the bumper and chassis boxes are at least ``clearance`` from every observed point and from the
    occluded layer behind it. A start that already clears is returned unchanged with back-off 0. The
    back-off is not bounded here; :class:`PushCondition` judges it against :data:`MAX_BACKOFF`.
    """
    distance = backoff_distance(robot_start, clearance_points(features), clearance)
    value = float(distance)
    if value <= 0.0:
        return robot_start, 0.0
    return backed_off(robot_start, distance), value


def check_start(robot_start: se3.Pose) -> se3.Pose:
    """``robot_start`` if it is one finite pose with a unit quaternion, else InvalidPoseError."""
    robot_start = se3.check_pose(robot_start, "robot_start")
    if robot_start.batch_shape != torch.Size([]):
        raise InvalidPoseError(f"robot_start must be one pose, got batch shape {tuple(robot_start.batch_shape)}")
    return robot_start
