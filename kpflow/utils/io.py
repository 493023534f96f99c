"""Atomic writes: write to a temporary sibling, then rename it over the target, so a crash never leaves a
half-written file or folder behind.

Temporaries are named ``.<name>.<pid>.<random>.tmp<suffix>`` beside the target (the target's suffix last, for
writers that choose a format by it). A process killed mid-write (SIGKILL, power
off) cannot remove its own; the next write of the same target removes every such leftover whose process is gone
(:func:`remove_stale_temporaries`), and never one that a live process is still writing.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from kpflow.utils.file_lock import FileLock, LockHeld

TMP_SUFFIX = ".tmp"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries of ``path`` (``.<name>.<pid>.*.tmp<suffix>``, files or folders) left by dead
    processes; returns what was removed."""
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    prefix, suffix = f".{path.name}.", TMP_SUFFIX + path.suffix
    for entry in path.parent.iterdir():
        if not (entry.name.startswith(prefix) and entry.name.endswith(suffix)):
            continue
        pid = entry.name[len(prefix) :].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid() or _pid_alive(int(pid)):
            continue
        shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() and not entry.is_symlink() else entry.unlink(
            missing_ok=True
        )
        removed.append(entry)
    return removed


def _temporary_name(path: Path) -> dict[str, Any]:
    return dict(prefix=f".{path.name}.{os.getpid()}.", suffix=TMP_SUFFIX + path.suffix, dir=path.parent)


#: the errors of a write that found no room: a full disk, a full quota, the file-size limit
NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def no_room(e: OSError, path: Path) -> OSError:
    """``e``, a write that found no room (:data:`NO_ROOM`), as one line naming ``path`` and the fix."""
    return OSError(e.errno, f"{path} was not written: no room left ({e.strerror}); nothing reached its name and what it held "
                            "before is intact. Free space (or raise the quota or file-size limit) and run again")  # fmt: skip


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary file path next to ``path``; on success it replaces ``path``, on error it is removed (a write
    that found no room is re-raised naming ``path``: :func:`no_room`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    try:
        fd, tmp = tempfile.mkstemp(**_temporary_name(path))
    except OSError as e:
        if e.errno in NO_ROOM:
            raise no_room(e, path) from None
        raise
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes it 0600; results are meant to be read by others
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno in NO_ROOM:
            raise no_room(e, path) from None
        raise


def _renameat2(a: Path, b: Path, flag: int) -> bool:
    """Linux ``renameat2(a, b, flag)``; False where the kernel or filesystem does not support ``flag``."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), flag) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS):  # filesystem or kernel without the flag
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (``RENAME_EXCHANGE``); False where unsupported."""
    return _renameat2(a, b, 2)


def _publish_new(tmp: Path, path: Path) -> None:
    """Rename ``tmp`` to ``path``, which must not exist: ``RENAME_NOREPLACE`` where the kernel has it, so a ``path``
    another process made meanwhile is never replaced (``FileExistsError`` naming it)."""
    try:
        if _renameat2(tmp, path, 1):
            return
    except FileExistsError:
        pass
    else:
        if not path.exists():
            os.replace(tmp, path)
            return
    raise FileExistsError(f"{path} was written by another process while this one wrote it; it was left as it is and "
                          "nothing of this run was kept (write elsewhere, or replace it with overwrite)")  # fmt: skip


@contextmanager
def atomic_dir(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder next to ``path``; on success it becomes ``path``, on error it is removed.

    With ``overwrite`` an existing ``path`` is swapped with the new folder in one step (``renameat2`` with
    ``RENAME_EXCHANGE``) and removed after, so a crash at any point leaves at ``path`` either the old folder or the
    new one, never a mix and never neither. (Where the kernel cannot swap, the old folder is renamed aside first:
    a crash between the two renames then leaves ``path`` missing and the old folder as a temporary.) Without
    ``overwrite`` an existing ``path`` raises ``FileExistsError`` before anything is written, and the new folder
    never replaces one that appeared meanwhile (``RENAME_NOREPLACE``).

    One writer at a time: the lock ``.<name>.lock`` beside ``path`` (:class:`~kpflow.utils.file_lock.FileLock`,
    removed at the end) is held throughout, and a second writer of the same ``path`` is refused at once
    (:class:`~kpflow.utils.file_lock.LockHeld`, naming the path and the holder's pid) instead of both writing and one
    result silently winning.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock_path = path.parent / f".{path.name}.lock"
    try:
        lock = FileLock(lock_path, wait=0)
    except LockHeld as e:
        who = f"process {e.holder}" if e.holder else "another process"
        raise LockHeld(
            f"{path} is being written by {who} ({lock_path.name} is held): wait for it to finish, or write elsewhere",
            e.path,
            e.holder,
        ) from None
    try:
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists already")
        remove_stale_temporaries(path)
        tmp = Path(tempfile.mkdtemp(**_temporary_name(path)))
        try:
            yield tmp
            os.chmod(tmp, 0o755)  # mkdtemp makes it 0700
            if not overwrite:
                _publish_new(tmp, path)
            elif not (path.exists() and _exchange(tmp, path)):
                aside = Path(tempfile.mkdtemp(**_temporary_name(path))) if path.exists() else None
                if aside is not None:
                    os.replace(path, aside / "old")
                os.replace(tmp, path)
                if aside is not None:
                    shutil.rmtree(aside, ignore_errors=True)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)  # the new folder on error, the old one after a swap
    finally:
        lock_path.unlink(missing_ok=True)  # while still held: a waiter never takes a lock on a removed file
        lock.release()


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def publish(path: str | os.PathLike, lines: list[str]) -> str:
    """A benchmark's report: the ``lines`` joined, printed, and written atomically to ``path``; returns the text."""
    text = "\n".join(lines) + "\n"
    print(text)
    write_text(path, text)
    return text


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    return write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def save_figure(fig, path: str | os.PathLike, **kwargs) -> Path:
    """``fig.savefig`` through a temporary file (the format follows ``path``'s suffix)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".") or "png", **kwargs)
    return Path(path)
