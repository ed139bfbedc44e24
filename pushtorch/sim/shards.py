"""The shard format of push records: write, read and verify shards that load without pickle.

Paper, Experimental Setup ("a push action is generated and a PDR is recorded"): every simulated push is
stored as arrays (:data:`ARRAYS`, the fields of :class:`pushtorch.sim.records.PushRecords`), a shard of
consecutive pushes at a time.

Shard format (version 1), in a run's ``pushes/`` folder:
    ``shard-000123.npz``   a plain ``numpy.savez_compressed`` archive of numeric, bool and fixed-width
                           unicode arrays only (see :data:`ARRAYS`); read with ``allow_pickle=False``.
    ``shard-000123.json``  its manifest: format name and version, push count and index range, the array
                           names with dtypes and shapes, and the SHA-256 of the ``.npz`` bytes.
Both files are written to a temporary name, flushed to disk and renamed into place (``os.replace``), the
``.json`` last: a shard exists exactly when its manifest does and the hash matches, so a run killed at any
moment never leaves a half shard that a loader or a resumed run would take as finished
(:func:`complete_shards`). A run's manifest beside its shards (:mod:`pushtorch.sim.run_manifest`) shares
their format name and version (:func:`read_manifest`).
"""

from __future__ import annotations

import hashlib
import io
import json
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pushtorch.errors import RecordFormatError
from pushtorch.io import atomic_write_bytes

__all__ = [
    "ARRAYS",
    "FORMAT",
    "UNIT_QUATERNION_TOLERANCE",
    "VERIFIED",
    "VERSION",
    "check_arrays",
    "complete_shards",
    "read_manifest",
    "read_shard",
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

#: Largest distance of a stored quaternion's norm from 1 (they are normalised float64 when written).
UNIT_QUATERNION_TOLERANCE = 1e-3

#: Pose arrays of a shard that must be finite, as (position array, quaternion array) pairs.
_POSES = [(f"{name}_p", f"{name}_q") for name in
          ("object_initial", "object_final", "robot_start", "object_trajectory", "robot_trajectory")]


def shard_stem(shard_id: int) -> str:
    """File stem of a shard: ``shard-000042``."""
    return f"shard-{int(shard_id):06d}"


def check_arrays(arrays: Mapping[str, np.ndarray], where: str) -> tuple[int, int]:
    """Validate names, dtypes and shapes against :data:`ARRAYS`; return (N, T).

    Shared by the shard writer and reader and by :func:`pushtorch.sim.records.records_from_arrays`.

    Raises:
        RecordFormatError: a missing array, or one of another dtype kind or shape (``where`` names it).
    """
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
    n, t = check_arrays(arrays, f"shard {shard_id}")
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


def read_manifest(path: Path, what: str = "shard manifest") -> dict:
    """The JSON manifest at ``path``, of this format and version: a shard's, or (``what="run manifest"``) a
    run's (:func:`pushtorch.sim.run_manifest.read_run_manifest`).

    Raises:
        RecordFormatError: an unreadable file, another format or another version.
    """
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
            f"{path} is not a push-record shard (shard-<number>.json/.npz): give a pushtorch-simulate run folder,"
            " its pushes/ folder or one of its shards"
        )
    manifest = read_manifest(manifest_path)
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
    n, _ = check_arrays(arrays, str(npz_path))
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
    (:data:`VERIFIED`) is not hashed again; :func:`~pushtorch.sim.records.load_records` still hashes
    everything it reads.
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
                manifest = read_manifest(entry)
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


