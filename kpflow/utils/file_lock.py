"""An exclusive inter-process lock on a file (``fcntl.flock``), released when closed or when its process dies.

The lock file is opened without following a symbolic link (``O_NOFOLLOW``) and must be a regular file with one name
(link count 1): a symbolic or hard link planted in its place (to a file elsewhere, or to one of the store's own files,
as a tar can carry) is refused by name before anything is written, never written through (:class:`UnsafeLockFile`).

A lock belongs to the process that took it: a child forked while it is held (a pool of workers) closes its copy of
the descriptor at once, so that the lock is released when its owner dies, not when the last of its children does.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import time
import weakref
from pathlib import Path

_HELD: "weakref.WeakSet[FileLock]" = weakref.WeakSet()  # this process's held locks


def _drop_in_child() -> None:
    """After ``fork``, in the child: close the inherited descriptors (``os.close`` only: ``flock(LOCK_UN)`` would
    release the parent's lock too, since both descriptors share one open file)."""
    for lock in list(_HELD):
        if lock._fd is not None:
            os.close(lock._fd)
            lock._fd = None
    _HELD.clear()


os.register_at_fork(after_in_child=_drop_in_child)


class LockHeld(TimeoutError):
    """A :class:`FileLock` could not be taken: ``holder`` (a pid, or None when unknown) held ``path``."""

    def __init__(self, message: str, path: Path, holder: int | None) -> None:
        super().__init__(message)
        self.path, self.holder = path, holder


class UnsafeLockFile(ValueError):
    """A lock file that is a symbolic link, a hard link (more than one name) or not a regular file: taking it would
    write through it."""


def _open_lock_file(path: Path) -> int:
    """``path`` opened read-write (created if missing) without following a link; :class:`UnsafeLockFile` for a link,
    a file with other names (a hard link) or anything but a regular file. Nothing is written before these checks
    (``O_CREAT`` without ``O_TRUNC`` leaves an existing file as it is)."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UnsafeLockFile(
                f"{path} is a symbolic link: a lock file is never followed (it would write into what it points to); remove the link"
            ) from None
        raise
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise UnsafeLockFile(f"{path} is not a regular file: remove it (a lock file holds the holder's pid only)")
    if info.st_nlink != 1:
        os.close(fd)
        raise UnsafeLockFile(
            f"{path} is a hard link ({info.st_nlink} names for one file): a lock file is never written through to "
            "another file; remove it (rm, which removes this name only)"
        )
    return fd


class FileLock:
    """Hold ``flock(LOCK_EX)`` on ``path`` (created if missing); the holder's pid is written into the file so a
    waiter can say who holds it.

    Args:
        path: the lock file.
        wait: seconds to wait for another holder (0: fail at once, None: wait for ever).
        on_wait: called once, with the holder's pid (or None), when the lock is taken and we start waiting.

    Raises:
        UnsafeLockFile: ``path`` is a symbolic link, a hard link or not a regular file (nothing is written).
        LockHeld: (a ``TimeoutError``) the lock was still held after ``wait`` seconds, or is held by this process
            through another handle (waiting would deadlock); the message names the file and the holder, and so do
            its ``path`` and ``holder``.
    """

    POLL_S = 0.05

    def __init__(self, path: str | os.PathLike, wait: float | None = 0.0, on_wait=None) -> None:
        self.path = Path(path)
        self._fd: int | None = _open_lock_file(self.path)
        deadline = None if wait is None else time.monotonic() + wait
        waiting = False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                if self._still_named():
                    break
                os.close(self._fd)  # its holder removed it as it let go (end of a run): lock the file now at path
                self._fd = None
                self._fd = _open_lock_file(self.path)
                continue
            except BlockingIOError:
                holder = self.holder()
                if holder == os.getpid():  # another handle of this very process: waiting would never end
                    self.release()
                    raise LockHeld(
                        f"{self.path} is held by this process already, through another open handle: close that first",
                        self.path,
                        holder,
                    ) from None
                if deadline is not None and time.monotonic() >= deadline:
                    self.release()
                    who = f"process {holder}" if holder else "another process"
                    after = f" after {wait} s" if wait else ""
                    raise LockHeld(
                        f"{self.path} is held by {who}{after}: wait for it to finish, or wait longer", self.path, holder
                    ) from None
                if not waiting and on_wait is not None:
                    on_wait(holder)
                waiting = True
                time.sleep(self.POLL_S)
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, str(os.getpid()).encode(), 0)
        _HELD.add(self)

    def _still_named(self) -> bool:
        """Whether the file locked is still the one at ``path`` (a holder removes its lock file before letting go)."""
        try:
            named = os.stat(self.path, follow_symlinks=False)
        except FileNotFoundError:
            return False
        held = os.fstat(self._fd)
        return (named.st_dev, named.st_ino) == (held.st_dev, held.st_ino)

    def holder(self) -> int | None:
        """The pid written by the current holder (None if unknown)."""
        try:
            text = self.path.read_text().strip()
        except OSError:
            return None
        return int(text) if text.isdigit() else None

    def release(self) -> None:
        _HELD.discard(self)
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None
