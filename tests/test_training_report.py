"""A training run reports itself (kpflow/eval/training_report.py): results.md, results.json and loss.png after
every epoch, whatever the logger, and a resumed run goes on from the epochs it had done."""

import json

import lightning

from kpflow.data.chunks import ChunkDataModule
from kpflow.eval.training_report import TrainingReport
from kpflow.policies.kcfm import KCFM
from kpflow.tasks.pusht.geometry import N_KEYPOINTS
from tests.helpers import walk_to_block_store


def _fit(tmp_path, epochs: int, ckpt_path=None):
    data = ChunkDataModule(tmp_path / "demos.zarr", horizon=8, batch_size=64, val_fraction=0.25)
    report = TrainingReport(str(tmp_path / "run"))
    trainer = lightning.Trainer(max_epochs=epochs, accelerator="cpu", logger=False, default_root_dir=tmp_path, callbacks=[report],
                                enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                                num_sanity_val_steps=1)  # fmt: skip
    lightning.seed_everything(0, verbose=False)
    model = KCFM(N_KEYPOINTS, horizon=8, network={"name": "unet", "down_dims": [16, 32], "time_dim": 16})
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data, ckpt_path=ckpt_path)
    return trainer


def test_every_epoch_is_reported_and_a_resumed_run_goes_on(tmp_path):
    walk_to_block_store(tmp_path / "demos.zarr")
    trainer = _fit(tmp_path, 2)
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    record = json.loads((tmp_path / "run" / "results.json").read_text())
    assert [r["epoch"] for r in record["epochs"]] == [0, 1] and record["model"] == "KCFM"
    assert all(r["train_loss"] > 0 and r["val_loss"] > 0 for r in record["epochs"])  # the sanity check is not an epoch
    assert record["best_epoch"] == min(record["epochs"], key=lambda r: r["val_loss"])["epoch"]
    table = (tmp_path / "run" / "results.md").read_text()
    assert "| epoch | training loss (mean) | validation loss |" in table and "Best validation loss" in table
    assert (tmp_path / "run" / "loss.png").stat().st_size > 1000
    _fit(tmp_path, 3, ckpt_path=tmp_path / "last.ckpt")  # resumed: epoch 2 only, after the two it had
    assert [r["epoch"] for r in json.loads((tmp_path / "run" / "results.json").read_text())["epochs"]] == [0, 1, 2]
