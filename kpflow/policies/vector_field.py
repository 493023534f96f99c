"""A first-order motion policy xdot = g(x): a gpytorch GP regression from positions to velocities, fitted on
(transported) demonstrations -- the paper's policy refit on transported data (Eq. 6). Far from the data the GP
mean, hence the velocity, falls to zero, so the robot stops rather than extrapolating."""

from __future__ import annotations

import torch

from kpflow.maps.gp_regression import GPRegressor


class GPVectorField:
    """xdot = g(x) with g the posterior mean of a GP fitted on (position, velocity) pairs.

    Args:
        max_points: subsample the training pairs evenly to at most this many (exact GP cost grows as N^3).
    """

    def __init__(self, max_points: int = 400, iters: int = 15) -> None:
        self.max_points = max_points
        self.gp = GPRegressor(iters=iters, noise=1e-2)

    def fit(self, positions: torch.Tensor, velocities: torch.Tensor) -> "GPVectorField":
        x, v = positions.reshape(-1, positions.shape[-1]), velocities.reshape(-1, positions.shape[-1])
        if x.shape[0] > self.max_points:
            idx = torch.linspace(0, x.shape[0] - 1, self.max_points).round().long()
            x, v = x[idx], v[idx]
        self.gp.fit(x, v)
        return self

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Velocity at ``x [..., D]``."""
        with torch.no_grad():
            return self.gp.mean(x.reshape(-1, x.shape[-1])).reshape(x.shape)

    def rollout(self, start: torch.Tensor, dt: float, steps: int) -> torch.Tensor:
        """Euler integration from ``start [D]``: ``[steps + 1, D]``."""
        xs = [start]
        for _ in range(steps):
            xs.append(xs[-1] + dt * self(xs[-1][None])[0])
        return torch.stack(xs)
