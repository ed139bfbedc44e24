"""A run's manifest: what a shard folder promises (the plan's digests), how much of it is there, and the checks
of loaded shards against it.

Paper, Experimental Setup and the parameter tables (tens of thousands of pushes per experiment, simulated in
resumable runs): a run's shard folder holds ``manifest.json`` (:data:`RUN_MANIFEST`, written by
:mod:`pushtorch.sim.runner` in the shard format of :mod:`pushtorch.sim.shards`): the plan's push count,
shard size, seed, the simulated world's version and digests of its push indices and actions
(:func:`plan_digests`). Loading a folder checks its records against it (:func:`run_status`,
:func:`check_against_manifest`, used by :func:`pushtorch.sim.records.load_records`): exactly the shards and
push indices it promises, each push's action, no duplicates. An unfinished run is refused with what is
missing and how to resume it (:meth:`RunStatus.describe`), unless ``allow_partial``. While a run writes the
folder it holds the folder's lock, the file ``.pushtorch-writer.lock`` (:func:`pushtorch.io.folder_lock`).
"""

from __future__ import annotations

import hashlib
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pushtorch.errors import RecordFormatError
from pushtorch.sim.settings import WORLD_VERSION
from pushtorch.sim.shards import complete_shards, read_manifest, shard_stem

__all__ = [
    "RUN_MANIFEST",
    "RunStatus",
    "check_against_manifest",
    "plan_digests",
    "read_run_manifest",
    "run_status",
    "shard_folder",
]

#: The run manifest in a shard folder (see the module docstring).
RUN_MANIFEST = "manifest.json"


def plan_digests(index: np.ndarray, action_index: np.ndarray, action: np.ndarray) -> dict:
    """What a run manifest records of its plan's pushes, so a loader can check records against it.

    Returns:
        ``index_first``: the first push index if the indices run consecutively (else None: then only
        the complete run is checked, by ``index_sha256``); ``index_sha256``, ``action_sha256``: SHA-256 of
        the plan's int64 indices and float64 actions in plan order; ``action_runs``: the plan's action
        indices run-length encoded, ``[[action_index, count], ...]``; ``actions``: action index → its
        action where every push of it shares one (else None).
    """
    index = np.ascontiguousarray(index, dtype=np.int64).reshape(-1)
    action_index = np.ascontiguousarray(action_index, dtype=np.int64).reshape(-1)
    action = np.ascontiguousarray(action, dtype=np.float64).reshape(-1, 2)
    consecutive = index.size == 0 or bool(np.array_equal(index, np.arange(index[0], index[0] + index.size)))
    runs: list[list[int]] = []
    for a in action_index.tolist():
        if runs and runs[-1][0] == a:
            runs[-1][1] += 1
        else:
            runs.append([a, 1])
    actions: dict[str, list[float]] | None = {}
    for a in np.unique(action_index).tolist():
        values = np.unique(action[action_index == a], axis=0)
        if len(values) != 1:
            actions = None
            break
        actions[str(a)] = values[0].tolist()
    return {
        "index_first": int(index[0]) if consecutive and index.size else None,
        "index_sha256": hashlib.sha256(index.tobytes()).hexdigest(),
        "action_sha256": hashlib.sha256(action.tobytes()).hexdigest(),
        "action_runs": runs,
        "actions": actions,
    }


