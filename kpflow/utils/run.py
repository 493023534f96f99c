"""What every entry point does around its job: seed, write the resolved config, build the loggers."""

from __future__ import annotations

from pathlib import Path

import lightning
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.utils.io import write_text


def start_run(cfg: DictConfig) -> Path:
    """Seed everything and write the resolved config as ``config.yaml`` into the run's output folder."""
    lightning.seed_everything(cfg.seed, workers=True, verbose=False)
    out = Path(cfg.output_dir)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    return out


def make_loggers(cfg: DictConfig) -> list:
    """Lightning loggers from the ``logger`` group (an empty list for ``logger=none``)."""
    if not cfg.get("logger"):
        return []
    return [instantiate(c) for c in cfg.logger.values() if c is not None and "_target_" in c]


def log_metrics(loggers: list, metrics: dict) -> None:
    for lg in loggers:
        lg.log_metrics(metrics)
        lg.finalize("success")
