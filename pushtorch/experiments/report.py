"""Outputs of an experiment run: results.json, report.md with the paper's tables, PNG figures, checks.

One module per concern: :mod:`~pushtorch.experiments.results` (results.json, checks),
:mod:`~pushtorch.experiments.statistics` (pooled groups, intervals), :mod:`~pushtorch.experiments.tables` (which
records a table reads, in which order and under which labels), :mod:`~pushtorch.experiments.figures` (PNG figures
and the data behind them) and :mod:`~pushtorch.experiments.markdown` (report.md); :func:`write_outputs` writes
them all, and this module gathers their public names.

Paper, Experimental Results: the report lays our numbers out as the paper's figures do (selection:
Fig. adaptive_results; pose: Fig. position_accuracy_results; biasing: the friction and mass results
figures, per model and test condition; per object: Fig. object_results, matched model and condition;
training pushes: the training-distribution figures) and puts the paper's own numbers beside ours where
it gives them (its figures carry no values; its text gives the linear errors below).

``results.json`` is ``{"experiment", "world", "physics", "config", "overrides", "wall_s", "records",
"model_bandwidths"}`` (``world`` and ``physics``: ``{"engine": ...}``, where the truth and the physics peers ran;
the last: per trained model, the bandwidths it chose from its training pushes); one record per group with the keys
``task, object, method, model, condition, n, hacc_mean, hacc_std, linear_cm, angular_deg`` (and
``selection_rate`` for the selection task), so ``pandas.DataFrame(json.load(f)["records"])`` is a tidy
table. ``hacc_std`` is the population standard deviation over the group's ``n`` comparisons.

``figure_data.npz`` keeps what the figures draw beyond the records (per-sample H_acc, training pushes), so
``tools/redraw_figures.py <run dir>`` redraws a run's figures from its outputs alone. The figures' rules
(one colour per method and per prior, intervals that cannot go below zero, when the axis is logarithmic,
n on every figure) are in the figures section below.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pushtorch.experiments.figures import (  # noqa: F401  (re-exported: the outputs' one entry point)
    FIGURE_DATA,
    make_figures,
    read_figure_data,
    write_figure_data,
)
from pushtorch.experiments.markdown import (  # noqa: F401  (re-exported: the outputs' one entry point)
    write_report,
)
from pushtorch.experiments.results import (  # noqa: F401  (re-exported: the outputs' one entry point)
    PAPER_LINEAR_CM,
    PAPER_POSE_LINEAR_CM,
    acceptance_checks,
    engines,
    write_results,
)
from pushtorch.experiments.statistics import (  # noqa: F401  (re-exported: the outputs' one entry point)
    BOOTSTRAP_RESAMPLES,
    LOG_AXIS_RATIO,
    mean_interval,
    pool,
    sample_entry,
    summary_interval,
    wants_log_axis,
)
from pushtorch.experiments.tables import (  # noqa: F401  (re-exported: the outputs' one entry point)
    ORACLES,
    frame_scores,
    primary,
)
from pushtorch.viz.colours import METHOD_COLOURS, PRIOR_COLOURS, colour_of  # re-exported: the figures' colours

__all__ = [
    "BOOTSTRAP_RESAMPLES",
    "FIGURE_DATA",
    "LOG_AXIS_RATIO",
    "METHOD_COLOURS",
    "ORACLES",
    "PAPER_LINEAR_CM",
    "PAPER_POSE_LINEAR_CM",
    "PRIOR_COLOURS",
    "acceptance_checks",
    "colour_of",
    "frame_scores",
    "make_figures",
    "mean_interval",
    "pool",
    "primary",
    "read_figure_data",
    "sample_entry",
    "summary_interval",
    "wants_log_axis",
    "write_figure_data",
    "write_outputs",
    "write_report",
    "write_results",
]


def write_outputs(out_dir: Path, experiment: str, config: Mapping[str, Any], wall_s: float,
                  records: Sequence[Mapping[str, Any]], extras: Mapping[str, Any],
                  overrides: Sequence[str] = (), draw_all=None) -> dict[str, Any]:
    """results.json, figures, report.md; returns their paths and the acceptance checks. ``draw_all`` draws the
    figures in parallel (:func:`pushtorch.experiments.figures.make_figures`)."""
    results = write_results(out_dir, experiment, config, wall_s, records, overrides,
                            extras.get("model_bandwidths"), extras.get("online_separability") or (),
                            extras.get("tasks"))
    figures = make_figures(out_dir, primary(records), extras, draw_all)
    figure_data = write_figure_data(out_dir, extras)  # what tools/redraw_figures.py redraws them from
    checks = acceptance_checks(primary(records), extras.get("thrown") or ())
    report = write_report(out_dir, experiment, wall_s, records, extras, figures, checks,
                          config.get("test_placement"), engines(config))
    return {"results": results, "report": report, "figures": figures, "figure_data": figure_data,
            "checks": checks}
