"""Shared pieces of the neural map families: a smooth MLP and the regression fit."""

from __future__ import annotations

import torch
from torch import nn


def smooth_mlp(d_in: int, d_out: int, hidden: int, layers: int, zero_last: bool = True) -> nn.Sequential:
    """tanh MLP (smooth, so the map's Jacobian is continuous); last layer zeroed for an identity start."""
    mods: list[nn.Module] = []
    width = d_in
    for _ in range(layers):
        mods += [nn.Linear(width, hidden), nn.Tanh()]
        width = hidden
    last = nn.Linear(width, d_out)
    if zero_last:
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
    return nn.Sequential(*mods, last)


def anchor_points(d: int, like: torch.Tensor, n: int = 64, radius: float = 3.0, seed: int = 0) -> torch.Tensor:
    """Fixed points spread uniformly over [-radius, radius]^d (normalised units) where the zero-transport prior
    is enforced."""
    g = torch.Generator().manual_seed(seed)
    return ((torch.rand(n, d, generator=g, dtype=torch.float64) * 2 - 1) * radius).to(like)


def fit_regression(
    module: nn.Module,
    f,
    x: torch.Tensor,
    y: torch.Tensor,
    anchors: torch.Tensor,
    anchor_targets: torch.Tensor,
    prior_weight: float,
    steps: int,
) -> list[float]:
    """Minimise mean |f(x) - y|^2 + prior_weight * mean |f(a) - a_target|^2 over ``module``'s parameters with
    full-batch L-BFGS (deterministic; stops when the loss stops changing). Returns the loss after each
    evaluation."""
    params = [p for p in module.parameters()]
    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=steps,
        tolerance_grad=1e-10,
        tolerance_change=1e-14,
        history_size=20,
        line_search_fn="strong_wolfe",
    )
    losses: list[float] = []

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = (f(x) - y).square().sum(-1).mean()
        if prior_weight > 0:
            loss = loss + prior_weight * (f(anchors) - anchor_targets).square().sum(-1).mean()
        loss.backward()
        losses.append(loss.item())
        return loss

    module.train()
    with torch.enable_grad():
        opt.step(closure)
    module.eval()
    for p in params:
        p.requires_grad_(False)
    return losses
