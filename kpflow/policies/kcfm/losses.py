"""The K-CFM's loss over chunks padded at an episode's end: only real steps count."""

from __future__ import annotations

import torch


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the steps where ``mask`` is True.

    ``pred, target [B, H, A]``, ``mask [B, H]`` (bool): ``sum_{b,h} m_bh ||pred_bh - target_bh||^2 / (A sum m)``;
    0 when no step is real. Masked-out steps contribute nothing, whatever their values (even NaN).
    """
    m = mask.to(pred.dtype)
    err = torch.where(mask[..., None], pred - target, torch.zeros((), dtype=pred.dtype, device=pred.device))
    return err.square().mean(-1).mul(m).sum() / m.sum().clamp_min(1.0)


def fill_padding(actions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``actions [B, H, A]`` with each masked-out step replaced by the latest real step before it (the first real
    step if none comes before), which is how :class:`~kpflow.data.chunks.ChunkDataset` pads past an episode's
    end. So the values stored at padded steps never reach the network: together with :func:`masked_mse`,
    padding does not affect training at all."""
    h = torch.arange(mask.shape[-1], device=mask.device).expand_as(mask)
    first = mask.to(torch.int64).argmax(-1, keepdim=True).expand_as(mask)
    idx = torch.where(mask, h, -1).cummax(-1).values
    idx = torch.where(idx < 0, first, idx)
    return actions.gather(1, idx[..., None].expand_as(actions))
