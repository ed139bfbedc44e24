"""Prediction: partial cloud + action → robot start pose, contact frames, initial pose, final-pose density.

Paper, Fig. pipeline (prediction) and §Motion Model / §Model Selection: :func:`predict` and
:func:`predict_many` (:mod:`pushtorch.prediction.forward`), and a planner's many candidate pushes of one cloud
(:func:`predict_candidates`), build each cloud's push condition
(:mod:`pushtorch.models.push_condition`, its start cleared of the cloud by :mod:`pushtorch.models.clearance`)
and anneal the action's product of experts over the object's final pose. The names a user needs around a
prediction are gathered here.
"""

from pushtorch.models.clearance import (
    GIVEN_START_OVERLAP,
    MAX_BACKOFF,
    OCCLUDED_DEPTH,
    OCCLUDED_STEP,
    START_CLEARANCE,
    clear_robot_start,
    clearance_points,
)
from pushtorch.models.push_condition import (
    PushCondition,
    contact_bandwidth,
    estimate_pose,
    generate_push_condition,
    manipulator_frame_at,
    manipulator_frames_at,
    motion_bandwidth,
    query_bandwidth,
)
from pushtorch.prediction.forward import (
    CandidatePredictions,
    Prediction,
    predict,
    predict_candidates,
    predict_many,
    transfer_bandwidth,
    transfer_distance,
)
from pushtorch.prediction.residual import ResidualCandidates, ResidualPrediction, predict_residual

__all__ = [
    "CandidatePredictions",
    "GIVEN_START_OVERLAP",
    "MAX_BACKOFF",
    "OCCLUDED_DEPTH",
    "OCCLUDED_STEP",
    "Prediction",
    "PushCondition",
    "ResidualCandidates",
    "ResidualPrediction",
    "START_CLEARANCE",
    "clear_robot_start",
    "clearance_points",
    "contact_bandwidth",
    "estimate_pose",
    "generate_push_condition",
    "manipulator_frame_at",
    "manipulator_frames_at",
    "motion_bandwidth",
    "predict",
    "predict_candidates",
    "predict_many",
    "predict_residual",
    "query_bandwidth",
    "transfer_bandwidth",
    "transfer_distance",
]
