"""One run at a time per session output folder: a lock file that names its holder.

``<output root>/.roomcap/lock`` stays in the folder; a run holds an exclusive ``flock`` on it while it
writes the session's outputs and writes into it who holds it (pid, host, start time, command). The
kernel releases the ``flock`` when the holder ends in any way (a crash, ``kill -9``), so a lock left by a
killed run is stale by construction: the next run takes it over and says so. A second run on a locked
session refuses with :class:`SessionLocked` (naming the holder's pid, host, start time and command), or
with ``wait=True`` waits until the holder is done.

Ray tasks and local worker processes take the same lock (it is taken in
:func:`roomcap.pipeline.runner.process_session`). On network file systems ``flock`` is as good as the file
system's locking (NFSv4 locks across hosts).

>>> import tempfile
>>> root = Path(tempfile.mkdtemp())
>>> with session_lock(root) as lock:
...     holder(root).pid == lock.holder.pid == os.getpid()
True
>>> holder(root) is None
True
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shlex
import socket
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from roomcap.core.errors import RoomcapError
from roomcap.core.redact import redact

log = logging.getLogger(__name__)

LOCK_NAME = "lock"
POLL_S = 0.2
REFUSE_AFTER_S = 0.5  # how long a refusing run retries first (another run's holder() probe takes a moment)


class SessionLocked(RoomcapError, RuntimeError):
    """The session is being processed by another run; the message names it and what to do."""


@dataclass(frozen=True)
class LockHolder:
    pid: int
    host: str
    started: str  # ISO 8601, UTC
    command: str

    def describe(self) -> str:
        when = self.started.replace("T", " ").split(".")[0].removesuffix("+00:00")
        return f"pid {self.pid} on {self.host}, started {when} UTC ({self.command})"


@dataclass(frozen=True)
class HeldLock:
    holder: LockHolder  # this run
    took_over: LockHolder | None = None  # the run that ended without releasing the lock, if any

    def took_over_message(self, root: str | os.PathLike[str]) -> str:
        if self.took_over is None:
            return ""
        who = self.took_over.describe()
        return f"{root}: took over the lock of a run that ended without releasing it ({who})"


def lock_path(root: str | os.PathLike[str]) -> Path:
    return Path(root) / ".roomcap" / LOCK_NAME


def _read(path: Path) -> LockHolder | None:
    try:
        d = json.loads(path.read_text() or "null")
        return LockHolder(int(d["pid"]), str(d["host"]), str(d["started"]), str(d["command"]))
    except (OSError, ValueError, TypeError, KeyError):
        return None


def holder(root: str | os.PathLike[str]) -> LockHolder | None:
    """The run that holds the session's lock now, or None when nobody does (a stale lock file is free)."""
    path = lock_path(root)
    if not path.exists():
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            for _ in range(10):  # the holder writes its name just after taking the lock
                h = _read(path)
                if h is not None:
                    return h
                time.sleep(0.01)
            return LockHolder(0, "?", "?", "a run that has not written its name yet")
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _message(root: Path, h: LockHolder | None) -> str:
    who = h.describe() if h is not None else "another run"
    kill = f" (kill {h.pid})" if h is not None and h.pid > 0 and h.host == socket.gethostname() else ""
    return (
        f"{root} is being processed by another run: {who}. Wait for it to finish, or rerun with --wait "
        f"to wait for it; if that run hangs, stop it{kill} and rerun (its finished stages are kept)."
    )


@contextmanager
def session_lock(
    root: str | os.PathLike[str],
    wait: bool = False,
    on_wait: Callable[[str], None] | None = None,
) -> Iterator[HeldLock]:
    """Hold the session's lock for the block; raises :class:`SessionLocked` when another run holds it
    (``wait=False``) or waits for it (``wait=True``, once calling ``on_wait(message)``, else logging it)."""
    root = Path(root)
    path = lock_path(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    locked = False
    try:
        told = False
        patience = time.monotonic() + REFUSE_AFTER_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                locked = True
                break
            except BlockingIOError:
                if not wait and time.monotonic() < patience:  # a moment's probe by holder() passes
                    time.sleep(0.05)
                    continue
                h = None
                for _ in range(10):  # the holder writes its name just after taking the lock
                    h = _read(path)
                    if h is not None:
                        break
                    time.sleep(0.01)
                if not wait:
                    raise SessionLocked(_message(root, h)) from None
                if not told:
                    msg = f"waiting: {_message(root, h).split('. Wait')[0]}"
                    (on_wait or log.warning)(msg)
                    told = True
                time.sleep(POLL_S)
        me = LockHolder(
            os.getpid(),
            socket.gethostname(),
            datetime.now(UTC).isoformat(timespec="seconds"),
            redact(shlex.join(sys.argv)),
        )
        held = HeldLock(me, _read(path))  # a name still in the file: a run that ended without releasing
        if held.took_over is not None:
            log.warning("%s", held.took_over_message(root))
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(asdict(me)).encode(), 0)
        os.fsync(fd)
        yield held
    finally:
        if locked:
            try:
                os.ftruncate(fd, 0)  # released cleanly: an empty file, so the next run sees no stale holder
            except OSError:
                pass
        os.close(fd)  # closing releases the flock
