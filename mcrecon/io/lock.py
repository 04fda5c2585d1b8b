"""The sample log's writer lock: one run or resume writes a log at a time.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import threading
import time
from pathlib import Path


from ..errors import InputError

__all__ = ['log_lock', 'lock_path', 'live_writer']

# ------------------------------------------------------------------ exclusive writers
# A writer holds an exclusive flock on ``LOG.lock`` (holding its PID) for as long as it
# writes: the adaptive driver for a whole run, append_log & co. for one call (re-entrant
# within a process).  The kernel releases a flock when its holder dies, so the lock file a
# killed run leaves behind is simply taken over.
_HELD: dict = {}  # realpath of the log -> [fd, depth]
_HELD_GUARD = threading.RLock()


def lock_path(path) -> Path:
    """The lock file of a log: ``LOG.lock`` beside it."""
    return Path(str(path) + ".lock")


def _read_pid(fd) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None


def _acquire(path, wait: float) -> int:
    lp = lock_path(path)
    deadline = time.monotonic() + wait
    while True:
        try:
            lp.parent.mkdir(parents=True, exist_ok=True)  # a new log's directory (write_log makes it too)
            fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise _err(path, "lock", f"cannot create the lock file {lp} ({exc.strerror or exc}); a run needs "
                       "a writable directory beside its log") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pid = _read_pid(fd)
            os.close(fd)
            if time.monotonic() < deadline:
                time.sleep(0.02)
                continue
            who = f"process {pid}" if pid else "another process"
            raise _err(path, "lock", f"the log is being written by {who} (lock {lp}): a second run or resume "
                       "on it is refused; wait for that run to end or stop it") from None
        try:  # a holder that released unlinks the file: we must hold the file that is at lp
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        # A PID left in the file belongs to a killed holder (a live one would hold the flock).
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return fd


@contextlib.contextmanager
def log_lock(path, *, wait: float = 0.5):
    """Hold the exclusive writer lock of a log (``LOG.lock``, with this process's PID).

    Re-entrant within a process.  Another process's lock is waited for at
    most ``wait`` seconds, then refused with an :class:`InputError` naming
    the holder's PID; a lock file left by a killed process is taken over.
    """
    key = os.path.realpath(path)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            held[1] += 1
        else:
            _HELD[key] = [_acquire(path, wait), 1]
    try:
        yield
    finally:
        with _HELD_GUARD:
            held = _HELD[key]
            held[1] -= 1
            if held[1] == 0:
                del _HELD[key]
                with contextlib.suppress(OSError):
                    os.unlink(lock_path(path))  # unlinked while locked: see _acquire
                os.close(held[0])


def live_writer(path) -> int | None:
    """PID of another live process holding the writer lock of ``path`` (-1 if unknown), or None."""
    if os.path.realpath(path) in _HELD:
        return None
    try:
        fd = os.open(lock_path(path), os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return _read_pid(fd) or -1
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _err(path, field, problem):
    return InputError(str(path), field, problem)
