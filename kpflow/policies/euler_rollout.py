"""Rolling out a first-order motion policy xdot = g(x)."""

from __future__ import annotations

from typing import Callable

import torch


def euler_rollout(
    field: Callable[[torch.Tensor], torch.Tensor], start: torch.Tensor, dt: float, steps: int
) -> torch.Tensor:
    """x_{k+1} = x_k + dt g(x_k) from ``start [D]``: ``[steps + 1, D]``."""
    xs = [start]
    with torch.no_grad():
        for _ in range(steps):
            xs.append(xs[-1] + dt * field(xs[-1]))
    return torch.stack(xs)
