"""Evaluation: how good a prediction is (paper, Prediction Accuracy Measure, Eq. pam; Pose Estimation).

:mod:`~pushtorch.evaluation.metrics` (H_acc, linear and angular errors, over an object's symmetries),
:mod:`~pushtorch.evaluation.likelihood` (the negative log-likelihood of the true outcome under a predicted
density, in the displacement sense) and :mod:`~pushtorch.evaluation.baselines` (the peers a prediction is
compared with: no motion, the mean motion, the nearest push, physics from the cloud).
"""
