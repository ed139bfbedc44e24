"""Shared steps of the paper's experiments: training, test conditions, predictions, ground truth, records.

The steps live in one module per concern: :mod:`~pushtorch.experiments.context` (configuration, seeds,
caches), :mod:`~pushtorch.experiments.training` (pushes and models), :mod:`~pushtorch.experiments.prediction_sets`
(test poses, clouds, every predictor's predictions), :mod:`~pushtorch.experiments.scoring` (ground truth,
likelihood scores, records) and :mod:`~pushtorch.experiments.recording` (Rerun). This module gathers their names
for the experiment modules.

Paper, Experimental Setup (Fig. prediction_accuracy_methodology): *training* — full cloud, contact models,
simulated pushes (PDRs) under a training prior; *prediction* — a single-shot cloud of the test object,
a push condition chosen by the model (robot start pose, contact frames, initial-pose estimate), a
predicted final pose; *ground truth* — the same push simulated from the chosen robot start pose with
mass and friction drawn from the test condition's prior, ``truth_samples`` times per condition and
action. Everything here composes library calls; an experiment module only decides *what* to compare.

Caching (a re-run with the same run directory resumes): training pushes are resumable shards under
``<run_dir>/data/<object>_<friction>_<mass>/``, trained models ``<run_dir>/models/<same>.npz``, each
group's predictions ``<run_dir>/predictions/<key>.npz`` and its ground-truth pushes
``<run_dir>/truth/<key>/``. A cached file is reused only if it was made with the same settings.
"""

from pushtorch.experiments.context import (  # noqa: F401
    LOG_RULES,
    MAX_LOGGED_CONDITIONS,
    ExperimentContext,
    LogConditions,
    as_names,
    context_from_config,
    fingerprint,
    load_arrays,
    load_test_objects,
    merged_model_config,
    plain,
    prior_pairs,
    progress_bar,
    save_arrays,
    stable_seed,
)
from pushtorch.experiments.prediction_sets import (  # noqa: F401
    PREDICTION_VERSION,
    Example,
    Examples,
    PredictionSet,
    observe,
    predict_set,
    sample_test_poses,
    spread_test_start,
)
from pushtorch.experiments.recording import (  # noqa: F401
    entity_label,
    log_examples,
)
from pushtorch.experiments.scoring import (  # noqa: F401
    METRICS,
    compare,
    compare_displacement,
    likelihood_scores,
    simulate_truth,
    summarise,
    truth_fingerprint,
)
from pushtorch.experiments.training import (  # noqa: F401
    train_model,
    train_pooled,
    train_pooled_residual,
    training_records,
)

__all__ = [
    "Example",
    "Examples",
    "ExperimentContext",
    "LOG_RULES",
    "LogConditions",
    "MAX_LOGGED_CONDITIONS",
    "METRICS",
    "PREDICTION_VERSION",
    "PredictionSet",
    "as_names",
    "compare",
    "compare_displacement",
    "context_from_config",
    "entity_label",
    "fingerprint",
    "likelihood_scores",
    "load_arrays",
    "load_test_objects",
    "log_examples",
    "merged_model_config",
    "observe",
    "plain",
    "prior_pairs",
    "predict_set",
    "progress_bar",
    "sample_test_poses",
    "save_arrays",
    "simulate_truth",
    "spread_test_start",
    "stable_seed",
    "summarise",
    "train_model",
    "train_pooled",
    "train_pooled_residual",
    "training_records",
    "truth_fingerprint",
]
