"""Training the learned map: a LightningModule over keypoint pairs (``python train.py experiment=pusht_map``).

A batch is a :class:`KeypointPairs`: B pairs ``(S, T)`` with M query points ``Q`` and where a reference map fitted
on each pair (ILWR, :mod:`kpflow.data.keypoint_pairs`) carries them, ``Q*``. In the normalised coordinates of
:func:`~kpflow.maps.conditional_flow.normalise` (``a``, ``b``, ``q = n(A Q + t)``, ``q* = n(Q*)``) the loss is

    L = mean_i |G(a_i) - b_i|^2                       (interpolation of the keypoints)
      + w_distill * mean_j |G(q_j) - q*_j|^2           (regularity: agree with the reference map between them)
      + w_far * mean_k |G(f_k) - f_k|^2                (regularity: the alignment alone far from them),

with ``f`` fixed points on the ring ``far_radius <= |f| <= 2 far_radius`` (normalised units; the keypoints' RMS
radius is 1). The regularisers choose among the many maps that interpolate the keypoints: ILWR's answer between
them, the alignment's far away. On Push-T the distillation term measured worse (``results/maps_learned.md``), so
its weight is 0 by default: the couplings' own structure, volume-preserving shears unless the gated MLP scales, keeps
the map smooth.

Validation logs ``val/loss`` (checkpoints monitor it) and the keypoint residual ``val/residual_px``: each batch's
median over its pairs of ``max_i |phi(s_i) - t_i|`` in the pairs' own units, averaged over the batches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import lightning
import torch

from kpflow.geometry.alignment import KINDS, fit_affine
from kpflow.maps.conditional_flow import ConditionalFlow, normalise


@dataclass
class KeypointPairs:
    """B keypoint pairs with query points: ``source, target [B, N, D]``, ``queries, query_targets [B, M, D]``."""

    source: torch.Tensor
    target: torch.Tensor
    queries: torch.Tensor
    query_targets: torch.Tensor

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, items) -> "KeypointPairs":
        return KeypointPairs(self.source[items], self.target[items], self.queries[items], self.query_targets[items])


def far_points(dim: int, n: int, radius: float, seed: int = 0) -> torch.Tensor:
    """``n`` fixed points with uniform directions and radii in ``[radius, 2 radius]`` ``[n, dim]``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, dim, generator=g)
    return d / d.norm(dim=-1, keepdim=True) * (radius * (1 + torch.rand(n, 1, generator=g)))


class MapModule(lightning.LightningModule):
    """Trains a :class:`~kpflow.maps.conditional_flow.ConditionalFlow` on keypoint pairs (module docstring).

    Args:
        n_keypoints, dim: the keypoint sets' shape (every pair of a task has the same).
        alignment: the alignment the flow sits on (``rigid``, ``similarity``, ``affine``, ``translation``, ``none``).
        n_layers, hidden, context, encoder_depth, s_max, coupling_depth: the flow's size (:class:`ConditionalFlow`).
        distill_weight, far_weight, far_radius: the regularisers of the loss.
        lr, weight_decay: AdamW, with a cosine decay over the run.
    """

    def __init__(
        self,
        n_keypoints: int,
        dim: int = 2,
        alignment: str = "rigid",
        n_layers: int = 16,
        hidden: int = 64,
        context: int = 128,
        encoder_depth: int = 2,
        s_max: float = 2.0,
        coupling_depth: int = 1,
        distill_weight: float = 0.0,
        far_weight: float = 0.1,
        far_radius: float = 3.0,
        lr: float = 5e-4,
        weight_decay: float = 1e-6,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if alignment not in (*KINDS, "none"):
            raise ValueError(f"unknown alignment {alignment!r}; choose one of {(*KINDS, 'none')}")
        for name, w in (("distill_weight", distill_weight), ("far_weight", far_weight), ("far_radius", far_radius)):
            if not (math.isfinite(w) and w >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {w}")
        self.save_hyperparameters()
        self.flow = ConditionalFlow(
            n_keypoints, dim, n_layers, hidden, context, encoder_depth, s_max, seed, coupling_depth
        )
        self.register_buffer("far", far_points(dim, 64, far_radius, seed), persistent=False)

    def losses(self, batch: KeypointPairs) -> dict[str, torch.Tensor]:
        """The loss terms of the module docstring (``distill`` only with a positive weight) and the per-pair
        keypoint residual ``[B]`` (``residual``)."""
        src, tgt = batch.source, batch.target
        if self.hparams.alignment == "none":
            aligned_src, aligned_q = src, batch.queries
        else:
            A, t = fit_affine(src, tgt, self.hparams.alignment)
            aligned_src = src @ A.transpose(1, 2) + t[:, None]
            aligned_q = batch.queries @ A.transpose(1, 2) + t[:, None]
        a, b, m, sigma = normalise(aligned_src, tgt)
        cond = self.flow.condition(a, b)
        ga = self.flow(a, cond)
        out = {"keypoints": (ga - b).square().sum(-1).mean()}
        far = self.far.to(a).expand(len(a), -1, -1)
        out["far"] = (self.flow(far, cond) - far).square().sum(-1).mean()
        h = self.hparams
        out["loss"] = out["keypoints"] + h.far_weight * out["far"]
        if h.distill_weight > 0:  # (off by default: no flow pass over the queries then)
            if batch.queries.shape[1] == 0:
                raise ValueError(
                    "distill_weight > 0 needs query points: set the data module's n_queries (e.g. data.n_queries=32)"
                )
            q, q_target = (aligned_q - m) / sigma, (batch.query_targets - m) / sigma
            out["distill"] = (self.flow(q, cond) - q_target).square().sum(-1).mean()
            out["loss"] = out["loss"] + h.distill_weight * out["distill"]
        out["residual"] = ((ga - b).norm(dim=-1) * sigma[..., 0]).amax(-1)
        return out

    def training_step(self, batch: KeypointPairs, batch_idx: int) -> torch.Tensor:
        out = self.losses(batch)
        for k in ("loss", "keypoints", "distill", "far"):
            if k in out:
                self.log(f"train/{k}", out[k], prog_bar=k == "loss", batch_size=len(batch))
        return out["loss"]

    def validation_step(self, batch: KeypointPairs, batch_idx: int) -> None:
        out = self.losses(batch)
        self.log("val/loss", out["loss"], prog_bar=True, batch_size=len(batch))
        self.log("val/residual_px", out["residual"].median(), prog_bar=True, batch_size=len(batch))

    def configure_optimizers(self):
        opt = torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        total = max(1, int(self.trainer.estimated_stepping_batches))
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=total)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}
