"""An exclusive inter-process lock on a file (``fcntl.flock``), released when closed or when its process dies."""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path


class FileLock:
    """Hold ``flock(LOCK_EX)`` on ``path`` (created if missing); the holder's pid is written into the file so a
    waiter can say who holds it.

    Args:
        path: the lock file.
        wait: seconds to wait for another holder (0: fail at once, None: wait for ever).
        on_wait: called once, with the holder's pid (or None), when the lock is taken and we start waiting.

    Raises:
        TimeoutError: the lock was still held after ``wait`` seconds, or is held by this process through another
            handle (waiting would deadlock); the message names the file and the holder.
    """

    POLL_S = 0.05

    def __init__(self, path: str | os.PathLike, wait: float | None = 0.0, on_wait=None) -> None:
        self.path = Path(path)
        self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = None if wait is None else time.monotonic() + wait
        waiting = False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                holder = self.holder()
                if holder == os.getpid():  # another handle of this very process: waiting would never end
                    self.release()
                    raise TimeoutError(f"{self.path} is held by this process already, through another open handle: close that first") from None
                if deadline is not None and time.monotonic() >= deadline:
                    self.release()
                    who = f"process {holder}" if holder else "another process"
                    after = f" after {wait} s" if wait else ""
                    raise TimeoutError(f"{self.path} is held by {who}{after}: wait for it to finish, or wait longer") from None
                if not waiting and on_wait is not None:
                    on_wait(holder)
                waiting = True
                time.sleep(self.POLL_S)
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, str(os.getpid()).encode(), 0)

    def holder(self) -> int | None:
        """The pid written by the current holder (None if unknown)."""
        try:
            text = self.path.read_text().strip()
        except OSError:
            return None
        return int(text) if text.isdigit() else None

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None
