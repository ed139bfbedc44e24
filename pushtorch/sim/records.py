"""Push records: what every simulated push leaves behind, stored as shards that load without pickle.

Paper, Experimental Setup ("a push action is generated and a PDR is recorded") and Rigid Body Motions
(contact frames are rigidly attached to the object, so their motion follows from the object's initial and
final poses: a record holds poses, never model-specific contact data, and any model can be trained from it).

Per push: object name, push index and run seed, action ``(ẋ m/s, θ̇ rad/s)`` and its index, the object's
initial and final pose, the robot's start pose, object and robot trajectories at the record rate, the
sampled mass and ground friction and the object's own friction coefficient, and validity flags (touched,
tipped, left the ground). Poses are world-frame, quaternions w,x,y,z.

Shard format (version 1), in a run's ``pushes/`` folder:
    ``shard-000123.npz``   a plain ``numpy.savez_compressed`` archive of numeric, bool and fixed-width
                           unicode arrays only (see :data:`ARRAYS`); read with ``allow_pickle=False``.
    ``shard-000123.json``  its manifest: format name and version, push count and index range, the array
                           names with dtypes and shapes, and the SHA-256 of the ``.npz`` bytes.
Both files are written to a temporary name, flushed to disk and renamed into place (``os.replace``), the
``.json`` last: a shard exists exactly when its manifest does and the hash matches, so a run killed at any
moment never leaves a half shard that a loader or a resumed run would take as finished.

A run's shard folder also holds ``manifest.json`` (written by :mod:`pushtorch.sim.runner`): the plan's push
count, shard size, seed and digests of its push indices and actions (:func:`plan_digests`). Loading a
folder checks its records against it (:func:`run_status`, :func:`load_records`): exactly the shards and
push indices it promises, each push's action, no duplicates, finite poses and unit quaternions. An
unfinished run is refused with what is missing and how to resume it, unless ``allow_partial``. While a run
writes the folder it holds the folder's lock, the file ``.pushtorch-writer.lock``
(:func:`pushtorch.io.folder_lock`, re-exported here).
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import shlex
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import IncompleteRunError, RecordFormatError
from pushtorch.io import atomic_write_bytes, folder_lock, temporary_files  # re-exported: their former home

__all__ = [
    "ARRAYS",
    "FORMAT",
    "VERSION",
    "PushRecords",
    "RUN_MANIFEST",
    "RunStatus",
    "atomic_write_bytes",
    "complete_shards",
    "folder_lock",
    "load_records",
    "plan_digests",
    "read_shard",
    "records_from_arrays",
    "records_table",
    "write_table",
    "run_status",
    "shard_stem",
    "temporary_files",
    "write_shard",
]

FORMAT = "pushtorch.push_records"
VERSION = 1

#: Array name → (dtype kind, trailing shape). "N" is the push count, "T" the number of recorded times.
#: Kinds: "i" int64, "f" float64, "b" bool, "U" unicode string.
ARRAYS: dict[str, tuple[str, tuple[str | int, ...]]] = {
    "index": ("i", ("N",)),
    "seed": ("i", ("N",)),
    "object_name": ("U", ("N",)),
    "action_index": ("i", ("N",)),
    "action": ("f", ("N", 2)),
    "object_initial_p": ("f", ("N", 3)),
    "object_initial_q": ("f", ("N", 4)),
    "object_final_p": ("f", ("N", 3)),
    "object_final_q": ("f", ("N", 4)),
    "robot_start_p": ("f", ("N", 3)),
    "robot_start_q": ("f", ("N", 4)),
    "object_trajectory_p": ("f", ("N", "T", 3)),
    "object_trajectory_q": ("f", ("N", "T", 4)),
    "robot_trajectory_p": ("f", ("N", "T", 3)),
    "robot_trajectory_q": ("f", ("N", "T", 4)),
    "time": ("f", ("T",)),
    "mass": ("f", ("N",)),
    "ground_friction": ("f", ("N",)),
    "object_friction": ("f", ("N",)),
    "touched": ("b", ("N",)),
    "tipped": ("b", ("N",)),
    "left_ground": ("b", ("N",)),
    "first_contact_time": ("f", ("N",)),
}

_SHARD_RE = re.compile(r"^shard-(\d{6,})\.json$")

#: The run manifest in a shard folder (see the module docstring).
RUN_MANIFEST = "manifest.json"

#: Largest distance of a stored quaternion's norm from 1 (they are normalised float64 when written).
UNIT_QUATERNION_TOLERANCE = 1e-3

#: Pose arrays of a shard that must be finite, as (position array, quaternion array) pairs.
_POSES = [(f"{name}_p", f"{name}_q") for name in
          ("object_initial", "object_final", "robot_start", "object_trajectory", "robot_trajectory")]


@dataclass
class PushRecords:
    """A batch of N pushes as stacked tensors (the loader's output; fields mirror :data:`ARRAYS`).

    Attributes:
        object_name: N object names.
        index: ``(N,)`` int64 push index within its run; seed: ``(N,)`` the run's base seed.
        action: ``(N, 2)`` (ẋ m/s, θ̇ rad/s); action_index: ``(N,)`` int64.
        object_initial, object_final, robot_start: poses ``(N,)``.
        object_trajectory, robot_trajectory: poses ``(N, T)`` at ``time (T,)`` seconds.
        mass: ``(N,)`` kg; ground_friction: ``(N,)`` effective object-ground coefficient;
        object_friction: ``(N,)`` the object body's own coefficient in the engine.
        touched, tipped, left_ground: ``(N,)`` bool; first_contact_time: ``(N,)`` s (NaN: never).
    """

    object_name: tuple[str, ...]
    index: torch.Tensor
    seed: torch.Tensor
    action_index: torch.Tensor
    action: torch.Tensor
    object_initial: se3.Pose
    object_final: se3.Pose
    robot_start: se3.Pose
    object_trajectory: se3.Pose
    robot_trajectory: se3.Pose
    time: torch.Tensor
    mass: torch.Tensor
    ground_friction: torch.Tensor
    object_friction: torch.Tensor
    touched: torch.Tensor
    tipped: torch.Tensor
    left_ground: torch.Tensor
    first_contact_time: torch.Tensor

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @property
    def valid(self) -> torch.Tensor:
        """``(N,)`` bool: the robot touched the object and it neither tipped nor left the ground."""
        return self.touched & ~self.tipped & ~self.left_ground

    def take(self, selection) -> PushRecords:
        """A subset by index, index list or tensor, slice or boolean mask (the N dim is kept)."""
        if isinstance(selection, int):
            selection = [selection]
        if isinstance(selection, list):
            selection = torch.as_tensor(selection, dtype=torch.int64)
        if isinstance(selection, torch.Tensor) and selection.dtype == torch.bool:
            selection = selection.nonzero(as_tuple=True)[0]
        names = np.asarray(self.object_name, dtype=object)[
            selection.cpu().numpy() if isinstance(selection, torch.Tensor) else selection
        ]
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "object_name":
                values[f.name] = tuple(str(n) for n in np.atleast_1d(names))
            elif f.name == "time":
                values[f.name] = value
            elif isinstance(value, se3.Pose):
                values[f.name] = se3.Pose.unchecked(value.p[selection], value.q[selection])
            else:
                values[f.name] = value[selection]
        return PushRecords(**values)

    def to(self, *args, **kwargs) -> PushRecords:
        """Move or cast the floating-point tensors (index, flags and names keep their types)."""
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, se3.Pose):
                values[f.name] = value.to(*args, **kwargs)
            elif isinstance(value, torch.Tensor) and value.is_floating_point():
                values[f.name] = value.to(*args, **kwargs)
            elif isinstance(value, torch.Tensor):
                positional = (a for a in args if isinstance(a, str | torch.device))
                device = kwargs.get("device", next(positional, None))
                values[f.name] = value.to(device) if device is not None else value
            else:
                values[f.name] = value
        return PushRecords(**values)

    @staticmethod
    def cat(batches: Iterable[PushRecords]) -> PushRecords:
        """Concatenate batches recorded at the same times.

        Raises:
            RecordFormatError: no batch, or batches with different record times.
        """
        batches = list(batches)
        if not batches:
            raise RecordFormatError("no push records to concatenate")
        time = batches[0].time
        for b in batches[1:]:
            if b.time.shape != time.shape or not torch.allclose(b.time, time):
                raise RecordFormatError("push records with different record times cannot be concatenated")
        values = {}
        for f in fields(PushRecords):
            items = [getattr(b, f.name) for b in batches]
            if f.name == "object_name":
                values[f.name] = tuple(n for item in items for n in item)
            elif f.name == "time":
                values[f.name] = time
            elif isinstance(items[0], se3.Pose):
                values[f.name] = se3.Pose.cat(items, 0)
            else:
                values[f.name] = torch.cat(items, 0)
        return PushRecords(**values)


def shard_stem(shard_id: int) -> str:
    """File stem of a shard: ``shard-000042``."""
    return f"shard-{int(shard_id):06d}"


def _check_arrays(arrays: Mapping[str, np.ndarray], where: str) -> tuple[int, int]:
    """Validate names, dtypes and shapes against :data:`ARRAYS`; return (N, T)."""
    missing = sorted(set(ARRAYS) - set(arrays))
    if missing:
        raise RecordFormatError(f"{where} lacks the arrays {', '.join(missing)}")
    n = int(np.asarray(arrays["index"]).shape[0]) if np.asarray(arrays["index"]).ndim == 1 else -1
    t = int(np.asarray(arrays["time"]).shape[0]) if np.asarray(arrays["time"]).ndim == 1 else -1
    if n < 0 or t < 1:
        raise RecordFormatError(f"{where}: 'index' must be 1-D and 'time' non-empty 1-D")
    sizes = {"N": n, "T": t}
    for name, (kind, shape) in ARRAYS.items():
        a = np.asarray(arrays[name])
        if a.dtype.kind != kind and not (kind == "f" and a.dtype.kind in "fi"):
            raise RecordFormatError(f"{where}: array {name!r} has dtype {a.dtype}, expected kind {kind!r}")
        expected = tuple(sizes.get(s, s) if isinstance(s, str) else s for s in shape)
        if a.shape != expected:
            raise RecordFormatError(f"{where}: array {name!r} has shape {a.shape}, expected {expected}")
    return n, t


def _npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{name: np.asarray(arrays[name]) for name in ARRAYS})
    return buffer.getvalue()


def write_shard(folder: str | Path, shard_id: int, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write one shard (``.npz`` then its ``.json`` manifest, each atomically); return the manifest path.

    Raises:
        RecordFormatError: the arrays do not match :data:`ARRAYS`.
    """
    folder = Path(folder)
    arrays = {name: np.asarray(arrays[name]) for name in ARRAYS if name in arrays}
    n, t = _check_arrays(arrays, f"shard {shard_id}")
    data = _npz_bytes(arrays)
    stem = shard_stem(shard_id)
    atomic_write_bytes(folder / f"{stem}.npz", data)
    index = arrays["index"]
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "shard": int(shard_id),
        "count": n,
        "record_times": t,
        "first_index": int(index.min()) if n else None,
        "last_index": int(index.max()) if n else None,
        "npz": f"{stem}.npz",
        "sha256": hashlib.sha256(data).hexdigest(),
        "arrays": {
            name: {"dtype": str(arrays[name].dtype), "shape": list(arrays[name].shape)} for name in ARRAYS
        },
    }
    path = folder / f"{stem}.json"
    atomic_write_bytes(path, json.dumps(manifest, indent=1).encode())
    return path


