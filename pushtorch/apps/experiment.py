"""The ``pushtorch`` command: a Hydra app that runs one experiment into its run directory.

``python -m pushtorch experiment=<name> [overrides]``; ``--help`` lists the experiments (the
``experiment`` config group) and every other config group. Each experiment (paper, Experimental Results) is an
entry of :data:`pushtorch.experiments.registry.EXPERIMENTS`: ``run(cfg, out_dir, overrides) -> dict``;
configuration reaches it as plain arguments, never as a global.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pushtorch.apps.cli import CONFIG_PATH, compose_or_exit, current_overrides, exit_without_collecting, run_stage
from pushtorch.experiments.registry import experiment_runner
from pushtorch.kde import declare_long_run

log = logging.getLogger("pushtorch")


def compiles(cfg: DictConfig) -> bool:
    """Whether an experiment compiles the fast path: an experiment predicts many times, so compiling pays, unless
    its config says ``experiment.compile: false`` (the main job: docs/speed.md, "The main job's time")."""
    return bool(cfg.experiment.get("compile", True))


def _run_experiment(cfg: DictConfig, out_dir: Path) -> dict:
    name = cfg.experiment.name
    declare_long_run(compiles(cfg))
    run = experiment_runner(name)  # an unknown name: InvalidParameterError listing the known ones
    log.info("experiment %s → %s", name, out_dir)
    return run(cfg, out_dir, current_overrides())


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def _app(cfg: DictConfig) -> dict:
    return run_stage("pushtorch", cfg, _run_experiment)


def main() -> None:
    """Console-script entry point (``pushtorch ...``); a user error exits with status 2 and one line."""
    compose_or_exit("pushtorch", "config")
    _app()
    exit_without_collecting()


if __name__ == "__main__":
    main()
