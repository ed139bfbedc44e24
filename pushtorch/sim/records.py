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
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import RecordFormatError

__all__ = [
    "ARRAYS",
    "FORMAT",
    "VERSION",
    "PushRecords",
    "atomic_write_bytes",
    "complete_shards",
    "load_records",
    "read_shard",
    "records_from_arrays",
    "shard_stem",
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
                values[f.name] = se3.Pose(value.p[selection], value.q[selection])
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


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: temporary file in the same folder, fsync, ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    try:  # make the rename itself durable
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:  # some filesystems cannot fsync a directory
        pass


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


def _read_manifest(path: Path) -> dict:
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RecordFormatError(f"{path} is not a readable shard manifest: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise RecordFormatError(f"{path} is not a {FORMAT} manifest")
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
    return arrays


def complete_shards(folder: str | Path, verify: bool = True) -> dict[int, Path]:
    """Shard id → manifest path of every finished shard in ``folder`` (hash-checked if ``verify``).

    A shard whose manifest is missing, unreadable or does not match its data is not finished.
    """
    folder = Path(folder)
    found: dict[int, Path] = {}
    if not folder.is_dir():
        return found
    for entry in sorted(folder.iterdir()):
        match = _SHARD_RE.match(entry.name)
        if not match:
            continue
        try:
            if verify:
                manifest = _read_manifest(entry)
                data = entry.with_name(str(manifest.get("npz", ""))).read_bytes()
                if hashlib.sha256(data).hexdigest() != manifest.get("sha256"):
                    continue
        except (RecordFormatError, OSError):
            continue
        found[int(match.group(1))] = entry
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
        return se3.Pose(f(prefix + "_p"), f(prefix + "_q"))

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


def _shard_folder(path: Path) -> Path:
    if (path / "pushes").is_dir():
        return path / "pushes"
    return path


def load_records(
    path: str | Path, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> PushRecords:
    """Load push records: one shard (``.json``/``.npz``), a shard folder, or a run folder (its ``pushes/``).

    Shards are read in push-index order, verified against their manifests and never unpickled.

    Returns:
        :class:`PushRecords` with every push of every finished shard.

    Raises:
        RecordFormatError: nothing to load, or a corrupt, tampered or foreign shard.
    """
    path = Path(path)
    if path.is_file():
        return records_from_arrays(read_shard(path), dtype, device)
    folder = _shard_folder(path)
    shards = complete_shards(folder, verify=False)
    if not shards:
        raise RecordFormatError(f"no finished push-record shard in {path}")
    batches = [records_from_arrays(read_shard(p), dtype, device) for _, p in sorted(shards.items())]
    records = PushRecords.cat(batches)
    order = torch.argsort(records.index, stable=True)
    if not torch.equal(order, torch.arange(len(records))):
        records = records.take(order)
    return records
