"""What every Hydra app of pushtorch does around its stage: find its configs, claim its run folder, run, report.

Shared by the main app (``python -m pushtorch``) and the stage apps (``pushtorch.simulate``,
``pushtorch.train``, ``pushtorch.predict``). Configs are the package ``pushtorch.conf`` (:data:`CONFIG_PATH`),
so an installed copy runs from any folder. A user error (a :class:`PushtorchError`) is printed as one line
naming the problem and exits with status 2; it must be caught inside the Hydra task, because Hydra catches
exceptions itself before they reach code around the decorated function.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import PushtorchError

__all__ = ["CONFIG_PATH", "RUN_ONLY_KEYS", "current_overrides", "job_dir_name", "run_stage"]

#: Where every app finds its configs: the installed package ``pushtorch.conf`` (the repository's conf/).
CONFIG_PATH = "pkg://pushtorch.conf"

_JOB_DIR_LIMIT = 120  # characters; file systems allow 255 bytes per name, Slurm logs and shells like less
#: Override keys that change how a job runs, not what it computes: left out of sweep folder names.
RUN_ONLY_KEYS = frozenset({"experiment.workers", "experiment.progress", "workers", "progress"})


def _override_key(override: str) -> str:
    return override.lstrip("+~").partition("=")[0]


@functools.lru_cache(maxsize=8)
def _swept_keys(multirun_yaml: str) -> frozenset[str]:
    """The keys a sweep varies, read from the ``multirun.yaml`` Hydra's sweeper writes before any job starts.

    A job's own config holds only its expanded overrides (``model.friction=low``), not which of them were
    swept (``model.friction=low,high``); the sweep folder's ``multirun.yaml`` holds the sweep as written.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        task = OmegaConf.load(multirun_yaml).hydra.overrides.task
        parsed = OverridesParser.create().parse_overrides([str(o) for o in task])
    except Exception:  # no sweep file (a user's own launcher) or one Hydra cannot parse: name by every override
        return frozenset()
    return frozenset(o.get_key_element() for o in parsed if o.is_sweep_override())


def job_dir_name(num: Any, sweep_dir: Any, overrides: Sequence[str]) -> str:
    """A sweep job's folder name: its number and the values it sweeps, safe as one file name.

    In a sweep of ``model.friction=low,high`` the jobs are ``0_model.friction=low`` and
    ``1_model.friction=high``, whatever other overrides the command has (without a ``multirun.yaml`` in
    ``sweep_dir``, every override but :data:`RUN_ONLY_KEYS` names the folder). Characters outside
    ``[A-Za-z0-9_.,=+-]`` (a ``/`` in a path value would nest folders) become ``_``; a name longer than 120
    characters is cut and ends in a hash of the whole, so two jobs never share a folder.
    """
    overrides = [str(o) for o in overrides]
    swept = _swept_keys(str(Path(str(sweep_dir)) / "multirun.yaml"))
    shown = [o for o in overrides if _override_key(o) in swept] if swept else [
        o for o in sorted(overrides) if _override_key(o) not in RUN_ONLY_KEYS]
    name = f"{num}_{','.join(shown)}" if shown else str(num)
    safe = re.sub(r"[^A-Za-z0-9_.,=+-]", "_", name)
    if len(safe) > _JOB_DIR_LIMIT:
        digest = hashlib.sha256(name.encode()).hexdigest()[:10]
        safe = f"{safe[: _JOB_DIR_LIMIT - 11]}_{digest}"
    return safe


OmegaConf.register_new_resolver("pushtorch.job_dir", job_dir_name, replace=True)


def current_overrides() -> list[str]:
    """The running Hydra job's command-line overrides (``[]`` outside a Hydra app)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    return list(HydraConfig.get().overrides.task)


@contextmanager
def _claimed(out_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock on the run folder while the stage runs.

    Two live processes never share a run folder: the second stops with a clear error. The lock goes with
    the process, so a killed run's folder can be resumed (``hydra.run.dir=<folder>``).
    """
    try:
        import fcntl
    except ImportError:  # Windows: no advisory locks; run folders are still unique by time
        yield
        return
    lock_path = out_dir / ".pushtorch.lock"
    with open(lock_path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            raise PushtorchError(f"run folder {out_dir} is in use by {holder}; give this run its own folder "
                                 f"(hydra.run.dir=<new folder>) or wait for that run to end") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()}")
        handle.flush()
        yield


def run_stage(name: str, cfg: DictConfig, run: Callable[[DictConfig, Path], dict[str, Any]]) -> dict[str, Any]:
    """Run ``run(cfg, out_dir)`` in the Hydra run directory and print its summary, one ``key: value`` a line."""
    from pushtorch.config_check import APPS, check_config

    hydra_cfg = hydra.core.hydra_config.HydraConfig.get()
    out_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        if hydra_cfg.job.config_name in APPS:  # again here: a launcher or callback list of the user's own
            check_config(cfg, hydra_cfg.job.config_name)
        with _claimed(out_dir):
            OmegaConf.save(cfg, out_dir / "resolved_config.yaml", resolve=True)
            summary = run(cfg, out_dir)
    except PushtorchError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        sys.exit(2)
    except OSError as exc:  # a read-only or full disk, a path under a file: name the path and the cause
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{name}: {where}{exc.strerror or exc}", file=sys.stderr)
        sys.exit(2)
    for key, value in summary.items():
        print(f"{key}: {value}")
    return summary