@dataclass
class RunStatus:
    """How much of a run its shard folder holds (:func:`run_status`).

    Attributes:
        folder: the shard folder; pushes: pushes the run's manifest promises; shard_size: pushes per shard.
        finished: ids of the finished shards; missing: ids of the shards not finished yet.
        missing_pushes: pushes in the missing shards; missing_by_action: action index → pushes missing.
        actions_per_index: action index → pushes the plan has of it.
        resume: how to resume the run (recorded by whoever started it), or None.
    """

    folder: Path
    pushes: int
    shard_size: int
    finished: list[int]
    missing: list[int]
    missing_pushes: int
    missing_by_action: dict[int, int]
    actions_per_index: dict[int, int]
    resume: str | None

    @property
    def complete(self) -> bool:
        return not self.missing

    def describe(self) -> str:
        """One line: what is missing and how to resume."""
        absent = [a for a, k in self.missing_by_action.items() if k == self.actions_per_index.get(a)]
        short = {a: k for a, k in self.missing_by_action.items() if k and a not in absent}
        parts = []
        if absent:
            parts.append(f"action{'s' if len(absent) > 1 else ''} {', '.join(map(str, absent))} ha"
                         f"{'ve' if len(absent) > 1 else 's'} no push at all")
        if short:
            parts.append("; ".join(f"action {a} lacks {k} of {self.actions_per_index[a]}" for a, k in short.items()))
        shards = _ranges(self.missing)
        detail = f" ({'; '.join(parts)})" if parts else ""
        resume = self.resume or "rerun the same simulation (same configuration and seed) into this folder"
        # a run copied or moved since it started resumes where it is now
        run_folder = self.folder.parent if self.folder.name == "pushes" else self.folder
        resume = re.sub(r"hydra\.run\.dir=\S+", lambda _: shlex.quote(f"hydra.run.dir={run_folder}"), resume)
        return (
            f"{self.folder} is an unfinished run: {self.missing_pushes} of the {self.pushes} pushes its manifest"
            f" promises are missing (shard{'s' if len(self.missing) > 1 else ''} {shards} of"
            f" {len(self.finished) + len(self.missing)}){detail}. Resume it: {resume}"
        )


def _ranges(ids: list[int]) -> str:
    """``[0, 1, 2, 5]`` → ``"0-2, 5"``."""
    out, start = [], None
    for k, i in enumerate(ids):
        if start is None:
            start = i
        if k + 1 == len(ids) or ids[k + 1] != i + 1:
            out.append(str(start) if start == i else f"{start}-{i}")
            start = None
    return ", ".join(out)


def read_run_manifest(folder: Path) -> dict | None:
    """The run manifest of a shard folder (:data:`RUN_MANIFEST`), None where it has none (a manifest written
    before the settings named their engine gains ``engine: pybullet``). Shared by :func:`run_status`, the
    loader and the runner, which checks a resumed run against it.

    Raises:
        RecordFormatError: an unreadable manifest, pushes of another world version, or a bad push count or
            shard size.
    """
    path = folder / RUN_MANIFEST
    if not path.is_file():
        return None
    manifest = read_manifest(path, "run manifest")
    if manifest.get("world", 1) != WORLD_VERSION:  # manifests before the world had a version were world 1
        raise RecordFormatError(
            f"{folder} holds pushes simulated by another version of the world (world {manifest.get('world', 1)}, "
            f"this pushtorch simulates world {WORLD_VERSION}); they are never mixed with new ones: simulate them "
            "again into a fresh folder"
        )
    settings = manifest.get("settings")
    if isinstance(settings, dict) and "engine" not in settings:  # written before the world named its engine
        settings["engine"] = "pybullet"
    for key in ("pushes", "shard_size"):
        value = manifest.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < (1 if key == "shard_size" else 0):
            raise RecordFormatError(f"{path}: {key} must be a non-negative integer, got {value!r}")
    return manifest


