"""What a training run reports about itself, whatever logger it has: ``results.md``, ``results.json`` and
``loss.png`` in the run folder, rewritten (atomically) at the end of every epoch.

:class:`TrainingReport` is a Lightning callback (``kpflow/conf/callbacks/default.yaml``). Each epoch's row holds the
mean training loss over its batches and the validation loss of the epoch's validation (``val/loss``, when the model
logs one and validation ran); ``results.md`` adds the best epoch by validation loss. A resumed run
(``resume=true``) reads the rows of the epochs it has already done from ``results.json`` and goes on.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import lightning
from lightning.pytorch.callbacks import Callback

from kpflow.utils.io import save_figure, write_json, write_text

log = logging.getLogger(__name__)  # one line per epoch: the console and the run's log file


def _loss(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"


class TrainingReport(Callback):
    """Write ``results.md``, ``results.json`` and ``loss.png`` into ``output_dir`` after every epoch (module
    docstring)."""

    def __init__(self, output_dir: str) -> None:
        self.out = Path(output_dir)
        self.rows: list[dict] = []
        self._losses: list[float] = []
        self._val: float | None = None

    def on_train_start(self, trainer: lightning.Trainer, pl_module) -> None:  # after a checkpoint was restored
        path = self.out / "results.json"
        if path.is_file():  # a resumed run: the epochs already done
            done = json.loads(path.read_text()).get("epochs", [])
            self.rows = [r for r in done if isinstance(r, dict) and r.get("epoch", math.inf) < trainer.current_epoch]

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._losses, self._val = [], None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        if loss is not None:
            self._losses.append(float(loss))

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        value = trainer.callback_metrics.get("val/loss")
        if not trainer.sanity_checking and value is not None:
            self._val = float(value)

    def on_train_epoch_end(self, trainer: lightning.Trainer, pl_module) -> None:
        if not trainer.is_global_zero:
            return
        train = sum(self._losses) / len(self._losses) if self._losses else None
        self.rows.append(
            {"epoch": trainer.current_epoch, "train_loss": train, "val_loss": self._val, "steps": trainer.global_step}
        )
        self.write(type(pl_module).__name__)
        log.info(
            "epoch %d (%d steps): training loss %s, validation loss %s",
            trainer.current_epoch,
            trainer.global_step,
            _loss(train),
            _loss(self._val),
        )

    def write(self, model: str) -> None:
        """``results.json``, ``results.md`` and ``loss.png`` from the rows so far."""
        self.out.mkdir(parents=True, exist_ok=True)
        vals = [r for r in self.rows if r["val_loss"] is not None]
        best = min(vals, key=lambda r: r["val_loss"]) if vals else None
        write_json(
            self.out / "results.json",
            {"model": model, "epochs": self.rows, "best_epoch": None if best is None else best["epoch"]},
        )
        lines = [f"# Training of {model}", "", f"{len(self.rows)} epochs, {self.rows[-1]['steps']} steps."]
        if best is not None:
            lines.append(f"Best validation loss {best['val_loss']:.4g} at epoch {best['epoch']} (checkpoints/).")
        lines += ["", "![loss](loss.png)", "", "| epoch | training loss (mean) | validation loss |", "|---|---|---|"]
        lines += [f"| {r['epoch']} | {_loss(r['train_loss'])} | {_loss(r['val_loss'])} |" for r in self.rows]
        write_text(self.out / "results.md", "\n".join(lines) + "\n")
        self._plot()

    def _plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.2))
        for key, label in (("train_loss", "training (mean over the epoch)"), ("val_loss", "validation")):
            points = [(r["epoch"], r[key]) for r in self.rows if r[key] is not None]
            if points:
                ax.plot(*zip(*points), marker="o", ms=3, label=label)
        ax.set_xlabel("epoch")
        ax.set_ylabel("loss")
        ax.legend()
        fig.tight_layout()
        save_figure(fig, self.out / "loss.png", dpi=120)
        plt.close(fig)
