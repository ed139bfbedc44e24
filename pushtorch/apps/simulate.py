"""The simulation app: training pushes of one object, sampled from the chosen priors, as resumable shards.

Paper, Experimental Setup and Biasing Transferable Push Manipulation Models: for each action, place the
robot against the object, draw the physical parameters from the prior, push, record. Usage::

    pushtorch-simulate object=cube friction=general mass=fixed samples_per_action=500
    pushtorch-simulate -m friction=general,low,medium,high hydra/launcher=joblib
    pushtorch-simulate -m hydra/launcher=slurm hydra.launcher.partition=<p> \
        mass=general,low,medium,high

Output in the run directory: ``pushes/`` (shards + ``manifest.json``, see :mod:`pushtorch.sim.shards`),
``summary.json``, ``resolved_config.yaml`` and ``pushes.rrd`` (a few pushes for Rerun, with a blueprint that
plays them on ``sim_time``); with ``export_table=true`` also ``pushes/meshes/`` and ``pushes/clouds/``, which make
``pushes/pushes.parquet`` a push table as a lab's own pushes are given (:mod:`pushtorch.sim.tables`). A killed
run resumes when the same command is repeated with ``hydra.run.dir=<its directory>``. Configuration reaches the library
as plain arguments through :func:`simulate_from_config`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, exit_without_collecting, run_stage
from pushtorch.apps.config_check import check_config
from pushtorch.errors import InvalidParameterError

__all__ = ["main", "simulate_from_config"]

log = logging.getLogger("pushtorch.apps.simulate")


def _plain(cfg: Any) -> Any:
    from pushtorch.experiments.common import plain

    return plain(cfg)  # names a mandatory key left unset (``???``)


def simulate_from_config(cfg: Mapping[str, Any] | DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Plan, simulate and record the pushes a ``conf/simulate.yaml``-shaped config describes.

    Args:
        cfg: the composed config (keys ``object``, ``friction``, ``mass``, ``sim``, ``actions``,
            ``placement``, ``seed``, ``samples_per_action``, ``workers``, ``shard_size``, ``progress``,
            ``start_method``, ``rerun_pushes``, ``export_table``: also write the mesh, clouds and metadata
            that make ``pushes/pushes.parquet`` a complete push table, :func:`pushtorch.sim.tables.export_run_table`).
        out_dir: the run directory; shards go to ``out_dir/pushes``.

    Returns:
        A summary dict (also written to ``out_dir/summary.json``).

    Raises:
        PushtorchError: any invalid setting (unknown object, bad prior, bad sizes, a foreign shard folder).
    """
    from pushtorch.objects import load_object
    from pushtorch.sim.executors import executor_from_config
    from pushtorch.sim.plan import Placement, plan_training_pushes
    from pushtorch.sim.priors import prior_from_config
    from pushtorch.sim.push import make_actions
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import object_spec, settings_from_config

    check_config(cfg, "simulate")  # types and bounds first, as the command line does
    c = _plain(cfg)
    out_dir = Path(out_dir)
    try:
        obj_cfg, actions_cfg = c["object"], c["actions"]
        model = load_object(obj_cfg["name"], obj_cfg.get("path"), float(obj_cfg.get("scale", 1.0)),
                            up=obj_cfg.get("up", "z"))
        actions = make_actions(
            int(actions_cfg["count"]), tuple(actions_cfg["angle_range_deg"]), float(actions_cfg["speed"])
        )
        settings = settings_from_config(c, "world")
        placement = Placement(**c.get("placement", {}))
        plan = plan_training_pushes(
            model,
            actions,
            int(c["samples_per_action"]),
            prior_from_config(c["mass"]),
            prior_from_config(c["friction"]),
            seed=int(c.get("seed", 0)),
            duration=float(actions_cfg["duration"]),
            placement=placement,
        )
    except (KeyError, TypeError) as exc:
        raise InvalidParameterError(f"simulate config is missing or mistypes a key: {exc}") from exc
    log.info("%d pushes of %s → %s", len(plan), model.name, out_dir / "pushes")
    summary = run_plan(
        object_spec(model),
        plan,
        out_dir / "pushes",
        settings,
        workers=int(c.get("workers", 0)),
        shard_size=int(c.get("shard_size", 100)),
        progress=bool(c.get("progress", True)),
        start_method=c.get("start_method"),
        executor=executor_from_config(c.get("executor")),
        resume=_resume_command(out_dir),
    )
    result: dict[str, Any] = {
        "object": model.name,
        "pushes": summary.pushes,
        "shards": summary.shards,
        "resumed_shards": summary.resumed_shards,
        "simulated_pushes": summary.simulated_pushes,
        "valid_pushes_simulated": summary.valid_pushes,
        "seconds": round(summary.seconds, 3),
        "pushes_per_second": round(summary.pushes_per_second, 2) if summary.simulated_pushes else None,
        "folder": str(summary.folder),
    }
    if c.get("export_table", False):
        from pushtorch.sim.tables import export_run_table

        result["table"] = str(export_run_table(out_dir / "pushes", model, settings.robot,
                                               float(actions_cfg["duration"]), seed=int(c.get("seed", 0))))
    n_rerun = int(c.get("rerun_pushes", 0))
    if n_rerun > 0:
        from pushtorch.viz.blueprint import pushes_blueprint
        from pushtorch.viz.core import open_recording
        from pushtorch.viz.sim import log_pushes

        records = load_records(out_dir / "pushes")
        per_action = int(c["samples_per_action"])
        count = actions.shape[0]
        # the first push of each action in turn, then the second of each, ...
        order = [a * per_action + k for k in range(per_action) for a in range(count)][:n_rerun]
        rec = open_recording(out_dir / "pushes.rrd", "pushtorch_simulate")
        log_pushes(rec, records, order, model.mesh)
        rec.send_blueprint(pushes_blueprint())  # opens on one 3D view, playing on sim_time
        rec.disconnect()  # completes the file (flush alone leaves it without its footer)
        result["rerun"] = str(out_dir / "pushes.rrd")
    (out_dir / "summary.json").write_text(json.dumps(result, indent=1))
    return result


def _resume_command(out_dir: Path) -> str:
    """The command that resumes this run if it is killed: the same overrides, the same run folder."""
    import shlex

    from pushtorch.apps.cli import current_overrides

    kept = [o for o in current_overrides() if not o.lstrip("+~").startswith("hydra.run.dir=")]
    return shlex.join(["pushtorch-simulate", *kept, f"hydra.run.dir={out_dir}"])


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="simulate")
def _app(cfg: DictConfig) -> dict[str, Any]:
    return run_stage("pushtorch-simulate", cfg, simulate_from_config)


def main() -> None:
    """Entry point of ``pushtorch-simulate`` (a user error exits with status 2 and one line)."""
    compose_or_exit("pushtorch-simulate", "simulate")
    _app()
    exit_without_collecting()


if __name__ == "__main__":
    main()