def _expected_action_index(manifest: dict) -> np.ndarray | None:
    runs = manifest.get("action_runs")
    if not isinstance(runs, list):
        return None
    try:
        expected = np.concatenate([np.full(int(n), int(a), dtype=np.int64) for a, n in runs]) if runs else \
            np.zeros(0, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise RecordFormatError(f"the run manifest's action_runs are malformed: {exc}") from exc
    if len(expected) != manifest["pushes"]:
        raise RecordFormatError("the run manifest's action_runs do not cover its pushes")
    return expected


def run_status(path: str | Path) -> RunStatus | None:
    """How much of its run a shard folder (or a run folder with ``pushes/``) holds; None without a run
    manifest (a folder of loose shards).

    Raises:
        RecordFormatError: an unreadable run manifest, or a finished shard the run does not promise.
    """
    folder = shard_folder(Path(path))
    manifest = read_run_manifest(folder)
    if manifest is None:
        return None
    n, size = manifest["pushes"], manifest["shard_size"]
    n_shards = (n + size - 1) // size
    finished = sorted(complete_shards(folder, verify=False))
    extra = [k for k in finished if k >= n_shards]
    if extra:
        raise RecordFormatError(
            f"{folder} holds shard {extra[0]}, beyond the {n_shards} shards its run promises (a shard of another run?)"
        )
    missing = [k for k in range(n_shards) if k not in set(finished)]
    expected = _expected_action_index(manifest)
    by_action: dict[int, int] = {}
    per_index: dict[int, int] = {}
    if expected is not None:
        per_index = {int(a): int(c) for a, c in zip(*np.unique(expected, return_counts=True), strict=True)}
        for k in missing:
            for a, c in zip(*np.unique(expected[k * size:(k + 1) * size], return_counts=True), strict=True):
                by_action[int(a)] = by_action.get(int(a), 0) + int(c)
    missing_pushes = sum(min(size, n - k * size) for k in missing)
    resume = manifest.get("resume") if isinstance(manifest.get("resume"), str) else None
    return RunStatus(folder, n, size, finished, missing, missing_pushes, by_action, per_index, resume)


def check_against_manifest(shards: dict[int, dict[str, np.ndarray]], manifest: dict, folder: Path,
                           complete: bool) -> None:
    """Every loaded shard holds exactly the pushes the run manifest promises at its place.

    Args:
        shards: shard id → its arrays (:func:`pushtorch.sim.shards.read_shard`); manifest: the run's
            (:func:`read_run_manifest`); folder: the shard folder (for messages); complete: every shard of
            the run is there, so the whole run's index and action digests are checked too.

    Raises:
        RecordFormatError: a shard with other pushes, actions, seed or object than the run promises there.
    """
    n, size = manifest["pushes"], manifest["shard_size"]
    expected_actions = _expected_action_index(manifest)
    first = manifest.get("index_first")
    actions = manifest.get("actions")
    for k, arrays in shards.items():
        where = f"{folder / shard_stem(k)}.npz"
        count = min(size, n - k * size)
        if len(arrays["index"]) != count:
            raise RecordFormatError(f"{where} holds {len(arrays['index'])} pushes, the run promises {count} there")
        if isinstance(first, int) and not np.array_equal(
            arrays["index"], np.arange(first + k * size, first + k * size + count)
        ):
            raise RecordFormatError(
                f"{where} holds push indices {int(arrays['index'].min())}-{int(arrays['index'].max())}, the run"
                f" promises {first + k * size}-{first + k * size + count - 1} there (a duplicated or moved shard?)"
            )
        if expected_actions is not None and not np.array_equal(
            arrays["action_index"], expected_actions[k * size:k * size + count]
        ):
            raise RecordFormatError(f"{where} holds other actions than the run promises there")
        if isinstance(actions, dict):
            for a in np.unique(arrays["action_index"]).tolist():
                promised = actions.get(str(a))
                rows = np.asarray(arrays["action"])[arrays["action_index"] == a]
                if promised is None or not np.array_equal(rows, np.broadcast_to(promised, rows.shape)):
                    raise RecordFormatError(f"{where} holds pushes of action {a} other than the run's {promised}")
        if "seed" in manifest and not (np.asarray(arrays["seed"]) == manifest["seed"]).all():
            raise RecordFormatError(f"{where} holds pushes of another seed than the run's {manifest['seed']}")
        if "object" in manifest and not (np.asarray(arrays["object_name"]) == manifest["object"]).all():
            raise RecordFormatError(f"{where} holds pushes of another object than the run's {manifest['object']!r}")
    if complete and shards:
        ordered = [shards[k] for k in sorted(shards)]
        for key, name, dtype in (("index_sha256", "index", np.int64), ("action_sha256", "action", np.float64)):
            if key in manifest:
                data = np.concatenate([np.ascontiguousarray(a[name], dtype=dtype) for a in ordered])
                if hashlib.sha256(data.tobytes()).hexdigest() != manifest[key]:
                    raise RecordFormatError(f"{folder}: the records' push {name}s differ from the run's plan")


def shard_folder(path: Path) -> Path:
    """The shard folder of ``path``: a run folder's ``pushes/``, else ``path`` itself."""
    if (path / "pushes").is_dir():
        return path / "pushes"
    return path
