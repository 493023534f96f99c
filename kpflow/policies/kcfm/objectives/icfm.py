"""I-CFM: independent conditional flow matching with the straight (optimal-transport) path and ``sigma = 0``
(Lipman et al. 2023, "Flow Matching for Generative Modeling", Sec. 4.1, eqs. 20-23; the I-CFM of Tong et al. 2024).

With ``x0 ~ N(0, I)`` drawn independently of the data chunk ``x1`` and ``t ~ U(0, 1)``:

    x_t = t x1 + (1 - t) x0,        u_t(x_t | x0, x1) = x1 - x0,        L = E || v(x_t, t, c) - u_t ||^2.

Sampling integrates ``dx/dt = v(x, t, c)`` from ``t = 0`` to 1 with a fixed-step solver (:mod:`.solvers`: Euler,
midpoint or Heun, in a budget of network calls). The interpolant and its velocity are :func:`.paths.straight_path`.
"""

from __future__ import annotations

import torch

from .base import Denoiser, TrainingTarget, identity_index, rand, randn_like
from .paths import straight_path
from .solvers import SOLVERS, integrate


class ICFM:
    """Independent-coupling conditional flow matching (module docstring)."""

    solvers = SOLVERS
    n_times = 1
    time_scale = 1000.0

    def pair(
        self, x0: torch.Tensor, x1: torch.Tensor, generator: torch.Generator | None, cond: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The coupling of noise and data rows: independent, so every row keeps its own."""
        return x0, identity_index(x1)

    def training_target(
        self, x1: torch.Tensor, cond: torch.Tensor | None = None, generator: torch.Generator | None = None, net=None
    ) -> TrainingTarget:
        x0, index = self.pair(randn_like(x1, generator), x1, generator, cond)
        t = rand(len(x1), x1, generator)
        x_t, u_t = straight_path(x0, x1[index], t)
        return TrainingTarget(x_t, t, u_t, index)

    def sample(self, net: Denoiser, noise: torch.Tensor, steps: int, solver: str = "euler") -> torch.Tensor:
        return integrate(net, noise, steps, solver)
