"""The training app: a push model from simulated pushes (paper, Fig. pipeline, training; §TPMM).

Stage one (full cloud → manipulator contact model and position model) and stage two (push records →
environment contact and motion models) of :func:`pushtorch.models.library.train_push_model`, as a
Hydra app. Usage::

    pushtorch-simulate object=cube friction=general hydra.run.dir=runs/sim_cube
    pushtorch-train object=cube data=runs/sim_cube
    pushtorch-train object=cylinder 'data=[runs/a,runs/b]' model=quick

Output in the run directory: ``model.npz`` (load with :func:`pushtorch.models.library.load_model`),
``summary.json``, ``resolved_config.yaml`` and ``recording.rrd`` (the contact and position frames, see
:func:`pushtorch.viz.contacts.log_contact_model`). Configuration reaches the library as plain arguments
through :func:`train_from_config`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, run_stage
from pushtorch.apps.config_check import check_config
from pushtorch.errors import InvalidParameterError

__all__ = ["main", "train_from_config"]

log = logging.getLogger("pushtorch.apps.train")


def train_from_config(cfg: Mapping[str, Any] | DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train and save the model a ``conf/train.yaml``-shaped config describes.

    Args:
        cfg: keys ``object`` (name, path, scale), ``model.settings`` (ModelSettings), ``data`` (one folder
            or a list), optional ``name``, ``seed``, ``recording`` and ``allow_partial`` (train on the
            finished part of an unfinished simulation run; the model file then records what was missing
            in its ``partial_data`` header field).
        out_dir: the run directory (``model.npz``, ``summary.json``, ``recording.rrd``).

    Returns:
        A summary dict (also written to ``out_dir/summary.json``).

    Raises:
        InvalidParameterError: no data, data of another object, or a bad setting.
        IncompleteRunError: a data folder is an unfinished run (unless ``allow_partial``).
        RecordFormatError: unreadable, duplicated or inconsistent push records.
        ModelError: no push record touches the object.
    """
    import torch

    from pushtorch.experiments.common import as_names, plain
    from pushtorch.models.settings import ModelSettings
    from pushtorch.models.training import train_push_model
    from pushtorch.objects import load_object
    from pushtorch.sim.records import PushRecords, load_records
    from pushtorch.sim.run_manifest import run_status

    check_config(cfg, "train")  # types and bounds first, as the command line does
    c = plain(cfg)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        obj_cfg = c["object"]
        obj = load_object(obj_cfg["name"], obj_cfg.get("path"), float(obj_cfg.get("scale", 1.0)),
                          up=obj_cfg.get("up", "z"))
        settings = ModelSettings.from_mapping((c.get("model") or {}).get("settings") or {})
        folders = [Path(p) for p in as_names(c.get("data"))]
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"train config is missing or mistypes a key: {exc}") from exc
    if not folders:
        raise InvalidParameterError("no training data: set data=<a pushtorch-simulate run directory>")
    allow_partial = c.get("allow_partial", False)
    if not isinstance(allow_partial, bool):
        raise InvalidParameterError(f"allow_partial must be true or false, got {allow_partial!r}")
    start = time.perf_counter()
    statuses = [run_status(folder) for folder in folders]
    records = PushRecords.cat([load_records(folder, allow_partial=allow_partial, trajectories=False)
                               for folder in folders])  # training uses the final poses only
    unfinished = [st for st in statuses if st is not None and not st.complete]
    partial_data = None
    if unfinished:  # only reachable with allow_partial
        partial_data = {
            "pushes": len(records),
            "missing_pushes": sum(st.missing_pushes for st in unfinished),
            "unfinished_runs": [str(st.folder) for st in unfinished],
            "missing_by_action": {str(a): sum(st.missing_by_action.get(a, 0) for st in unfinished)
                                  for a in sorted({a for st in unfinished for a in st.missing_by_action})},
        }
        for st in unfinished:
            log.warning("training on part of a run (allow_partial): %s", st.describe())
    others = sorted(set(records.object_name) - {obj.name})
    if others:
        raise InvalidParameterError(
            f"the data hold pushes of {', '.join(others)}, not only of object {obj.name!r}: "
            "train one object at a time (object=<the simulated object>)"
        )
    name = c.get("name") or f"{obj.name}_{folders[-1].resolve().name}"
    log.info("training %s on %d pushes (%d valid) of %s", name, len(records), int(records.valid.sum()),
             obj.name)
    model = train_push_model(
        obj, records, settings, name=name, generator=torch.Generator().manual_seed(int(c.get("seed", 0))),
        meta={"data": [str(f) for f in folders], "pushes": len(records)}, partial_data=partial_data,
    )
    path = model.save(out_dir / "model.npz")
    seconds = time.perf_counter() - start
    summary: dict[str, Any] = {
        "model": str(path),
        "name": model.name,
        "object": obj.name,
        "pushes": len(records),
        "valid_pushes": int(records.valid.sum()),
        "partial_data": partial_data,
        "actions": model.actions.tolist(),
        "contact_frames": len(model.contact.frames),
        "position_frames": len(model.position.frames),
        "motion_kernels": [{"manipulator": len(m.manipulator), "environment": len(m.environment)}
                           for m in model.motions],
        "seconds": round(seconds, 2),
    }
    if c.get("recording", True):
        from pushtorch.viz.contacts import log_contact_model
        from pushtorch.viz.core import open_recording

        rec = open_recording(out_dir / "recording.rrd", "pushtorch_train")
        log_contact_model(rec, model, obj)
        rec.disconnect()  # completes the file
        summary["recording"] = str(out_dir / "recording.rrd")
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")
def _app(cfg: DictConfig) -> dict[str, Any]:
    return run_stage("pushtorch-train", cfg, train_from_config)


def main() -> None:
    """Entry point of ``pushtorch-train`` (a user error exits with status 2 and one line)."""
    compose_or_exit("pushtorch-train", "train")
    _app()


if __name__ == "__main__":
    main()
