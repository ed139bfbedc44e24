"""Run experiment parts into one run directory: shared context, one recording, one results.json and report
(paper, Experimental Results: every experiment of it runs through here, alone or as a quickstart part).

Each paper experiment (``model_selection``, ``pose_estimation``, ``friction_biasing``, ``mass_biasing``, and
``online_adaptation``, ``shape_transfer``) is one *part*; ``quickstart`` runs them all at small sizes. A part is
``(kind, its experiment config, its model config)``: ``kind`` picks its ``run_part`` in
:data:`pushtorch.experiments.registry.PARTS` (``model_selection``, ``pose_estimation``, ``biasing``,
``online_adaptation``, ``shape_transfer``).

The recording (``recording.rrd``) gets, per part, each group's H_acc as a series and a markdown summary
(:mod:`pushtorch.viz.scores`), and at the end the blueprint that lays it out for review
(:func:`pushtorch.viz.blueprint.experiment_blueprint`): a tab per part.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pushtorch.experiments.common import ExperimentContext, context_from_config, entity_label, plain
from pushtorch.experiments.registry import part_runner
from pushtorch.experiments.summary import summary_table

__all__ = ["EXPECTED_WARNINGS", "expected_warnings_quiet", "run_suite"]

log = logging.getLogger("pushtorch.experiments")

#: Library loggers whose warnings an experiment expects and counts itself: a predicted start backed off too far
#: (an invalid condition, counted in the summary and report.md) and an observation no kernel explains
#: (counted in the posterior's ``rejected``). During a run they are logged at DEBUG, so the progress bars
#: read clean; a library user who calls ``predict`` or ``condition_on`` still gets the warning.
EXPECTED_WARNINGS = ("pushtorch.models.push_condition", "pushtorch.models.evidence")


class _Expected(logging.Filter):
    """Logs an expected warning at DEBUG: the record is demoted, and passed on only where its logger has DEBUG
    enabled (a handler without a level of its own, as Hydra's console, would print it otherwise)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


@contextlib.contextmanager
def expected_warnings_quiet():
    """Within the block, the warnings of :data:`EXPECTED_WARNINGS`' loggers are logged at DEBUG."""
    expected = _Expected()
    for logger in EXPECTED_WARNINGS:
        logging.getLogger(logger).addFilter(expected)
    try:
        yield
    finally:
        for logger in EXPECTED_WARNINGS:
            logging.getLogger(logger).removeFilter(expected)


def _merge_extras(into: dict[str, Any], extras: Mapping[str, Any]) -> None:
    """Parts' extras into one: mappings update, lists extend."""
    for key, value in extras.items():
        if isinstance(value, Mapping):
            into.setdefault(key, {}).update(value)
        elif isinstance(value, list):
            into.setdefault(key, []).extend(value)
        else:
            into[key] = value


def _part_origin(kind: str, name: str) -> str:
    """Root entity of what a part logs: its predictions, or pose estimation's own subtree."""
    from pushtorch.viz.core import WORLD
    from pushtorch.viz.predictions import PREDICTION

    if kind == "pose_estimation":
        return f"{WORLD}/experiments/pose_estimation"  # where pose_estimation._log_pose_example logs
    return f"{PREDICTION}/{entity_label(name)}"


def _log_part(ctx: ExperimentContext, kind: str, name: str, records: list[dict], first_group: int):
    """A finished part's H_acc series and summary in the recording; returns the part's blueprint tab."""
    from pushtorch.viz.blueprint import ReviewTab
    from pushtorch.viz.scores import hacc_root, log_group_hacc, log_markdown, part_summary, part_summary_path

    origin = _part_origin(kind, name)
    logged = [(root, text) for root, text in ctx.logged_predictions if root.startswith(f"{origin}/")]
    log_group_hacc(ctx.recording, name, records, first_group)
    log_markdown(ctx.recording, part_summary_path(name),
                 part_summary(name, records, first_group, [text for _, text in logged]))
    return ReviewTab(name=name, origin=origin, prediction_roots=[root for root, _ in logged],
                     summary=part_summary_path(name), hacc=hacc_root(name))


def run_suite(cfg, out_dir: str | Path, parts: Sequence[tuple[str, Any, Any]],
              overrides: Sequence[str] = ()) -> dict[str, Any]:
    """Run ``parts`` in order and write the run's outputs.

    Args:
        cfg: the composed config (``seed``, ``model``, ``priors``, ``sim``, ``experiment``, ``object``), as
            the app checked it (:func:`pushtorch.apps.config_check.check_config`).
        out_dir: the run directory (outputs and caches).
        parts: ``(kind, part config, model config)`` per part.
        overrides: the command line's overrides, recorded in results.json (the app passes them).

    Returns:
        The summary the CLI prints: a table per object (:func:`~pushtorch.experiments.summary.summary_table`),
        where results.json, report.md and recording.rrd are, the wall time, the number of records, the
        acceptance checks passed and the command that opens the recording.

    Raises:
        InvalidParameterError: an unknown part kind (:func:`pushtorch.experiments.registry.part_runner`);
            PushtorchError from any step.
    """
    from pushtorch.experiments.report import write_outputs
    from pushtorch.experiments.tasks import spread_calls
    from pushtorch.viz.blueprint import experiment_blueprint
    from pushtorch.viz.core import open_recording

    start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = str(plain(cfg)["experiment"].get("name", "experiment"))
    ctx = context_from_config(cfg, out_dir)
    recording_path = out_dir / "recording.rrd"
    ctx.recording = open_recording(recording_path, f"pushtorch_{name}")
    records: list[dict] = []
    extras: dict[str, Any] = {}
    tabs = []
    try:
        for kind, part, model_cfg in parts:
            run_part = part_runner(kind)
            part_start = time.perf_counter()
            model_cfg = plain(model_cfg)
            part_name = str(plain(part).get("name", kind))
            with expected_warnings_quiet():
                part_records, part_extras = run_part(cfg, part, ctx.with_model(model_cfg), model_cfg)
            log.info("%s: %d records in %.0f s", part_name, len(part_records), time.perf_counter() - part_start)
            tabs.append(_log_part(ctx, kind, part_name, part_records, first_group=len(records)))
            records.extend(part_records)
            _merge_extras(extras, part_extras)
    finally:
        # the layout of whatever was logged, even if a part failed: saved in the file with the data
        ctx.recording.send_blueprint(experiment_blueprint(tabs))
        ctx.recording.disconnect()  # completes the file (flush alone leaves it without its footer)
    extras["model_bandwidths"] = {m.name: m.meta["bandwidths"] for m in ctx._models.values()
                                  if "bandwidths" in m.meta}
    extras["tasks"] = dict(sorted(ctx.task_counts.items()))
    wall = time.perf_counter() - start
    outputs = write_outputs(out_dir, name, plain(cfg), wall, records, extras, overrides=list(overrides),
                            draw_all=lambda draw, calls: spread_calls(ctx, draw, calls, "figures"))
    passed = sum(c["passed"] for c in outputs["checks"])
    return {
        "summary": summary_table(records, outputs["checks"], extras.get("thrown") or ()),
        "report": str(outputs["report"]),
        "recording": str(recording_path),
        "results": str(outputs["results"]),
        "figures": len(outputs["figures"]),
        "records": len(records),
        "wall_s": round(wall, 1),
        "checks": f"{passed}/{len(outputs['checks'])} passed",
        "view": f"rerun {recording_path}",
    }
