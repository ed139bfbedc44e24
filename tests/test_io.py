"""Locks that hold across processes and machines, and writes that are never half done (pushtorch.io).

Real processes and real files only: lockers are separate Python processes driven over a pipe, killed with
SIGKILL or stopped with SIGSTOP; a lock "of another host" is the lock file such a host writes, aged with
``os.utime``; atomic writers are forked and killed mid-write.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from pushtorch.errors import FolderInUseError, RecordFormatError
from pushtorch.io import (
    FOLDER_LOCK,
    atomic_write_bytes,
    folder_lock,
    lock_file,
    read_sealed_archive,
    sealed_archive,
    temporary_files,
)

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(os.name != "posix", reason="SIGKILL, SIGSTOP and fork")


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


#: A process that takes and releases a folder's lock when told to, one command a line on stdin:
#: ``try`` (wait=False), ``wait`` (wait=True), ``release``, ``turns N`` (N times: wait for the lock, enter
#: a critical section that a second holder would find occupied, leave it).
_LOCKER = r"""
import json, os, sys, time, warnings
from pathlib import Path
import pushtorch.io as pio
from pushtorch.errors import FolderInUseError

folder = Path(sys.argv[1])
pio.HEARTBEAT_S = float(sys.argv[2])
held = None


def say(*words):
    print(*words, flush=True)


