"""The training app: a push model from simulated pushes or a lab's push table (paper, Fig. pipeline, training;
§TPMM).

Stage one (full cloud → manipulator contact model and position model) and stage two (push records →
environment contact and motion models) of :func:`pushtorch.models.library.train_push_model`, as a
Hydra app. Usage::

    pushtorch-simulate object=cube friction=general hydra.run.dir=runs/sim_cube
    pushtorch-train object=cube data=runs/sim_cube
    pushtorch-train object=cylinder 'data=[runs/a,runs/b]' model=quick
    pushtorch-train data=lab/pushes.parquet          # a push table: its objects and meshes (docs/usage.md)

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

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, exit_without_collecting, run_stage
from pushtorch.apps.config_check import check_config
from pushtorch.errors import InvalidParameterError

__all__ = ["main", "train_from_config"]

log = logging.getLogger("pushtorch.apps.train")


def train_from_config(cfg: Mapping[str, Any] | DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train and save the model a ``conf/train.yaml``-shaped config describes.

    Args:
        cfg: keys ``object`` (name, path, scale), ``model.settings`` (ModelSettings), ``data`` (one folder
            or a list, or push tables: ``.parquet`` files, :mod:`pushtorch.sim.tables`), optional ``name``,
            ``seed``, ``recording`` and ``allow_partial`` (train on the finished part of an unfinished simulation
            run; the model file then records what was missing in its ``partial_data`` header field). With
            tables, the objects and their meshes are the tables' (``object`` is not used), the rows must hold
            the configured ``actions``, and one model is trained per object (``model<_object>.npz``), or one
            pooled model of the objects ``model.training_objects`` names.
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
        settings = ModelSettings.from_mapping((c.get("model") or {}).get("settings") or {})
        folders = [Path(p) for p in as_names(c.get("data"))]
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"train config is missing or mistypes a key: {exc}") from exc
    if not folders:
        raise InvalidParameterError("no training data: set data=<a pushtorch-simulate run directory or a push table>")
    tables = [f for f in folders if f.suffix.lower() == ".parquet"]
    if tables:
        if len(tables) != len(folders):
            raise InvalidParameterError("data mixes push tables (.parquet) with simulation runs: train on one kind "
                                        "(a run's pushes/pushes.parquet is a table of its pushes)")
        summary = _tables(c, tables, settings, out_dir)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        return summary
    try:
        obj_cfg = c["object"]
        obj = load_object(obj_cfg["name"], obj_cfg.get("path"), float(obj_cfg.get("scale", 1.0)),
                          up=obj_cfg.get("up", "z"))
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"train config is missing or mistypes a key: {exc}") from exc
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
    summary = _saved(model, obj, records, out_dir, "", c.get("recording", True))
    summary["partial_data"] = partial_data
    summary["seconds"] = round(time.perf_counter() - start, 2)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def _saved(model, obj, records, out_dir: Path, suffix: str, recording: bool) -> dict[str, Any]:
    """Save ``model`` as ``model<suffix>.npz`` (and its contact model to ``recording<suffix>.rrd``); its summary."""
    path = model.save(out_dir / f"model{suffix}.npz")
    summary: dict[str, Any] = {
        "model": str(path),
        "name": model.name,
        "object": obj.name,
        "pushes": len(records),
        "valid_pushes": int(records.valid.sum()),
        "actions": model.actions.tolist(),
        "contact_frames": len(model.contact.frames),
        "position_frames": len(model.position.frames),
        "motion_kernels": [{"manipulator": len(m.manipulator), "environment": len(m.environment)}
                           for m in model.motions],
    }
    if recording:
        from pushtorch.viz.contacts import log_contact_model
        from pushtorch.viz.core import open_recording

        rec = open_recording(out_dir / f"recording{suffix}.rrd", "pushtorch_train")
        log_contact_model(rec, model, obj)
        rec.disconnect()  # completes the file
        summary["recording"] = str(out_dir / f"recording{suffix}.rrd")
    return summary


def _tables(c: Mapping[str, Any], tables: list[Path], settings, out_dir: Path) -> dict[str, Any]:
    """Train from push tables (:mod:`pushtorch.sim.tables`): one model per object of the tables, or one pooled
    model of the objects ``model.training_objects`` names. Every table is read and checked before anything is
    trained or written."""
    import torch

    from pushtorch.experiments.common import as_names
    from pushtorch.models.pooled import train_pooled_model
    from pushtorch.models.training import train_push_model
    from pushtorch.sim.push import ACTION_DURATION, ACTION_SPEED, make_actions
    from pushtorch.sim.records import PushRecords
    from pushtorch.sim.tables import read_push_table

    start = time.perf_counter()
    # the paper's actions unless configured (conf/train.yaml states them)
    a = c.get("actions") or {"count": 3, "angle_range_deg": [-10.0, 10.0], "speed": ACTION_SPEED,
                             "duration": ACTION_DURATION}
    try:
        actions = make_actions(int(a["count"]), tuple(a["angle_range_deg"]), float(a["speed"]))
        duration = float(a["duration"])
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"train config: the actions (count, angle_range_deg, speed, duration) the "
                                    f"tables must hold: {exc}") from exc
    read = [read_push_table(t, actions, duration) for t in tables]
    objects = {}
    for table in read:
        for name in table.object_names:
            objects.setdefault(name, table.object(name))
    records = {name: PushRecords.cat([t.records.take([i for i, n in enumerate(t.records.object_name) if n == name])
                                      for t in read if name in t.object_names]) for name in objects}
    for table in read:
        if table.inferred:
            log.info("%s has no %s column: inferred from the object's motion (pushtorch.sim.tables.infer_flags)",
                     table.path, ", ".join(table.inferred))
        if not table.has_physics:
            log.warning("%s has no mass and ground_friction columns: its models predict, but cannot be conditioned "
                        "on observed pushes (condition_on)", table.path)
    generator = torch.Generator().manual_seed(int(c.get("seed", 0)))
    meta = {"data": [str(t) for t in tables]}
    pooled = as_names((c.get("model") or {}).get("training_objects"))
    if pooled:
        unknown = [n for n in pooled if n not in objects]
        if unknown:
            raise InvalidParameterError(f"model.training_objects names {', '.join(unknown)}, which the tables do not "
                                        f"hold (they hold {', '.join(objects)})")
        name = c.get("name") or "pooled"
        model = train_pooled_model([objects[n] for n in pooled], [records[n] for n in pooled], settings, name=name,
                                   generator=generator, meta=meta)
        summaries = [_saved(model, objects[pooled[0]], PushRecords.cat([records[n] for n in pooled]), out_dir, "",
                            c.get("recording", True))]
        summaries[0]["object"] = list(pooled)
    else:
        summaries = []
        for n, obj in objects.items():
            log.info("training %s on %d pushes (%d valid) of the tables", n, len(records[n]),
                     int(records[n].valid.sum()))
            model = train_push_model(obj, records[n], settings, name=c.get("name") or n, generator=generator,
                                     meta={**meta, "pushes": len(records[n])})
            summaries.append(_saved(model, obj, records[n], out_dir, "" if len(objects) == 1 else f"_{n}",
                                    c.get("recording", True)))
    summary = dict(summaries[0]) if len(summaries) == 1 else {"models": summaries}
    summary["seconds"] = round(time.perf_counter() - start, 2)
    return summary


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")
def _app(cfg: DictConfig) -> dict[str, Any]:
    return run_stage("pushtorch-train", cfg, train_from_config)


def main() -> None:
    """Entry point of ``pushtorch-train`` (a user error exits with status 2 and one line)."""
    compose_or_exit("pushtorch-train", "train")
    _app()
    exit_without_collecting()


if __name__ == "__main__":
    main()
