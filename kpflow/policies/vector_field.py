"""A first-order motion policy xdot = g(x) fitted on (transported) demonstrations -- the paper's policy refit on
transported data (Eq. 6):

    g(x) = k (x* - x) + f(x),   f ~ GP fitted on the residuals v_i - k (x* - x_i)   (gpytorch),

a linear attractor to the goal x* plus a GP correction. Near the demonstrations the GP reproduces them; far from
them f -> 0 and the robot heads straight to the goal instead of stalling or drifting (a stable prior, the
policy's counterpart of the maps' zero-transport prior). Without a goal (``goal=None``) the prior is zero."""

from __future__ import annotations

import torch

from kpflow.maps.gp_regression import GPRegressor


class GPVectorField:
    """xdot = k (x* - x) + GP mean (module docstring).

    Args:
        gain: attractor gain k in 1/s.
        max_points: subsample the training pairs evenly to at most this many (exact GP cost grows as N^3).
    """

    def __init__(self, gain: float = 2.0, max_points: int = 400, iters: int = 15) -> None:
        self.gain, self.max_points = gain, max_points
        self.gp = GPRegressor(iters=iters, noise=1e-2)
        self.goal: torch.Tensor | None = None

    def prior(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x) if self.goal is None else self.gain * (self.goal.to(x) - x)

    def fit(
        self, positions: torch.Tensor, velocities: torch.Tensor, goal: torch.Tensor | None = None
    ) -> "GPVectorField":
        d = positions.shape[-1]
        x, v = positions.reshape(-1, d), velocities.reshape(-1, d)
        if x.shape[0] > self.max_points:
            idx = torch.linspace(0, x.shape[0] - 1, self.max_points).round().long()
            x, v = x[idx], v[idx]
        self.goal = goal
        self.gp.fit(x, v - self.prior(x))
        return self

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Velocity at ``x [..., D]``."""
        flat = x.reshape(-1, x.shape[-1])
        with torch.no_grad():
            return (self.prior(flat) + self.gp.mean(flat)).reshape(x.shape)
