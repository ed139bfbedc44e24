"""What every Hydra app of pushtorch does around its stage: find its configs, claim its run folder, run, report.

Shared by the main app (``python -m pushtorch``) and the stage apps (``pushtorch-simulate``,
``pushtorch-train``, ``pushtorch-predict``). Configs are the package ``pushtorch.conf`` (:data:`CONFIG_PATH`),
so an installed copy runs from any folder. A user error (a :class:`PushtorchError`) is printed as one line
naming the problem and exits with status 2; it must be caught inside the Hydra task, because Hydra catches
exceptions itself before they reach code around the decorated function.
"""

from __future__ import annotations

import functools
import gc
import hashlib
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import PushtorchError
from pushtorch.io import lock_file

__all__ = ["CONFIG_PATH", "RUN_ONLY_KEYS", "compose_or_exit", "current_overrides", "job_dir_name", "run_stage"]

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


#: The lock file of a run folder, held while its stage runs.
RUN_LOCK = ".pushtorch.lock"


@contextmanager
def _claimed(out_dir: Path) -> Iterator[None]:
    """Hold the run folder's lock (:data:`RUN_LOCK`, :func:`pushtorch.io.lock_file`) while the stage runs.

    Two live processes never share a run folder, on one machine or on several nodes of a shared
    filesystem: the second stops with a clear error. A killed run's folder can be resumed
    (``hydra.run.dir=<folder>``): at once on the same machine, and on another node once the dead run's
    lock has expired (:data:`pushtorch.io.STALE_AFTER_S` after its last heartbeat).
    """
    def refuse(who: str) -> str:
        return (f"run folder {out_dir} is in use by {who}; give this run its own folder "
                f"(hydra.run.dir=<new folder>) or wait for that run to end")

    with lock_file(Path(out_dir) / RUN_LOCK, wait=False, refuse=refuse):
        yield


#: What a run folder holds before its stage has written anything of its own.
_BOOKKEEPING = frozenset({".hydra", RUN_LOCK, "resolved_config.yaml"})


def _discard_if_empty(out_dir: Path) -> None:
    """Remove a run folder that a refused run leaves with nothing but Hydra's and our bookkeeping (and its
    date folder under ``runs/`` if that is left empty); a folder holding any result or data is kept."""
    import shutil

    try:
        if (out_dir / RUN_LOCK).exists():  # another run holds it (this run's lock is released by now)
            return
        entries = list(out_dir.iterdir())
        if any(e.name not in _BOOKKEEPING and e.suffix != ".log" for e in entries):
            return
        shutil.rmtree(out_dir)
        parent = out_dir.parent
        if parent.resolve().parent == Path("runs").resolve() and not any(parent.iterdir()):
            parent.rmdir()
    except OSError:  # nothing to tidy, or not ours to remove: the error message matters more
        pass


def run_stage(name: str, cfg: DictConfig, run: Callable[[DictConfig, Path], dict[str, Any]]) -> dict[str, Any]:
    """Run ``run(cfg, out_dir)`` in the Hydra run directory and print its summary, one ``key: value`` a line."""
    from pushtorch.apps.config_check import APPS, check_config

    hydra_cfg = hydra.core.hydra_config.HydraConfig.get()
    out_dir = Path(hydra_cfg.runtime.output_dir)
    _share_cores(hydra_cfg)
    try:
        if hydra_cfg.job.config_name in APPS:  # again here: a launcher or callback list of the user's own
            check_config(cfg, hydra_cfg.job.config_name)
        with _claimed(out_dir):
            OmegaConf.save(cfg, out_dir / "resolved_config.yaml", resolve=True)
            summary = run(cfg, out_dir)
    except PushtorchError as exc:
        _discard_if_empty(out_dir)
        print(f"{name}: {exc}", file=sys.stderr)
        sys.exit(2)
    except OSError as exc:  # a read-only or full disk, a path under a file: name the path and the cause
        _discard_if_empty(out_dir)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{name}: {where}{exc.strerror or exc}", file=sys.stderr)
        sys.exit(2)
    for key, value in summary.items():
        if key == "summary":  # a table of its own lines, before the paths
            if value:
                print(value)
        else:
            print(f"{key}: {value}")
    return summary


def _share_cores(hydra_cfg) -> None:
    """The thread and process policy (:mod:`pushtorch.parallel`): a joblib sweep's jobs share the cores."""
    from pushtorch.parallel import declare_parallel_jobs, share_cores

    launcher = hydra_cfg.get("launcher") or {}
    if "Joblib" in str(launcher.get("_target_", "")):
        declare_parallel_jobs(int(launcher.get("n_jobs", -1)))
    share_cores()


def _one_line(message: str) -> str:
    """Hydra's multi-line composition error as one line: its sentences, then the options it lists."""
    lines, options, listing = [], [], False
    for raw in message.splitlines():
        line = raw.strip()
        if line.startswith("Config search path") or line.startswith("Set the environment variable"):
            break
        if line.startswith("Available options in"):
            listing = True
            continue
        if line:
            (options if listing else lines).append(line)
    text = " ".join(lines)
    return f"{text} (available: {', '.join(options)})" if options else text


def exit_without_collecting() -> None:
    """Called by a command whose work is done, just before it exits: the objects alive now are frozen
    (``gc.freeze``), so that the interpreter's exit does not walk them again in its full collections (about a
    second after a run that compiled the fast path and started Ray; measured by ``tools/bench_scale.py``'s
    experiment runs). Outputs are closed by then; the exit still frees everything and runs the atexit hooks
    (Ray's shutdown among them)."""
    gc.freeze()


def compose_or_exit(app: str, config_name: str, argv: Sequence[str] | None = None) -> None:
    """Compose the config the command line asks for (every job of a sweep, up to 256) before Hydra does,
    so an unknown option of a config group or a key that does not exist is one line and exit 2 (Hydra
    itself prints several lines and exits 1); every sweep job's config is also checked here
    (:func:`pushtorch.apps.config_check.check_config`), before the sweep folder exists. ``--help``, ``--cfg``
    and the like are left to Hydra.
    """
    from hydra import compose, initialize_config_module
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra._internal.utils import get_args_parser
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        args = get_args_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    except SystemExit:
        return  # Hydra's own parser reports it
    if args.help or args.hydra_help or args.cfg or args.info or args.shell_completion or args.resolve:
        return
    try:
        if args.multirun:
            parsed = OverridesParser.create().parse_overrides(list(args.overrides))
            jobs = [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch][:256]
        else:
            jobs = [list(args.overrides)]
    except Exception as exc:  # an override Hydra cannot parse
        print(f"{app}: {_one_line(str(exc))}", file=sys.stderr)
        sys.exit(2)
    if GlobalHydra.instance().is_initialized():
        return  # called inside another Hydra app (a test): leave it to that app
    from pushtorch.apps.config_check import APPS, ConfigError, check_config

    try:
        with initialize_config_module(config_module=CONFIG_PATH.removeprefix("pkg://"), version_base="1.3"):
            for job in jobs:
                composed = compose(config_name, overrides=job, return_hydra_config=True)
                if args.multirun and config_name in APPS:  # a single run is checked by the callback
                    check_config(composed, config_name)
    except ConfigError as exc:
        print(f"{app}: {exc} (sweep job {' '.join(job)})", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:
        where = f" (sweep job {' '.join(job)})" if args.multirun else ""
        print(f"{app}: {_one_line(str(exc))}{where}", file=sys.stderr)
        sys.exit(2)
    finally:
        GlobalHydra.instance().clear()
