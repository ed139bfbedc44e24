"""Files that are never half-written, locks that hold across machines, and sealed archives.

**Atomic writes.** Every file the library writes — push-record shards and their manifests, model files,
cached decompositions — goes through :func:`atomic_write_bytes`: a temporary file in the same folder, fsync,
``os.replace``, so a reader sees the old file or the new one, never part of either, and a killed writer
leaves only a temporary (:func:`temporary_files` finds them; the writers remove them on their next write of
that name).

**Locks.** A run folder, a shard folder and a folder that model files are saved to are written by one
process at a time: :func:`folder_lock` (the lock file :data:`FOLDER_LOCK` in the folder; shard folders and
model saves) and the apps' claim on their run folder (``.pushtorch.lock``, :mod:`pushtorch.apps.cli`) both hold
a :func:`lock_file`. A run folder may be run and resumed from many machines, on a filesystem the nodes of
a cluster share, so the lock is not ``flock``/``fcntl``: on NFS those lock only within one node (or not at
all), and two nodes would both pass the check. A lock is a file created by one atomic exclusive create
(``os.open(path, O_CREAT | O_EXCL | O_WRONLY)``, atomic on local filesystems and on NFSv3 and later): of
any number of processes on any number of nodes, exactly one creates it. It holds JSON ``{"host", "pid",
"started", "token", "pid_scope"}`` (the holder, its start time, a random token, and the boot and PID
namespace its pid belongs to); releasing the lock deletes it.

While a process holds a lock, a daemon thread refreshes the lock file's modification time every
:data:`HEARTBEAT_S` (5 s). A lock is stale, and the next process that wants it breaks it,

- at once when its holder ran on this host and that process no longer exists: a killed run resumes at
  once, as with a lock that dies with its process;
- when its heartbeat is older than :data:`STALE_AFTER_S` (60 s), whichever host holds it: when a node
  dies, loses power or loses the filesystem, its locks expire a minute after their last heartbeat. The
  age is read on the filesystem's own clock (the modification time of a file created to read it), so the
  nodes' clocks need not agree.

Breaking a stale lock is race-free: a breaker first creates, exclusively, a claim named after that lock's
token (one breaker per stale lock), checks under the claim that the lock is still the one it judged stale,
renames it to a name of its own and deletes it; then all contenders race for the exclusive create again,
and one wins. What no lease can do: a holder that stops for longer than the timeout (its process frozen,
or its node cut off from the filesystem while it keeps running) is taken for dead, and its lock goes to
another process (the old holder warns when it releases: it no longer held the lock); nodes that share a
folder must have different host names.

Within a process a lock belongs to the thread that took it: that thread taking it again is refused at once
(waiting would never end), other threads wait or are refused like other processes. Processes forked while
a lock is held (worker pools) do not hold it: they have no heartbeat thread, and leaving the lock's block
in a child releases nothing.

**Sealed archives.** Model files are zip archives (``.npz``) sealed by one SHA-256 over all their bytes
before the seal, kept as the archive's 64-character zip comment (:func:`sealed_archive`,
:func:`read_sealed_archive`): any edited byte breaks the seal.

No paper section: the reliability the experiments rely on. Only the standard library is used here.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import random
import socket
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from pushtorch.errors import FolderInUseError, RecordFormatError

__all__ = [
    "FOLDER_LOCK",
    "HEARTBEAT_S",
    "SEAL_BYTES",
    "STALE_AFTER_S",
    "LockHolder",
    "atomic_write_bytes",
    "folder_lock",
    "lock_file",
    "read_sealed_archive",
    "sealed_archive",
    "temporary_files",
]


# --- atomic writes -----------------------------------------------------------------------------------------

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
    _sync_folder(path.parent)


def temporary_files(folder: str | Path, name: str) -> list[Path]:
    """The temporaries :func:`atomic_write_bytes` leaves for ``folder/name`` when killed mid-write."""
    return sorted(Path(folder).glob(f".{glob.escape(name)}.tmp-*"))


def _sync_folder(folder: Path) -> None:
    """Make the renames in ``folder`` durable (some filesystems cannot fsync a folder: then nothing)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


