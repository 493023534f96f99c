"""A neural first-order motion policy xdot = g(x) trained with Lightning: an MLP on standardised positions,
mean-squared velocity error. Its standardisation statistics live in buffers, so a checkpoint is all a
deployment needs (``load_checkpoint(NeuralVectorField, path)`` from :mod:`kpflow.utils.checkpoint`)."""

from __future__ import annotations

import lightning
import torch
from torch import nn


class NeuralVectorField(lightning.LightningModule):
    def __init__(
        self, dim: int = 2, hidden: int = 128, depth: int = 3, lr: float = 3e-3, weight_decay: float = 1e-5
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        layers, width = [], dim
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        self.net = nn.Sequential(*layers, nn.Linear(width, dim))
        self.register_buffer("x_mean", torch.zeros(dim))
        self.register_buffer("x_std", torch.ones(dim))
        self.register_buffer("v_std", torch.ones(dim))

    def setup(self, stage: str) -> None:
        """Take the standardisation from the training data (once; a resumed run keeps the checkpoint's)."""
        if stage != "fit" or self.trainer is None or bool((self.x_std != 1).any()):
            return
        x, v = self.trainer.datamodule.train_set.tensors
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(1e-6))
        self.v_std.copy_(v.std(0).clamp_min(1e-6))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Velocity at positions ``x [..., dim]``."""
        return self.net((x - self.x_mean) / self.x_std) * self.v_std

    def _loss(self, batch) -> torch.Tensor:
        x, v = batch
        return ((self(x) - v) / self.v_std).square().sum(-1).mean()

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        loss = self._loss(batch)
        self.log("train/loss", loss, prog_bar=True, on_epoch=True, on_step=False)
        return loss

    def validation_step(self, batch, batch_idx: int) -> None:
        self.log("val/loss", self._loss(batch), prog_bar=True)

    def configure_optimizers(self):
        return torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
