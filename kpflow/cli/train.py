"""Train: ``kpflow-train experiment=kcfm data.path=STORE_OR_LEROBOT_DATASET`` (``python train.py ...`` from a
checkout). Builds the datamodule, model and trainer from ``kpflow/conf/``,
checkpoints the best and last epochs under the run folder (``kpflow/conf/callbacks``), and with ``run_name=NAME resume=true`` continues
that run from its last checkpoint.

A run folder belongs to one run: a run started into a folder another live run holds is refused at once, naming
that run's pid (:func:`~kpflow.utils.run.claim_run_folder`, taken before anything else looks at the folder), reusing
a finished or dead run's folder without ``resume=true`` is refused, and the resolved config is written only once
training has started (a resume that fails, e.g. on a size mismatch, leaves the run's config as it was).
Checkpoints are read with ``torch.load(weights_only=True)`` (:class:`~kpflow.utils.checkpoint.SafeCheckpointIO`),
so resuming never runs code from a checkpoint file."""

import logging
from pathlib import Path

import hydra
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, open_dict

from kpflow.policies.config import PolicyConfig
from kpflow.utils.checkpoint import SafeCheckpointIO, read_checkpoint
from kpflow.utils.config_checks import SEED, TRAINER_KEYS, Key
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.run import make_loggers, run_folder_contents, start_run, write_config

log = logging.getLogger(__name__)  # the console and the run's train.log (Hydra's job logging)
KEYS = {"seed": SEED, "resume": Key(bool), "run_name": Key(str), **TRAINER_KEYS}


class WriteConfig(Callback):
    """Write the run's resolved config once training starts (after a resumed checkpoint has been restored)."""

    def __init__(self, cfg: DictConfig) -> None:
        self.cfg = cfg

    def on_train_start(self, trainer, pl_module) -> None:
        if trainer.is_global_zero:
            write_config(self.cfg)


def fill_from_data(model: DictConfig, datamodule) -> None:
    """Fill the model keys the config leaves null (``n_keypoints: null``...) with what the data says
    (``datamodule.model_dims()``: the keypoint layout and action size read from the store or dataset), in place, so
    that the run's config.yaml records them."""
    wanted = [key for key in getattr(datamodule, "MODEL_DIMS", ()) if key in model and model[key] is None]
    if not wanted:  # the data is not read before training unless the config asks for it
        return
    dims = datamodule.model_dims()
    with open_dict(model):
        for key in wanted:
            model[key] = dims[key]


def record_layout(model, layout) -> None:
    """Have ``model`` (a policy: it has a ``policy_config``) record the task's keypoint ``layout`` in every checkpoint
    it writes, so that loading one needs no task to know its keypoints; ``ValueError`` when the model's keypoints and
    actions are not the layout's."""
    if not hasattr(model, "policy_config"):
        return
    have = (int(model.hparams.n_keypoints), int(model.hparams.keypoint_dim), int(model.hparams.action_dim))
    if have != layout.shape:
        raise ValueError(
            f"the model is sized for {have[0]} keypoints in {have[1]}-D and {have[2]}-D actions, but the task's layout has "
            f"{layout.n_keypoints} keypoints in {layout.keypoint_dim}-D and {layout.action_dim}-D actions: set model.n_keypoints "
            f"(and keypoint_dim, action_dim) to the task's, or leave task= out"
        )
    model.policy_config = PolicyConfig(layout=layout.record())


def check_resumable(model, last: Path) -> None:
    """Raise ``ValueError`` before anything is written if ``last``'s weights do not fit ``model`` (resuming with
    another model config than the run's)."""
    saved = read_checkpoint(last)["state_dict"]
    own = model.state_dict()
    missing, extra = sorted(set(own) - set(saved)), sorted(set(saved) - set(own))
    shapes = [
        f"{k}: checkpoint {list(saved[k].shape)} vs model {list(own[k].shape)}"
        for k in own
        if k in saved and saved[k].shape != own[k].shape
    ]
    if missing or extra or shapes:
        what = "; ".join(
            shapes[:3] + [f"missing {missing[:3]}"] * bool(missing) + [f"unexpected {extra[:3]}"] * bool(extra)
        )
        raise ValueError(
            f"{last} does not fit the configured model ({what}): resume with the run's own model config (see its config.yaml)"
        )


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="train")
@command
def main(cfg: DictConfig) -> dict:
    out = start_run(cfg, KEYS, write=False)  # claims the folder (rank 0): no other run passes the check below with us
    if "model_checkpoint" not in cfg.get("callbacks", {}):
        raise ValueError(
            "callbacks.model_checkpoint is missing: train.py checkpoints every run (see kpflow/conf/callbacks/default.yaml)"
        )
    last = Path(cfg.callbacks.model_checkpoint.dirpath) / "last.ckpt"
    if cfg.resume and not last.exists():
        raise FileNotFoundError(f"resume=true but {last} does not exist: pass the run_name of an earlier run")
    # DDP's other processes re-run this script into the same folder (rank 0 has claimed and checked it): only rank 0
    # claims it (start_run) and checks it
    if not cfg.resume and rank_zero_only.rank == 0 and (used := run_folder_contents(out)):
        raise FileExistsError(
            f"{out} already holds a run ({', '.join(used)}): pass resume=true to continue it, or choose another run_name"
        )
    datamodule = instantiate(cfg.data)
    fill_from_data(cfg.model, datamodule)
    model = instantiate(
        cfg.model, _convert_="all"
    )  # plain lists and dicts as hparams: checkpoints load with weights_only
    if cfg.get("task") is not None:
        record_layout(model, instantiate(cfg.task).policy_layout)
    if cfg.resume:
        check_resumable(model, last)
    elif fit_processor := getattr(model, "fit_processor", None):  # a policy's statistics, from the data it trains on
        fit_processor(datamodule.training_chunks())
    callbacks = {name: instantiate(node) for name, node in cfg.callbacks.items()}
    checkpoints = callbacks["model_checkpoint"]
    trainer = instantiate(
        cfg.trainer,
        logger=make_loggers(cfg) or False,
        callbacks=[*callbacks.values(), WriteConfig(cfg)],
        plugins=[SafeCheckpointIO()],
        default_root_dir=out,
    )
    trainer.fit(model, datamodule=datamodule, ckpt_path=str(last) if cfg.resume else None)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    log.info("checkpoints: %s  best: %s  metrics: %s", Path(checkpoints.dirpath), checkpoints.best_model_path, metrics)
    if (Path(cfg.output_dir) / "results.md").is_file():  # the training report (kpflow/conf/callbacks/default.yaml)
        log.info("results: %s  plot: %s", Path(cfg.output_dir) / "results.md", Path(cfg.output_dir) / "loss.png")
    return metrics


if __name__ == "__main__":
    main()
