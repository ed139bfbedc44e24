"""What every Hydra app of pushtorch does around its stage: save the resolved config, run, report.

Shared by the main app (``python -m pushtorch``) and the stage apps (``pushtorch.simulate``,
``pushtorch.train``, ``pushtorch.predict``). A user error (a :class:`PushtorchError`) is printed as one
line naming the problem and exits with status 2; it must be caught inside the Hydra task, because
Hydra catches exceptions itself before they reach code around the decorated function.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import PushtorchError

__all__ = ["run_stage"]


def run_stage(name: str, cfg: DictConfig, run: Callable[[DictConfig, Path], dict[str, Any]]) -> dict[str, Any]:
    """Run ``run(cfg, out_dir)`` in the Hydra run directory and print its summary, one ``key: value`` a line."""
    out_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    OmegaConf.save(cfg, out_dir / "resolved_config.yaml", resolve=True)
    try:
        summary = run(cfg, out_dir)
    except PushtorchError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        sys.exit(2)
    for key, value in summary.items():
        print(f"{key}: {value}")
    return summary