# --- locks -------------------------------------------------------------------------------------------------

#: Seconds between two refreshes of a held lock file's modification time.
HEARTBEAT_S = 5.0
#: Seconds without a heartbeat after which a lock is stale, whichever host holds it.
STALE_AFTER_S = 60.0
#: The lock file of :func:`folder_lock`, in the locked folder.
FOLDER_LOCK = ".pushtorch-writer.lock"

#: With ``wait=False``: how long to wait for another process that is breaking the same stale lock.
_BREAKING_GRACE_S = 2.0
#: Longest pause between two tries of a waiting lock.
_MAX_POLL_S = 0.5
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


def _pid_scope() -> str:
    """This boot and PID namespace: a pid means this process only within them (Linux; elsewhere '')."""
    parts = []
    try:
        parts.append(Path("/proc/sys/kernel/random/boot_id").read_text().strip())
    except OSError:
        pass
    try:
        parts.append(os.readlink("/proc/self/ns/pid"))
    except OSError:
        pass
    return "/".join(parts)


_HOST = socket.gethostname()
_PID_SCOPE = _pid_scope()


@dataclass(frozen=True)
class LockHolder:
    """Who holds a lock: the content of its lock file."""

    host: str
    pid: int
    started: str
    token: str
    pid_scope: str = ""

    @property
    def on_this_host(self) -> bool:
        """Whether :attr:`pid` is a process of this host (same host name, boot and PID namespace)."""
        return self.host == _HOST and (not self.pid_scope or not _PID_SCOPE or self.pid_scope == _PID_SCOPE)

    def __str__(self) -> str:
        return f"pid {self.pid} on {self.host}" + (f" since {self.started}" if self.started else "")


def _parse_holder(data: bytes) -> LockHolder | None:
    """The holder a lock file names, or None (empty: its creator is writing it; or not a lock of ours)."""
    try:
        d = json.loads(data.decode())
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(d, dict):
        return None
    host, pid, token = d.get("host"), d.get("pid"), d.get("token")
    if not (isinstance(host, str) and isinstance(pid, int) and not isinstance(pid, bool) and pid > 0
            and isinstance(token, str) and token):
        return None
    started, scope = d.get("started"), d.get("pid_scope")
    return LockHolder(host, pid, started if isinstance(started, str) else "", token,
                      scope if isinstance(scope, str) else "")


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host exists (a zombie does not; unknown counts as alive)."""
    if pid == os.getpid():
        return True
    if os.name == "nt":  # os.kill would end the process there; the heartbeat decides instead
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rsplit(b")", 1)[1].split()[0]
        return state not in (b"Z", b"X")
    except (OSError, IndexError):
        return True


#: A look at a lock file: its holder (None: unreadable) and its stat, read through one descriptor.
_Seen = tuple[LockHolder | None, os.stat_result]


def _inspect(path: Path) -> _Seen | None:
    """The lock file at ``path`` now, or None when there is none."""
    try:
        fd = os.open(path, os.O_RDONLY | _CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        st = os.fstat(fd)  # after open: fresh attributes, also on NFS (close-to-open)
        data = os.read(fd, 65536)
    finally:
        os.close(fd)
    return _parse_holder(data), st


def _identity(seen: _Seen) -> str:
    """What tells this lock file from every other one at the same path: its token, or (unreadable) its
    inode and modification time."""
    holder, st = seen
    key = holder.token if holder is not None else f"{st.st_dev}:{st.st_ino}:{st.st_mtime_ns}:{st.st_size}"
    return hashlib.sha256(key.encode()).hexdigest()[:32]


def _create(path: Path, data: bytes) -> int | None:
    """Create ``path`` exclusively holding ``data`` (flushed to disk); its open descriptor, or None when it
    exists."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY | _CLOEXEC, 0o644)
    except FileExistsError:
        return None
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        try:
            os.unlink(path)
        except OSError:
            pass
        raise
    return fd