say("ready")
for line in sys.stdin:
    command = line.split()
    if command[0] in ("try", "wait"):
        block = pio.folder_lock(folder, wait=command[0] == "wait", holder="the locker")
        try:
            block.__enter__()
        except FolderInUseError as exc:
            say("refused", exc)
            continue
        held = block
        say("held", json.loads((folder / pio.FOLDER_LOCK).read_text())["token"])
    elif command[0] == "release":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            held.__exit__(None, None, None)
        say("released", *[str(w.message) for w in caught])
    elif command[0] == "turns":
        inside = folder / "inside"
        outcome = "turns done"
        for turn in range(int(command[1])):
            with pio.folder_lock(folder, holder="the other locker"):
                try:
                    os.close(os.open(inside, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:  # the other process is inside too
                    outcome = f"two holders at turn {turn}"
                    break
                time.sleep(0.002)
                os.unlink(inside)
        say(outcome)
"""


class Locker:
    """A locker process and the lines it prints."""

    def __init__(self, script: Path, folder: Path, heartbeat_s: float = 5.0):
        self.process = subprocess.Popen([sys.executable, str(script), str(folder), str(heartbeat_s)], env=_env(),
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(line.strip())

    def send(self, command: str) -> None:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()

    def expect(self, timeout: float = 120.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                return self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.process.poll() is not None:
                    try:
                        return self.lines.get(timeout=1.0)  # its last words, still being read
                    except queue.Empty:
                        pass
                    raise AssertionError(f"the locker ended (status {self.process.returncode})") from None
        raise AssertionError(f"the locker said nothing in {timeout} s")

    def silent_for(self, seconds: float) -> bool:
        try:
            line = self.lines.get(timeout=seconds)
        except queue.Empty:
            return True
        self.lines.put(line)
        return False

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()


@pytest.fixture
def lockers(tmp_path):
    script = tmp_path / "locker.py"
    script.write_text(_LOCKER)
    started: list[Locker] = []

    def start(folder: Path, heartbeat_s: float = 5.0) -> Locker:
        locker = Locker(script, folder, heartbeat_s)
        started.append(locker)
        return locker

    yield start
    for locker in started:
        locker.close()


def _token(folder: Path) -> str:
    return json.loads((folder / FOLDER_LOCK).read_text())["token"]


def _lock_of(folder: Path, host: str, pid: int, age_s: float) -> Path:
    """The lock file a holder ``pid`` on ``host`` writes, its last heartbeat ``age_s`` ago."""
    path = folder / FOLDER_LOCK
    path.write_text(json.dumps({"host": host, "pid": pid, "started": "2024-05-01T08:00:00Z",
                                "token": uuid.uuid4().hex}))
    then = time.time() - age_s
    os.utime(path, (then, then))
    return path


def _dead_pid() -> int:
    """The pid of a process of this host that has ended (and been reaped)."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


# --- two live processes ----------------------------------------------------------------------------------

def test_two_processes_hold_a_folder_one_at_a_time(tmp_path, lockers):
    folder = tmp_path / "pushes"
    folder.mkdir()
    first, second = lockers(folder), lockers(folder)
    assert first.expect() == "ready" and second.expect() == "ready"
    first.send("try")
    held = first.expect()
    assert held.startswith("held ")
    second.send("try")
    refused = second.expect()
    assert refused.startswith("refused ") and "is being written by the locker" in refused
    assert f"pid {first.process.pid} on " in refused, refused
    second.send("wait")
    assert second.silent_for(1.5), "the second process took a lock the first one holds"
    first.send("release")
    assert first.expect() == "released"
    taken = second.expect()
    assert taken.startswith("held ") and taken != held
    assert _token(folder) == taken.split()[1]
    second.send("release")
    assert second.expect() == "released"
    assert not (folder / FOLDER_LOCK).exists()  # a released lock leaves no file


def test_two_processes_never_hold_a_folder_together(tmp_path, lockers):
    folder = tmp_path / "pushes"
    folder.mkdir()
    both = [lockers(folder), lockers(folder)]
    for locker in both:
        assert locker.expect() == "ready"
    for locker in both:
        locker.send("turns 40")
    for locker in both:
        assert locker.expect() == "turns done"  # a second holder in the critical section ends the locker
    assert sorted(p.name for p in folder.iterdir()) == []


def test_this_thread_taking_its_own_lock_again_is_refused_at_once(tmp_path):
    with folder_lock(tmp_path, holder="a run"):
        for wait in (False, True):  # waiting would never end
            with pytest.raises(FolderInUseError, match="being written by a run .*this thread holds the lock"):
                with folder_lock(tmp_path, wait=wait, holder="a run"):
                    pass
        refusal: list[BaseException] = []

        def other_thread():
            try:
                with folder_lock(tmp_path, wait=False):
                    pass
            except FolderInUseError as exc:
                refusal.append(exc)

        thread = threading.Thread(target=other_thread)
        thread.start()
        thread.join()
        assert len(refusal) == 1 and f"pid {os.getpid()}" in str(refusal[0])
    with folder_lock(tmp_path, wait=False):
        pass


# --- dead holders ----------------------------------------------------------------------------------------

def test_a_killed_holders_lock_is_broken_at_once_on_its_host(tmp_path, lockers):
    folder = tmp_path / "pushes"
    folder.mkdir()
    holder = lockers(folder)
    assert holder.expect() == "ready"
    holder.send("try")
    assert holder.expect().startswith("held ")
    holder.process.send_signal(signal.SIGKILL)
    holder.process.wait()
    assert (folder / FOLDER_LOCK).exists()  # left behind by the killed process
    start = time.monotonic()
    with folder_lock(folder, wait=False):
        assert _token(folder) != ""
    assert time.monotonic() - start < 2.0
    assert sorted(p.name for p in folder.iterdir()) == []


def test_a_lock_from_another_host_is_broken_only_when_its_heartbeat_is_old(tmp_path):
    _lock_of(tmp_path, "a-node-that-is-gone", 4242, age_s=10.0)
    with pytest.raises(FolderInUseError, match=r"pid 4242 on a-node-that-is-gone since 2024-05-01T08:00:00Z, "
                                               r"last heartbeat 1\d s ago"):
        with folder_lock(tmp_path, wait=False):
            pass
    assert (tmp_path / FOLDER_LOCK).exists()
    _lock_of(tmp_path, "a-node-that-is-gone", 4242, age_s=3600.0)
    with folder_lock(tmp_path, wait=False):
        assert "a-node-that-is-gone" not in (tmp_path / FOLDER_LOCK).read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_lock_of_this_host_with_a_live_pid_and_an_old_heartbeat_is_stale(tmp_path):
    # a reused pid: the process lives, but no heartbeat for longer than the timeout
    _lock_of(tmp_path, socket.gethostname(), os.getppid(), age_s=3600.0)
    with folder_lock(tmp_path, wait=False):
        pass


def test_unreadable_lock_files_are_respected_until_they_expire(tmp_path):
    path = tmp_path / FOLDER_LOCK
    path.write_bytes(b"")  # as its creator leaves it between the create and the write
    with pytest.raises(FolderInUseError, match="still being written"):
        with folder_lock(tmp_path, wait=False):
            pass
    os.utime(path, (time.time() - 3600,) * 2)
    with folder_lock(tmp_path, wait=False):
        pass


def test_the_heartbeat_keeps_a_lock_alive_and_a_stopped_holder_loses_it(tmp_path, lockers):
    folder = tmp_path / "pushes"
    folder.mkdir()
    holder = lockers(folder, heartbeat_s=0.1)
    assert holder.expect() == "ready"
    holder.send("try")
    token = holder.expect().split()[1]
    lock = folder / FOLDER_LOCK
    os.utime(lock, (time.time() - 3600,) * 2)
    time.sleep(0.5)
    assert time.time() - lock.stat().st_mtime < 5.0  # refreshed by the holder's heartbeat
    with pytest.raises(FolderInUseError):  # a live holder keeps it, beyond any timeout of its heartbeat
        with lock_file(lock, wait=False, stale_after=1.0):
            pass
    holder.process.send_signal(signal.SIGSTOP)  # alive, but no heartbeat
    try:
        time.sleep(1.5)
        with lock_file(lock, wait=False, stale_after=1.0):
            mine = _token(folder)
            assert mine != token
            holder.process.send_signal(signal.SIGCONT)
            holder.send("release")  # the holder that lost its lock must not remove this one
            released = holder.expect()
            assert released.startswith("released ") and "was taken over" in released
            assert _token(folder) == mine
    finally:
        holder.process.send_signal(signal.SIGCONT)
    assert not lock.exists()


# --- breaking one stale lock, many contenders ------------------------------------------------------------

_CONTENDER = r"""
import os, sys, time
from pathlib import Path
from pushtorch.errors import FolderInUseError
from pushtorch.io import folder_lock

folder, control, me = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
rounds, count = int(sys.argv[4]), int(sys.argv[5])
print("ready", flush=True)
for r in range(rounds):
    go = control / f"go-{r}"
    while not go.exists():
        time.sleep(0.0005)
    try:
        with folder_lock(folder, wait=False):
            (control / f"result-{r}-{me}").write_text("won")
            deadline = time.monotonic() + 60
            while len(list(control.glob(f"result-{r}-*"))) < count and time.monotonic() < deadline:
                time.sleep(0.001)  # held until every contender has tried
    except FolderInUseError:
        (control / f"result-{r}-{me}").write_text("refused")
    (control / f"done-{r}-{me}").write_text("")
"""


def test_contenders_breaking_one_stale_lock_exactly_one_wins(tmp_path):
    folder, control = tmp_path / "pushes", tmp_path / "control"
    folder.mkdir()
    control.mkdir()
    script = tmp_path / "contender.py"
    script.write_text(_CONTENDER)
    rounds, count = 24, 3
    contenders = [subprocess.Popen([sys.executable, str(script), str(folder), str(control), str(i), str(rounds),
                                    str(count)], env=_env(), stdout=subprocess.PIPE, text=True)
                  for i in range(count)]
    try:
        for c in contenders:
            assert c.stdout.readline().strip() == "ready"
        for r in range(rounds):
            if r % 2:  # killed on this host
                _lock_of(folder, socket.gethostname(), _dead_pid(), age_s=0.0)
            else:  # a node that died long ago
                _lock_of(folder, "a-node-that-is-gone", 4242, age_s=3600.0)
            (control / f"go-{r}").touch()
            deadline = time.monotonic() + 120
            while len(list(control.glob(f"done-{r}-*"))) < count:
                assert time.monotonic() < deadline and all(c.poll() is None for c in contenders), f"round {r}"
                time.sleep(0.005)
            results = sorted((control / f"result-{r}-{i}").read_text() for i in range(count))
            assert results == ["refused"] * (count - 1) + ["won"], (r, results)
            assert sorted(p.name for p in folder.iterdir()) == [], r  # no claim, probe or lock left
    finally:
        for c in contenders:
            c.kill()
            c.wait()


# --- forked children -------------------------------------------------------------------------------------

_FORKER = r"""
import json, multiprocessing, os, sys, threading
from pathlib import Path
from pushtorch.errors import FolderInUseError
from pushtorch.io import FOLDER_LOCK, folder_lock

folder = Path(sys.argv[1])


def try_lock(_):
    try:
        with folder_lock(folder, wait=False):
            return "took it"
    except FolderInUseError:
        return "refused"


with folder_lock(folder):
    token = json.loads((folder / FOLDER_LOCK).read_text())["token"]
    pid = os.fork()
    if pid == 0:
        print("child", try_lock(None), len(threading.enumerate()), flush=True)
    else:
        os.waitpid(pid, 0)  # the child left this block too: it released nothing
        print("after child", json.loads((folder / FOLDER_LOCK).read_text())["token"] == token, flush=True)
        with multiprocessing.get_context("fork").Pool(2) as pool:
            print("pool", *pool.map(try_lock, range(4)), flush=True)
        print("after pool", json.loads((folder / FOLDER_LOCK).read_text())["token"] == token, flush=True)
if pid == 0:
    os._exit(0)
print("released", not (folder / FOLDER_LOCK).exists(), flush=True)
"""


def test_forked_children_neither_hold_nor_release_their_parents_lock(tmp_path):
    script = tmp_path / "forker.py"
    script.write_text(_FORKER)
    result = subprocess.run([sys.executable, str(script), str(tmp_path)], env=_env(), capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        "child refused 1",  # refused like any other process, and no heartbeat thread of its own
        "after child True",
        "pool refused refused refused refused",
        "after pool True",
        "released True",
    ], result.stdout + result.stderr


# --- atomic writes ---------------------------------------------------------------------------------------

def test_a_killed_atomic_writer_never_leaves_a_partial_file(tmp_path):
    target = tmp_path / "model.npz"
    payloads = [bytes([65 + i]) * (4 << 20) for i in range(2)]
    for attempt in range(8):
        pid = os.fork()
        if pid == 0:  # the writer: alternate the two payloads until killed
            try:
                for k in range(10**9):
                    atomic_write_bytes(target, payloads[k % 2])
            finally:
                os._exit(1)
        deadline = time.monotonic() + 0.05 + 0.03 * attempt
        while time.monotonic() < deadline:  # a concurrent reader only ever sees a whole file
            try:
                data = target.read_bytes()
            except FileNotFoundError:
                continue
            assert data in payloads
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        assert not target.exists() or target.read_bytes() in payloads
        for orphan in temporary_files(tmp_path, target.name):  # what the killed writer may leave: not the file
            assert orphan != target
            orphan.unlink()
    assert target.read_bytes() in payloads


# --- sealed archives -------------------------------------------------------------------------------------

def test_a_sealed_archive_round_trips_and_refuses_any_edited_byte(tmp_path):
    import io
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("a.txt", "pushes")
    plain = buffer.getvalue()
    sealed = sealed_archive(plain)
    assert len(sealed) == len(plain) + 64
    assert read_sealed_archive(sealed, "x.npz") == plain
    with zipfile.ZipFile(io.BytesIO(sealed)) as archive:  # still a zip: the seal is its comment
        assert archive.read("a.txt") == b"pushes"
    for at in (0, len(plain) // 2, len(sealed) - 1):
        edited = bytearray(sealed)
        edited[at] ^= 1
        with pytest.raises(RecordFormatError, match="x.npz fails its checksum"):
            read_sealed_archive(bytes(edited), "x.npz")
    with pytest.raises(RecordFormatError, match="without a comment"):
        sealed_archive(sealed)  # sealed once only
