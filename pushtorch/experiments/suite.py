"""Run experiment parts into one run directory: shared context, one recording, one results.json and report.

Each paper experiment (``model_selection``, ``pose_estimation``, ``friction_biasing``, ``mass_biasing``) is
one *part*; ``quickstart`` runs all four at small sizes. A part is ``(kind, its experiment config, its
model config)``: ``kind`` picks the module (``model_selection``, ``pose_estimation`` or ``biasing``).
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pushtorch.cli import current_overrides
from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.common import context_from_config, plain

__all__ = ["KINDS", "run_suite"]

log = logging.getLogger("pushtorch.experiments")

#: Part kind → module with ``run_part(cfg, part, ctx, model_cfg) -> (records, extras)``.
KINDS = {
    "model_selection": "pushtorch.experiments.model_selection",
    "pose_estimation": "pushtorch.experiments.pose_estimation",
    "biasing": "pushtorch.experiments.biasing",
}


def _merge_extras(into: dict[str, Any], extras: Mapping[str, Any]) -> None:
    """Parts' extras into one: mappings update, lists extend."""
    for key, value in extras.items():
        if isinstance(value, Mapping):
            into.setdefault(key, {}).update(value)
        elif isinstance(value, list):
            into.setdefault(key, []).extend(value)
        else:
            into[key] = value


def run_suite(cfg, out_dir: str | Path, parts: Sequence[tuple[str, Any, Any]]) -> dict[str, Any]:
    """Run ``parts`` in order and write the run's outputs.

    Args:
        cfg: the composed config (``seed``, ``model``, ``priors``, ``sim``, ``experiment``, ``object``).
        out_dir: the run directory (outputs and caches).
        parts: ``(kind, part config, model config)`` per part.

    Returns:
        The summary the CLI prints: where results.json, report.md and recording.rrd are, the wall time,
        the number of records and the acceptance checks passed.

    Raises:
        InvalidParameterError: an unknown part kind; PushtorchError from any step.
    """
    from pushtorch.experiments.report import write_outputs
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
    try:
        for kind, part, model_cfg in parts:
            if kind not in KINDS:
                raise InvalidParameterError(f"unknown experiment part {kind!r}; use {', '.join(KINDS)}")
            module = importlib.import_module(KINDS[kind])
            part_start = time.perf_counter()
            model_cfg = plain(model_cfg)
            part_records, part_extras = module.run_part(cfg, part, ctx.with_model(model_cfg), model_cfg)
            log.info("%s: %d records in %.0f s", plain(part).get("name", kind), len(part_records),
                     time.perf_counter() - part_start)
            records.extend(part_records)
            _merge_extras(extras, part_extras)
    finally:
        ctx.recording.disconnect()  # completes the file (flush alone leaves it without its footer)
    wall = time.perf_counter() - start
    outputs = write_outputs(out_dir, name, plain(cfg), wall, records, extras, overrides=current_overrides())
    passed = sum(c["passed"] for c in outputs["checks"])
    return {
        "report": str(outputs["report"]),
        "recording": str(recording_path),
        "results": str(outputs["results"]),
        "figures": len(outputs["figures"]),
        "records": len(records),
        "wall_s": round(wall, 1),
        "checks": f"{passed}/{len(outputs['checks'])} passed",
    }
