"""Train: ``python train.py experiment=frames_field``. Builds the datamodule, model and trainer from ``conf/``,
checkpoints the best and last epochs under the run folder, and with ``run_name=NAME resume=true`` continues
that run from its last checkpoint."""

from pathlib import Path

import hydra
from hydra.utils import instantiate
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig

from kpflow.utils.run import make_loggers, start_run


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> dict:
    out = start_run(cfg)
    last = out / "checkpoints" / "last.ckpt"
    if cfg.resume and not last.exists():
        raise FileNotFoundError(f"resume=true but {last} does not exist: pass the run_name of an earlier run")
    datamodule = instantiate(cfg.data)
    model = instantiate(cfg.model)
    checkpoints = ModelCheckpoint(dirpath=out / "checkpoints", monitor="val/loss", save_top_k=2, save_last=True, filename="epoch{epoch:03d}", auto_insert_metric_name=False)
    trainer = instantiate(cfg.trainer, logger=make_loggers(cfg) or False, callbacks=[checkpoints], default_root_dir=out)
    trainer.fit(model, datamodule=datamodule, ckpt_path=str(last) if cfg.resume else None)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    print(f"checkpoints: {Path(checkpoints.dirpath)}  best: {checkpoints.best_model_path}  metrics: {metrics}")
    return metrics


if __name__ == "__main__":
    main()