class _Clock:
    """The filesystem's clock, read once per acquisition as its offset from this host's clock (the
    modification time of a probe file created there), so a heartbeat's age does not depend on clock skew
    between nodes."""

    def __init__(self, lock: Path):
        self._lock = lock
        self._offset: float | None = None

    def now(self) -> float:
        if self._offset is None:
            probe = self._lock.with_name(f"{self._lock.name}.probe-{uuid.uuid4().hex}")
            try:
                fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY | _CLOEXEC, 0o644)
                try:
                    self._offset = os.fstat(fd).st_mtime - time.time()
                finally:
                    os.close(fd)
                    try:
                        os.unlink(probe)
                    except OSError:
                        pass
            except OSError:
                self._offset = 0.0
        return time.time() + self._offset


def _heartbeat_age(seen: _Seen, clock: _Clock) -> float:
    return clock.now() - seen[1].st_mtime


def _stale(seen: _Seen, clock: _Clock, stale_after: float) -> bool:
    """A lock of a process of this host that is gone, or one whose heartbeat is older than ``stale_after``."""
    holder = seen[0]
    if holder is not None and holder.on_this_host and not _pid_alive(holder.pid):
        return True
    return _heartbeat_age(seen, clock) > stale_after


def _break(path: Path, seen: _Seen, me: bytes, clock: _Clock, stale_after: float) -> bool:
    """Remove the stale lock ``seen`` at ``path``, unless another live process is removing it (False).

    One breaker per stale lock: the claim ``<lock>.break-<identity>.<n>`` is created exclusively; under it
    the lock is checked to be still ``seen`` (no other process can remove ``seen`` meanwhile), renamed to a
    name of this breaker's own and deleted. A claim whose breaker died is stale like a lock: the next
    breaker takes claim ``n + 1``.
    """
    ident = _identity(seen)
    generation = 0
    while generation < 1000:
        claim = path.with_name(f"{path.name}.break-{ident}.{generation}")
        fd = _create(claim, me)
        if fd is None:
            other = _inspect(claim)
            if other is not None and not _stale(other, clock, stale_after):
                return False  # a live process is breaking this lock now
            if other is not None:
                generation += 1
            continue
        try:
            current = _inspect(path)
            if current is None or _identity(current) != ident:
                return True  # broken already: race for it again
            moved = path.with_name(f"{path.name}.stale-{uuid.uuid4().hex}")
            try:
                os.rename(path, moved)
            except FileNotFoundError:
                return True
            taken = _inspect(moved)
            if taken is not None and _identity(taken) != ident:
                # only if the stale holder was alive after all, released, and a new holder took the name
                # between the check and the rename: give the new holder its lock back
                try:
                    os.link(moved, path)
                except OSError:
                    pass
            try:
                os.unlink(moved)
            except FileNotFoundError:
                pass
            return True
        finally:
            os.close(fd)
            try:
                os.unlink(claim)
            except FileNotFoundError:
                pass
    return False


def _tidy(path: Path, own: str) -> None:
    """Under the lock: remove what killed breakers and contenders left beside it (claims on locks other
    than this one, renamed stale locks, clock probes; none is in use by a live process's decision)."""
    prefix = f"{path.name}."
    try:
        entries = [e.name for e in os.scandir(path.parent) if e.name.startswith(prefix)]
    except OSError:
        return
    for name in entries:
        rest = name[len(prefix):]
        ours = rest.startswith(f"break-{own}.")  # a claim on this very lock: not left over
        if rest.startswith(("stale-", "probe-")) or (rest.startswith("break-") and not ours):
            try:
                os.unlink(path.parent / name)
            except OSError:
                pass


@dataclass
class _Lease:
    """A lock this process holds."""

    key: str
    path: Path
    fd: int
    holder: LockHolder
    pid: int
    thread: int


class _State:
    """This process's leases and their heartbeat thread (a forked child starts with a fresh one)."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.leases: dict[str, _Lease] = {}
        self.thread: threading.Thread | None = None


_STATE = _State()


def _touch(lease: _Lease) -> None:
    try:
        os.utime(lease.fd if os.utime in os.supports_fd else lease.path)
    except OSError:  # a filesystem hiccup: the next beat tries again
        pass


def _beat(state: _State) -> None:
    """The heartbeat: refresh every held lock file's modification time every :data:`HEARTBEAT_S`; end when
    none is held. Runs under the state's lock, so a descriptor is never touched after its release."""
    with state.cond:
        while state.leases:
            for lease in state.leases.values():
                _touch(lease)
            state.cond.wait(HEARTBEAT_S)
        state.thread = None


