"""What every entry point does around its job: check the config, seed, write the resolved config, build the loggers."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Mapping

import lightning
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.io import write_text


def start_run(cfg: DictConfig, keys: Mapping[str, Key] | None = None, write: bool = True) -> Path:
    """Check the config's typed ``keys`` (before anything is written), seed everything and, with ``write``, write
    the resolved config as ``config.yaml`` into the run's output folder.

    A config that fails its checks leaves no run behind: the output folder Hydra made for it is removed again when
    it holds nothing but Hydra's own log."""
    out = Path(cfg.output_dir)
    try:
        check_config(cfg, keys or {})
    except ValueError:
        remove_unused_run_folder(out)
        raise
    lightning.seed_everything(cfg.seed, workers=True, verbose=False)
    if write:
        write_config(cfg)
    return out


def write_config(cfg: DictConfig) -> Path:
    """The resolved config as ``<output_dir>/config.yaml`` (atomically)."""
    return write_text(Path(cfg.output_dir) / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))


def run_folder_contents(out: Path) -> list[str]:
    """What ``out`` holds besides Hydra's own bookkeeping (its job log and ``.hydra``)."""
    if not out.is_dir():
        return []
    return sorted(p.name for p in out.iterdir() if not (p.name == ".hydra" or (p.suffix == ".log" and p.is_file())))


def remove_unused_run_folder(out: Path) -> None:
    """Remove ``out`` if it holds nothing but Hydra's bookkeeping (a run that failed before writing anything)."""
    if out.is_dir() and not run_folder_contents(out):
        shutil.rmtree(out, ignore_errors=True)


def make_loggers(cfg: DictConfig) -> list:
    """Lightning loggers from the ``logger`` group (an empty list for ``logger=none``)."""
    if not cfg.get("logger"):
        return []
    return [instantiate(c) for c in cfg.logger.values() if c is not None and "_target_" in c]


def log_metrics(loggers: list, metrics: dict) -> None:
    for lg in loggers:
        lg.log_metrics(metrics)
        lg.finalize("success")
