"""The ``pushtorch`` command: a Hydra app that runs one experiment into its run directory.

``python -m pushtorch experiment=<name> [overrides]``; ``--help`` lists the experiments (the
``experiment`` config group) and every other config group. Each experiment is a module in
:mod:`pushtorch.experiments` with ``run(cfg, out_dir) -> dict``; configuration reaches it as plain
arguments, never as a global.
"""

from __future__ import annotations

import importlib
import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import PushtorchError

log = logging.getLogger("pushtorch")


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def _app(cfg: DictConfig) -> dict:
    out_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    name = cfg.experiment.name
    try:
        module = importlib.import_module(f"pushtorch.experiments.{name}")
    except ModuleNotFoundError as exc:
        raise PushtorchError(f"no experiment module pushtorch.experiments.{name}") from exc
    log.info("experiment %s → %s", name, out_dir)
    summary = module.run(cfg, out_dir)
    OmegaConf.save(cfg, out_dir / "resolved_config.yaml", resolve=True)
    for key, value in summary.items():
        print(f"{key}: {value}")
    return summary


def main() -> None:
    """Console-script entry point (``pushtorch ...``)."""
    try:
        _app()
    except PushtorchError as exc:  # a user error: say what is wrong, no traceback
        print(f"pushtorch: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