def _forget_in_child() -> None:
    """After a fork: the child holds none of its parent's locks and runs no heartbeat."""
    global _STATE
    for lease in _STATE.leases.values():
        try:
            os.close(lease.fd)
        except OSError:
            pass
    _STATE = _State()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_in_child)


def _describe(seen: _Seen, clock: _Clock) -> str:
    holder = seen[0]
    if holder is None:
        return "a process whose lock file is still being written or is not a pushtorch lock"
    if holder.on_this_host:
        return str(holder)
    age = _heartbeat_age(seen, clock)
    return (f"{holder}, last heartbeat {max(age, 0.0):.0f} s ago; a node that is gone loses its lock "
            f"{STALE_AFTER_S:.0f} s after its last heartbeat")


def _acquire(path: Path, wait: bool, refuse: Callable[[str], str], stale_after: float) -> _Lease:
    key = os.path.join(os.path.realpath(path.parent), path.name)
    thread = threading.get_ident()
    with _STATE.cond:
        mine = _STATE.leases.get(key)
        if mine is not None and mine.thread == thread:
            raise FolderInUseError(refuse(f"{mine.holder}: this thread holds the lock already and cannot wait for "
                                          "itself"))
    holder = LockHolder(_HOST, os.getpid(), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                        uuid.uuid4().hex, _PID_SCOPE)
    data = json.dumps(asdict(holder)).encode()
    clock = _Clock(path)
    delay, give_up, vanished = 0.02, time.monotonic() + _BREAKING_GRACE_S, 0
    while True:
        fd = _create(path, data)
        if fd is not None:
            break
        seen = _inspect(path)
        if seen is None:  # released meanwhile: try again at once (unless it is no file, e.g. a dangling link)
            vanished += 1
            if vanished < 100:
                continue
            if not wait:
                raise FolderInUseError(refuse(f"something at {path} that is not a readable lock file"))
        elif _stale(seen, clock, stale_after):
            if _break(path, seen, data, clock, stale_after):
                continue
            if not wait and time.monotonic() > give_up:
                raise FolderInUseError(refuse("a process that is taking over a stale lock"))
        elif not wait:
            raise FolderInUseError(refuse(_describe(seen, clock)))
        time.sleep(delay * (0.5 + random.random()))
        delay = min(delay * 1.5, _MAX_POLL_S)
    lease = _Lease(key, path, fd, holder, os.getpid(), thread)
    with _STATE.cond:
        _STATE.leases[key] = lease
        if _STATE.thread is None:
            _STATE.thread = threading.Thread(target=_beat, args=(_STATE,), name="pushtorch-lock-heartbeat",
                                             daemon=True)
            _STATE.thread.start()
    _tidy(path, _identity((holder, os.fstat(fd))))
    return lease


def _release(lease: _Lease) -> None:
    if lease.pid != os.getpid():  # a forked child leaving the block: the lock is its parent's
        return
    with _STATE.cond:
        if _STATE.leases.get(lease.key) is lease:
            del _STATE.leases[lease.key]
        os.close(lease.fd)  # under the lock: the heartbeat never touches a closed descriptor
        _STATE.cond.notify_all()
    path = lease.path
    moved = path.with_name(f"{path.name}.stale-{lease.holder.token}")
    try:
        os.rename(path, moved)  # then check: delete only our own lock file
    except FileNotFoundError:
        lost = path.parent.is_dir()  # else the folder itself was removed
    except OSError as exc:  # left in place: it goes stale once this process ends or after the timeout
        warnings.warn(f"could not remove the lock {path}: {exc}", RuntimeWarning, stacklevel=3)
        return
    else:
        taken = _inspect(moved)
        lost = taken is not None and (taken[0] is None or taken[0].token != lease.holder.token)
        if lost:
            try:
                os.link(moved, path)  # another process's lock: put it back
            except OSError:
                pass
        try:
            os.unlink(moved)
        except OSError:
            pass
    if lost:
        warnings.warn(f"the lock {path} was taken over while this process held it (no heartbeat for "
                      f"{STALE_AFTER_S:.0f} s): another process may have written beside this one",
                      RuntimeWarning, stacklevel=3)


