"""Prediction: partial cloud + action → robot start pose, contact frames, initial pose, final-pose density.

Paper, Fig. pipeline (prediction) and §Query Density / §Motion Model / §Model Selection:

:mod:`~pushtorch.prediction.conditions` builds push conditions, :mod:`~pushtorch.prediction.clearance`
keeps their robot starts clear of the observed cloud, :mod:`~pushtorch.prediction.predict` predicts. This
package is callable as :func:`predict` (``pushtorch.predict(model, cloud, action)`` works in any import
order, see :class:`~pushtorch.prediction.predict._CallableModule`).
"""

import sys

from pushtorch.prediction.clearance import (
    GIVEN_START_OVERLAP,
    MAX_BACKOFF,
    OCCLUDED_DEPTH,
    OCCLUDED_STEP,
    START_CLEARANCE,
    clear_robot_start,
    clearance_points,
)
from pushtorch.prediction.conditions import (
    PushCondition,
    contact_bandwidth,
    estimate_pose,
    generate_push_condition,
    manipulator_frame_at,
    motion_bandwidth,
    query_bandwidth,
)
from pushtorch.prediction.predict import (
    Prediction,
    _CallableModule,
    predict,
    predict_many,
)

__all__ = [
    "GIVEN_START_OVERLAP",
    "MAX_BACKOFF",
    "OCCLUDED_DEPTH",
    "OCCLUDED_STEP",
    "Prediction",
    "PushCondition",
    "START_CLEARANCE",
    "clear_robot_start",
    "clearance_points",
    "contact_bandwidth",
    "estimate_pose",
    "generate_push_condition",
    "manipulator_frame_at",
    "motion_bandwidth",
    "predict",
    "predict_many",
    "query_bandwidth",
]

sys.modules[__name__].__class__ = _CallableModule