def _read_manifest(path: Path, what: str = "shard manifest") -> dict:
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RecordFormatError(f"{path} is not a readable {what}: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise RecordFormatError(f"{path} is not a {FORMAT} {what.removeprefix('shard ')}")
    if manifest.get("version") != VERSION:
        raise RecordFormatError(
            f"{path} has format version {manifest.get('version')}, this reader knows {VERSION}"
        )
    return manifest


def read_shard(path: str | Path) -> dict[str, np.ndarray]:
    """Read and verify one shard (its ``.json`` or ``.npz`` path) as numpy arrays, without pickle.

    Raises:
        RecordFormatError: missing file, hash mismatch (tampered or truncated), arrays that would need
            pickle (object dtype), or arrays that do not match :data:`ARRAYS`.
    """
    path = Path(path)
    manifest_path = path.with_suffix(".json")
    if not _SHARD_RE.match(manifest_path.name):
        raise RecordFormatError(
            f"{path} is not a push-record shard (shard-<number>.json/.npz): give a pushtorch.simulate run folder,"
            " its pushes/ folder or one of its shards"
        )
    manifest = _read_manifest(manifest_path)
    npz_path = manifest_path.with_name(str(manifest.get("npz", "")))
    try:
        data = npz_path.read_bytes()
    except OSError as exc:
        raise RecordFormatError(f"shard data {npz_path} is missing: {exc}") from exc
    if hashlib.sha256(data).hexdigest() != manifest.get("sha256"):
        raise RecordFormatError(f"{npz_path} does not match the SHA-256 in {manifest_path.name}")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except ValueError as exc:  # object arrays refuse to load without pickle
        raise RecordFormatError(f"{npz_path} holds an array that would need pickle: {exc}") from exc
    except Exception as exc:  # zipfile/format errors
        raise RecordFormatError(f"{npz_path} is not a readable .npz archive: {exc}") from exc
    n, _ = _check_arrays(arrays, str(npz_path))
    if n != manifest.get("count"):
        raise RecordFormatError(f"{npz_path} holds {n} pushes, its manifest says {manifest.get('count')}")
    _check_values(arrays, str(npz_path))
    return arrays


def _check_values(arrays: Mapping[str, np.ndarray], where: str) -> None:
    """Finite poses, unit quaternions, finite actions, masses and frictions (the shapes are checked)."""
    for p_name, q_name in _POSES:
        p, q = np.asarray(arrays[p_name], dtype=np.float64), np.asarray(arrays[q_name], dtype=np.float64)
        if not (np.isfinite(p).all() and np.isfinite(q).all()):
            raise RecordFormatError(f"{where}: {p_name[:-2]} poses hold NaN or infinite values")
        off = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
        if off.size and off.max() > UNIT_QUATERNION_TOLERANCE:
            raise RecordFormatError(
                f"{where}: {q_name} holds quaternions that are not unit length (off by up to {off.max():.3g})"
            )
    for name in ("action", "mass", "ground_friction", "object_friction", "time"):
        if not np.isfinite(np.asarray(arrays[name], dtype=np.float64)).all():
            raise RecordFormatError(f"{where}: {name} holds NaN or infinite values")


#: Beside the shards: what :func:`complete_shards` already verified (file size, modification time and the
#: manifest's SHA-256 per shard), so a resumed run does not hash its finished shards again.
VERIFIED = ".verified.json"


def _read_verified(folder: Path) -> dict:
    try:
        cached = json.loads((folder / VERIFIED).read_text())
    except (OSError, ValueError):
        return {}
    return cached if isinstance(cached, dict) else {}


def complete_shards(folder: str | Path, verify: bool = True) -> dict[int, Path]:
    """Shard id → manifest path of every finished shard in ``folder`` (hash-checked if ``verify``).

    A shard whose manifest is missing, unreadable or does not match its data is not finished. A shard whose
    data file has the size and modification time it had when it was last verified against the same SHA-256
    (:data:`VERIFIED`) is not hashed again; :func:`load_records` still hashes everything it reads.
    """
    folder = Path(folder)
    found: dict[int, Path] = {}
    if not folder.is_dir():
        return found
    cache = _read_verified(folder) if verify else {}
    verified: dict[str, list] = {}
    for entry in sorted(folder.iterdir()):
        match = _SHARD_RE.match(entry.name)
        if not match:
            continue
        try:
            if verify:
                manifest = _read_manifest(entry)
                npz = entry.with_name(str(manifest.get("npz", "")))
                stat = npz.stat()
                key = [stat.st_size, stat.st_mtime_ns, manifest.get("sha256")]
                if cache.get(npz.name) != key:
                    if hashlib.sha256(npz.read_bytes()).hexdigest() != manifest.get("sha256"):
                        continue
                verified[npz.name] = key
        except (RecordFormatError, OSError):
            continue
        found[int(match.group(1))] = entry
    if verify and verified != cache:
        try:
            atomic_write_bytes(folder / VERIFIED, json.dumps(verified).encode())
        except OSError:  # a read-only folder: verified again next time
            pass
    return found


def records_from_arrays(
    arrays: Mapping[str, np.ndarray], dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> PushRecords:
    """Stack shard arrays into :class:`PushRecords` (floats cast to ``dtype``).

    Raises:
        RecordFormatError: the arrays do not match :data:`ARRAYS`.
    """
    _check_arrays(arrays, "push records")

    def f(name: str) -> torch.Tensor:
        return torch.as_tensor(np.asarray(arrays[name], dtype=np.float64), device=device).to(dtype)

    def pose(prefix: str) -> se3.Pose:
        return se3.Pose.unchecked(f(prefix + "_p"), f(prefix + "_q"))

    return PushRecords(
        object_name=tuple(str(n) for n in np.asarray(arrays["object_name"]).tolist()),
        index=torch.as_tensor(np.asarray(arrays["index"], dtype=np.int64), device=device),
        seed=torch.as_tensor(np.asarray(arrays["seed"], dtype=np.int64), device=device),
        action_index=torch.as_tensor(np.asarray(arrays["action_index"], dtype=np.int64), device=device),
        action=f("action"),
        object_initial=pose("object_initial"),
        object_final=pose("object_final"),
        robot_start=pose("robot_start"),
        object_trajectory=pose("object_trajectory"),
        robot_trajectory=pose("robot_trajectory"),
        time=f("time"),
        mass=f("mass"),
        ground_friction=f("ground_friction"),
        object_friction=f("object_friction"),
        touched=torch.as_tensor(np.asarray(arrays["touched"], dtype=bool), device=device),
        tipped=torch.as_tensor(np.asarray(arrays["tipped"], dtype=bool), device=device),
        left_ground=torch.as_tensor(np.asarray(arrays["left_ground"], dtype=bool), device=device),
        first_contact_time=f("first_contact_time"),
    )


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


def _read_run_manifest(folder: Path) -> dict | None:
    path = folder / RUN_MANIFEST
    if not path.is_file():
        return None
    manifest = _read_manifest(path, "run manifest")
    from pushtorch.sim.world import WORLD_VERSION

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
    folder = _shard_folder(Path(path))
    manifest = _read_run_manifest(folder)
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


def _check_against_manifest(shards: dict[int, dict[str, np.ndarray]], manifest: dict, folder: Path,
                            complete: bool) -> None:
    """Every loaded shard holds exactly the pushes the run manifest promises at its place."""
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


def _shard_folder(path: Path) -> Path:
    if (path / "pushes").is_dir():
        return path / "pushes"
    return path


def _trimmed(arrays: dict[str, np.ndarray], trajectories: bool) -> dict[str, np.ndarray]:
    """The shard's arrays, its trajectories cut to their last sample unless ``trajectories``."""
    if trajectories:
        return arrays
    out = dict(arrays)
    for name in ("object_trajectory_p", "object_trajectory_q", "robot_trajectory_p", "robot_trajectory_q"):
        out[name] = np.ascontiguousarray(arrays[name][:, -1:])
    out["time"] = np.ascontiguousarray(arrays["time"][-1:])
    return out


def load_records(
    path: str | Path,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    allow_partial: bool = False,
    trajectories: bool = True,
) -> PushRecords:
    """Load push records: one shard (``.json``/``.npz``), a shard folder, or a run folder (its ``pushes/``).

    Shards are read in push-index order, verified against their manifests and never unpickled. A folder
    with a run manifest is checked against it: every promised shard finished, each holding exactly the
    push indices and actions the run promises there, no push twice, finite poses, unit quaternions.

    Args:
        allow_partial: load the finished shards of an unfinished run instead of refusing it (check with
            :func:`run_status` what is missing).
        trajectories: keep the recorded trajectories; False keeps only their last sample (``T = 1``: the
            robot's final pose, all training uses), a sixteenth of the memory at the paper's 41 samples.

    Returns:
        :class:`PushRecords` with every push of every finished shard.

    Raises:
        IncompleteRunError: an unfinished run (what is missing and how to resume it), unless ``allow_partial``.
        RecordFormatError: nothing to load, or a corrupt, tampered, duplicated or foreign shard.
    """
    path = Path(path)
    if path.is_file():
        return records_from_arrays(_trimmed(read_shard(path), trajectories), dtype, device)
    if not path.exists():
        raise RecordFormatError(f"{path} does not exist: give a pushtorch.simulate run folder (or its pushes/)")
    folder = _shard_folder(path)
    status = run_status(folder)
    if status is not None and not status.complete and not allow_partial:
        raise IncompleteRunError(status.describe() + "; or train on what is there with allow_partial=true")
    shards = complete_shards(folder, verify=False)
    if not shards:
        raise RecordFormatError(f"no finished push-record shard in {path}")
    arrays = {k: _trimmed(read_shard(p), trajectories) for k, p in sorted(shards.items())}
    if status is not None:
        _check_against_manifest(arrays, _read_run_manifest(folder), folder, status.complete)
    records = PushRecords.cat([records_from_arrays(a, dtype, device) for a in arrays.values()])
    order = torch.argsort(records.index, stable=True)
    repeated = records.index[order][1:] == records.index[order][:-1]
    if repeated.any():
        twice = int(records.index[order][1:][repeated][0])
        holders = [k for k, a in arrays.items() if twice in a["index"]]
        raise RecordFormatError(
            f"{folder}: push {twice} appears more than once (in shards {', '.join(map(str, holders))}): a duplicated"
            " shard; remove the copy"
        )
    if not torch.equal(order, torch.arange(len(records))):
        records = records.take(order)
    return records


#: The per-push table beside a finished run's shards (:func:`write_table`): Parquet, readable without pushtorch.
TABLE = "pushes.parquet"


def records_table(records: PushRecords):
    """The per-push table of ``records`` as a ``pyarrow.Table``: one row per push, the columns ``index``,
    ``seed``, ``object_name``, ``action_index``, ``speed``, ``yaw_rate`` (m/s, rad/s), the poses
    ``object_initial_*``, ``object_final_*``, ``robot_start_*`` and ``robot_final_*`` as ``x, y, z`` (m) and
    ``qw, qx, qy, qz``, then ``mass``, ``ground_friction``, ``object_friction``, ``touched``, ``tipped``,
    ``left_ground``, ``valid`` and ``first_contact_time`` (s). No trajectories: those stay in the shards.
    """
    import pyarrow as pa

    columns: dict[str, np.ndarray] = {
        "index": records.index.numpy(), "seed": records.seed.numpy(),
        "object_name": np.asarray(records.object_name, dtype=object),
        "action_index": records.action_index.numpy(),
        "speed": records.action[:, 0].double().numpy(), "yaw_rate": records.action[:, 1].double().numpy(),
    }
    final_robot = se3.Pose.unchecked(records.robot_trajectory.p[:, -1], records.robot_trajectory.q[:, -1])
    for name, pose in (("object_initial", records.object_initial), ("object_final", records.object_final),
                       ("robot_start", records.robot_start), ("robot_final", final_robot)):
        for k, axis in enumerate("xyz"):
            columns[f"{name}_{axis}"] = pose.p[:, k].double().numpy()
        for k, axis in enumerate(("qw", "qx", "qy", "qz")):
            columns[f"{name}_{axis}"] = pose.q[:, k].double().numpy()
    for name in ("mass", "ground_friction", "object_friction", "first_contact_time"):
        columns[name] = getattr(records, name).double().numpy()
    for name in ("touched", "tipped", "left_ground", "valid"):
        columns[name] = getattr(records, name).numpy()
    return pa.table(columns)


def write_table(folder: str | Path) -> Path:
    """Write :data:`TABLE` (Parquet) beside a finished run's shards, atomically; returns its path.

    ``pandas.read_parquet(path)`` or ``pyarrow.parquet.read_table(path)`` read it without pushtorch.

    Raises:
        IncompleteRunError: the run is not finished.
    """
    import pyarrow.parquet as pq

    folder = _shard_folder(Path(folder))
    table = records_table(load_records(folder, dtype=torch.float64, trajectories=False))
    buffer = io.BytesIO()
    pq.write_table(table, buffer)
    path = folder / TABLE
    atomic_write_bytes(path, buffer.getvalue())
    return path
