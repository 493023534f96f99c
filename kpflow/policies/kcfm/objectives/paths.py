"""The straight conditional probability path with ``sigma = 0`` (Lipman et al. 2023, "Flow Matching for Generative
Modeling", Sec. 4.1, eqs. 20-23; Tong et al. 2024, eqs. 14-15 with ``sigma = 0``): between a noise row ``x0`` and a
data row ``x1`` at time ``t``,

    x_t = t x1 + (1 - t) x0,        u_t(x_t | x0, x1) = x1 - x0.

I-CFM, OT-CFM and reflow regress the network on ``u_t`` at ``x_t``; they differ only in how ``x0`` and ``x1`` are
paired.
"""

from __future__ import annotations

import torch


def straight_path(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(x_t, u_t)`` of the module docstring for rows ``x0, x1 [B, ...]`` at times ``t [B]``."""
    if t.shape != (len(x0),) or x0.shape != x1.shape:
        raise ValueError(
            f"straight_path needs x0 and x1 of one shape and t [B]; got {tuple(x0.shape)}, {tuple(x1.shape)}, {tuple(t.shape)}"
        )
    s = t.reshape(-1, *([1] * (x0.dim() - 1)))
    return s * x1 + (1 - s) * x0, x1 - x0