@contextmanager
def lock_file(path: str | Path, wait: bool = True, refuse: Callable[[str], str] | None = None,
              stale_after: float | None = None) -> Iterator[LockHolder]:
    """Hold the lock file ``path`` for the block (see the module docstring); yields this holder.

    Args:
        path: the lock file; its folder must exist and be writable.
        wait: wait until the lock is free; False raises at once when a live process holds it.
        refuse: the error message, given who holds the lock (e.g. ``"pid 12 on node3 since ..."``).
        stale_after: seconds without a heartbeat after which a lock is stale (default :data:`STALE_AFTER_S`).

    Raises:
        FolderInUseError: ``wait`` is False and a live process holds the lock, or this thread holds it.
    """
    path = Path(path)
    lease = _acquire(path, wait, refuse or (lambda who: f"{path} is held by {who}"),
                     STALE_AFTER_S if stale_after is None else float(stale_after))
    try:
        yield lease.holder
    finally:
        _release(lease)


@contextmanager
def folder_lock(folder: str | Path, wait: bool = True, holder: str = "another process") -> Iterator[None]:
    """Hold the lock of ``folder`` (its lock file :data:`FOLDER_LOCK`, deleted on release) for the block.

    It holds across the nodes of a shared filesystem; a killed holder's lock is broken at once on its own
    host and expires :data:`STALE_AFTER_S` after its last heartbeat elsewhere (see the module docstring).

    Args:
        folder: an existing folder.
        wait: block until the lock is free; False raises at once when another process holds it.
        holder: who holds the lock, for the message.

    Raises:
        FolderInUseError: ``wait`` is False and the folder is locked, or this thread holds its lock already.
    """

    def refuse(who: str) -> str:
        return f"{folder} is being written by {holder} ({who}); wait for it to finish or use another folder"

    with lock_file(Path(folder) / FOLDER_LOCK, wait, refuse):
        yield


# --- sealed archives ---------------------------------------------------------------------------------------

#: Length of a seal: the hex SHA-256 of the archive before it, stored as the zip comment.
SEAL_BYTES = 64
_END_RECORD = b"PK\x05\x06"  # a zip's end of central directory record: 22 bytes, then the comment


def sealed_archive(archive: bytes) -> bytes:
    """Seal a zip archive that has no comment (as ``numpy.savez`` writes it): its comment becomes the hex
    SHA-256 of every byte before it, the comment length in the end record included.

    Raises:
        RecordFormatError: ``archive`` does not end with a zip end record without a comment.
    """
    if archive[-22:-18] != _END_RECORD or archive[-2:] != b"\x00\x00":
        raise RecordFormatError("the archive to seal does not end with a zip end record without a comment")
    body = archive[:-2] + SEAL_BYTES.to_bytes(2, "little")
    return body + hashlib.sha256(body).hexdigest().encode()


def read_sealed_archive(data: bytes, where: str | Path, sealed: str = "every byte before it",
                        remedy: str = "restore the file") -> bytes:
    """The archive that :func:`sealed_archive` sealed into ``data`` (without its seal), or an error.

    Args:
        data: the bytes of a sealed file.
        where: the file, for the message.
        sealed: what the seal covers, for the message.
        remedy: what the user can do, for the message.

    Raises:
        RecordFormatError: the seal does not match (an edited or corrupt file), or it seals no zip archive.
    """
    body, seal = data[:-SEAL_BYTES], data[-SEAL_BYTES:]
    if len(data) <= SEAL_BYTES or hashlib.sha256(body).hexdigest().encode() != seal:
        raise RecordFormatError(
            f"{where} fails its checksum: the file was edited or is corrupt (its SHA-256 seal over {sealed} "
            f"does not match); {remedy}"
        )
    if body[-22:-18] != _END_RECORD or body[-2:] != SEAL_BYTES.to_bytes(2, "little"):
        raise RecordFormatError(f"{where} is sealed but is not a sealed zip archive")
    return body[:-2] + b"\x00\x00"
