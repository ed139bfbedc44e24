"""Files that are never half-written: atomic writes (and, for the run folders, the locks beside them).

Every file the library writes — push-record shards and their manifests, model files, cached decompositions —
goes through :func:`atomic_write_bytes`: a temporary file in the same folder, fsync, ``os.replace``, so a
reader sees the old file or the new one, never part of either, and a killed writer leaves only a temporary
(:func:`temporary_files` finds them; the next write of that name removes them). No paper section: the
reliability the experiments rely on.
"""

from __future__ import annotations

import glob
import os
import uuid
from pathlib import Path

__all__ = ["atomic_write_bytes", "temporary_files"]


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


def temporary_files(folder: str | Path, name: str) -> list[Path]:
    """The temporaries :func:`atomic_write_bytes` leaves for ``folder/name`` when killed mid-write."""
    return sorted(Path(folder).glob(f".{glob.escape(name)}.tmp-*"))
