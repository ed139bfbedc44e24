"""The ``pushtorch`` command: a Hydra app that runs one experiment into its run directory.

``python -m pushtorch experiment=<name> [overrides]``; ``--help`` lists the experiments (the
``experiment`` config group) and every other config group. Each experiment is a module in
:mod:`pushtorch.experiments` with ``run(cfg, out_dir) -> dict``; configuration reaches it as plain
arguments, never as a global.
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, current_overrides, run_stage
from pushtorch.errors import PushtorchError
from pushtorch.kde import declare_long_run

log = logging.getLogger("pushtorch")


def _run_experiment(cfg: DictConfig, out_dir: Path) -> dict:
    name = cfg.experiment.name
    try:
        module = importlib.import_module(f"pushtorch.experiments.{name}")
    except ModuleNotFoundError as exc:
        raise PushtorchError(f"no experiment module pushtorch.experiments.{name}") from exc
    log.info("experiment %s → %s", name, out_dir)
    return module.run(cfg, out_dir, current_overrides())


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def _app(cfg: DictConfig) -> dict:
    return run_stage("pushtorch", cfg, _run_experiment)


def main() -> None:
    """Console-script entry point (``pushtorch ...``); a user error exits with status 2 and one line."""
    compose_or_exit("pushtorch", "config")
    declare_long_run()  # an experiment predicts many times: compiling the fast path pays
    _app()


if __name__ == "__main__":
    main()
