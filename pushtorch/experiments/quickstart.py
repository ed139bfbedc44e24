"""Quickstart: all four paper experiments at small sizes in one run (``make demo``).

Model selection, pose estimation, friction biasing and mass biasing (paper, Experimental Results), with online
adaptation (and shape transfer, on request), each with fewer test conditions, training pushes and annealing steps
(``conf/experiment/quickstart.yaml``, ``conf/model/quick.yaml``), into one ``results.json``, ``report.md`` (with
the acceptance checks: our predictor beats no-motion and the position model beats the centroid on every object,
adaptive selection matches congruent within noise), ``figures/`` and ``recording.rrd``. Each part's ``kind``
names its ``run_part`` in :data:`pushtorch.experiments.registry.PARTS`.

``python -m pushtorch`` (quickstart is the default) or ``python -m pushtorch experiment=quickstart``;
parts can be dropped, e.g. ``~experiment.parts.mass_biasing`` or ``experiment.parts.mass_biasing.skip=true``.
The shape-transfer part is marked ``skip`` (left out for time): ``experiment=quickstart_transfer`` runs it alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.common import merged_model_config, plain
from pushtorch.experiments.registry import PARTS
from pushtorch.experiments.suite import run_suite

__all__ = ["run"]


def run(cfg, out_dir: Path, overrides: Sequence[str] = ()) -> dict:
    """Run every part in ``experiment.parts`` (in order) into ``out_dir``; see :func:`run_suite`."""
    parts = []
    for name, part in (plain(cfg.experiment).get("parts") or {}).items():
        if part is None or part.get("skip", False):
            continue
        kind = part.get("kind", name)
        if kind not in PARTS:
            raise InvalidParameterError(
                f"quickstart part {name!r} has unknown kind {kind!r}; use {', '.join(PARTS)}"
            )
        parts.append((kind, {"name": name, **part}, merged_model_config(cfg.model, part.get("model"))))
    if not parts:
        raise InvalidParameterError("quickstart has no parts to run (experiment.parts is empty)")
    summary = run_suite(cfg, out_dir, parts, overrides)
    more = plain(cfg.experiment).get("more")
    return {**summary, "more": more} if more else summary
