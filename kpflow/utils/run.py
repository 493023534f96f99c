"""What every entry point does around its job: check the config, claim the run folder, seed, write the resolved
config, build the loggers."""

from __future__ import annotations

import atexit
import os
import shutil
from pathlib import Path
from typing import Mapping

import lightning
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.file_lock import FileLock, LockHeld
from kpflow.utils.io import write_text

#: the run folder's lock file (:func:`claim_run_folder`)
RUN_LOCK = ".kpflow-run.lock"

_claimed: tuple[Path, FileLock] | None = None  # this process's run folder and the lock it holds on it


class RunFolderInUse(FileExistsError):
    """Another live process is running in the run folder."""


def start_run(cfg: DictConfig, keys: Mapping[str, Key] | None = None, write: bool = True) -> Path:
    """Check the config's typed ``keys`` (before anything is written), claim the run's output folder
    (:func:`claim_run_folder`), seed everything and, with ``write``, write the resolved config as ``config.yaml``
    into it.

    A config that fails its checks leaves no run behind: the output folder Hydra made for it is removed again when
    it holds nothing but Hydra's own log. A folder another live run holds is refused (:class:`RunFolderInUse`)
    before anything is written into it."""
    out = Path(cfg.output_dir)
    try:
        check_config(cfg, keys or {})
    except ValueError:
        remove_unused_run_folder(out)
        raise
    claim_run_folder(out)
    route_library_logs()
    lightning.seed_everything(cfg.seed, workers=True, verbose=False)
    if write:
        write_config(cfg)
    return out


def route_library_logs() -> None:
    """Let Lightning's messages (the trainer's set-up, why fitting stopped) reach the handlers Hydra gave the run, the
    console and the run's log file, instead of the console alone: Lightning gives its logger a handler of its own when
    it is imported before logging is configured, and stops it propagating."""
    import logging

    if not logging.getLogger().handlers:  # logging is not configured (not a Hydra run): leave Lightning's as it is
        return
    names = ["lightning", *(n for n in logging.root.manager.loggerDict if n.startswith("lightning."))]
    for name in names:
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            logger.removeHandler(handler)
        logger.propagate = True


def claim_run_folder(out: Path) -> None:
    """Make ``out`` (created if missing) this process's run folder: take the exclusive lock ``<out>/.kpflow-run.lock``
    (``flock``, :class:`~kpflow.utils.file_lock.FileLock`) without waiting, and hold it until the process ends or
    claims another folder (the next job of a sweep run in this process), when :func:`end_run` removes it (and the
    folder, if the run wrote nothing into it). Claiming the folder this process holds already does nothing.

    Raises :class:`RunFolderInUse`, naming the folder and the holder's pid, when another live process holds it; a
    run that died released its lock with its process, so its folder can be claimed again (``resume=true``, a
    re-run). Under DDP the processes other than rank 0 re-run the entry point into rank 0's folder: they claim
    nothing (rank 0 holds it for them)."""
    global _claimed
    if rank_zero_only.rank != 0:
        return
    if _claimed is not None and _claimed[0] == out.resolve():
        return
    out.mkdir(parents=True, exist_ok=True)
    try:
        lock = FileLock(out / RUN_LOCK, wait=0)
    except LockHeld as e:
        who = f"process {e.holder}" if e.holder else "another process"
        raise RunFolderInUse(
            f"{out} is in use by another run ({who}): wait for it to end, or give this run another folder "
            "(run_name=... or hydra.run.dir=...)"
        ) from None
    if _claimed is None:
        atexit.register(end_run)
    else:
        end_run()
    _claimed = (out.resolve(), lock)


def end_run() -> None:
    """Let go of this process's run folder (:func:`claim_run_folder`), however the run ended: its lock file is
    removed while still held, so a finished or failed run leaves none behind, and a run folder holding nothing but
    bookkeeping (a run that failed before its first result) goes too, unless it is the working folder or above it."""
    global _claimed
    if _claimed is None:
        return
    out, lock = _claimed
    _claimed = None
    try:
        (out / RUN_LOCK).unlink(missing_ok=True)
    finally:
        lock.release()
    here = Path.cwd().resolve()
    if out not in (here, *here.parents) and out.is_dir() and not run_folder_contents(out):
        shutil.rmtree(out, ignore_errors=True)
        remove_empty_parents(out)


def write_config(cfg: DictConfig) -> Path:
    """The resolved config as ``<output_dir>/config.yaml`` (atomically)."""
    return write_text(Path(cfg.output_dir) / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))


def run_folder_contents(out: Path) -> list[str]:
    """What ``out`` holds besides the bookkeeping of Hydra (its job log and ``.hydra``) and of the run lock."""
    if not out.is_dir():
        return []
    return sorted(
        p.name for p in out.iterdir() if not (p.name in (".hydra", RUN_LOCK) or (p.suffix == ".log" and p.is_file()))
    )


def remove_unused_run_folder(out: Path) -> None:
    """Remove ``out`` if it holds nothing but bookkeeping (a run that failed before writing anything) and no live
    run holds it (a run that has claimed it but not written yet keeps it), then the folders above it left empty
    (:func:`remove_empty_parents`)."""
    if not out.is_dir() or run_folder_contents(out):
        return
    try:
        lock = FileLock(out / RUN_LOCK, wait=0)
    except LockHeld:
        return
    try:
        if run_folder_contents(out):
            return
        shutil.rmtree(out, ignore_errors=True)
    finally:
        lock.release()
    remove_empty_parents(out)


def remove_empty_parents(out: Path) -> None:
    """Remove the folders above a removed run folder ``out`` that it leaves empty, up to the working folder (Hydra's
    ``outputs/<task>/``, made for that run alone)."""
    here = Path.cwd().resolve()
    for parent in out.resolve().parents:
        if parent == here or not parent.is_relative_to(here):
            return
        try:
            parent.rmdir()  # only an empty one
        except OSError:
            return


def abandon_run(out: Path) -> None:
    """A run that failed before its first result: the ``config.yaml`` it wrote goes, so that the run folder, holding
    nothing else, is removed when the run lets go of it (:func:`end_run`)."""
    (out / "config.yaml").unlink(missing_ok=True)


def wandb_disabled() -> bool:
    """True when the environment turns wandb off (``WANDB_MODE=disabled``)."""
    return os.environ.get("WANDB_MODE", "").strip().lower() == "disabled"


def make_loggers(cfg: DictConfig) -> list:
    """Lightning loggers from the ``logger`` group (an empty list for ``logger=none``); with ``WANDB_MODE=disabled``
    the wandb logger is left out, so nothing of wandb is written."""
    if not cfg.get("logger"):
        return []
    wanted = [c for c in cfg.logger.values() if c is not None and "_target_" in c]
    if wandb_disabled():
        wanted = [c for c in wanted if str(c._target_).rsplit(".", 1)[-1] != "WandbLogger"]
    return [instantiate(c) for c in wanted]


def log_metrics(loggers: list, metrics: dict) -> None:
    for lg in loggers:
        lg.log_metrics(metrics)
        lg.finalize("success")
