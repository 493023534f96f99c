"""MeanFlow: a network of *average* velocities over an interval, so that one step goes from noise to data (Geng et
al. 2025, "Mean Flows for One-step Generative Modeling", eqs. 3, 6, 9-10 and Alg. 1; the one-step policy MP1 of
Sheng et al. 2025 trains it on action chunks). Trained from scratch, no teacher.

With the straight path of :mod:`.icfm` (noise at ``t = 0``, data at 1: ``x_t = t x1 + (1 - t) x0``, conditional
velocity ``v = x1 - x0``), the average velocity over ``[s, t]`` from the point reached at the start ``s`` is

    u(x_s, s, t) = 1 / (t - s) int_s^t v(x_tau, tau) dtau,       so that  x_t = x_s + (t - s) u(x_s, s, t).

Differentiating ``(t - s) u(x_s, s, t) = x_t - x_s`` along the trajectory in ``s`` gives the MeanFlow identity (the
paper's eq. 6 with its time reversed: its ``t = 1`` is noise)

    u(x_s, s, t) = v(x_s, s) + (t - s) d/ds u(x_s, s, t),     d/ds u = v . d_x u + d_s u,

and the regression target (eqs. 9-10), with the total derivative computed as one Jacobian-vector product of the
network in the tangent ``(v, 1, 0)`` of its inputs ``(x, s, t)`` (``torch.func.jvp``) and held fixed:

    u_tgt = v + (t - s) (v . d_x u_theta + d_s u_theta),     L = E || u_theta(x_s, s, t, c) - sg(u_tgt) ||^2.

``s < t`` are the sorted pair of two ``U(0, 1)`` draws, and for a fraction ``flow_fraction`` of the rows ``s = t``
(then ``u_tgt = v``: plain flow matching, the paper's 75 %). The network takes the two times as ``t [B, 2] = (s, t)``,
embedded smoothly (``time_scale = 1``: with the flows' ``sin(1000 s w)`` the time derivative in the target is a
thousand times the velocity's size, and training stalls, on the tests' walking data too).

Sampling with ``steps`` calls walks the grid ``tau_k = k / steps`` by average velocities,
``x <- x + (tau_{k+1} - tau_k) u(x, tau_k, tau_{k+1})``, exact at any ``steps`` for an exact ``u``; one step is
``x1 = x0 + u(x0, 0, 1)``.
"""

from __future__ import annotations

import torch

from .base import Denoiser, Network, TrainingTarget, identity_index, rand, randn_like


class MeanFlow:
    """Average-velocity flow matching (module docstring).

    Args:
        flow_fraction: the fraction of training rows with ``s = t`` (instantaneous velocity), in [0, 1].
    """

    solvers = ("euler",)  # steps of the average velocity over each interval
    n_times = 2
    time_scale = 1.0  # d/ds of sin(1000 s w) would put a factor ~1000 into the target (tests/test_few_step.py)

    def __init__(self, flow_fraction: float = 0.75) -> None:
        if not 0.0 <= flow_fraction <= 1.0:
            raise ValueError(f"flow_fraction must be in [0, 1]; got {flow_fraction!r}")
        self.flow_fraction = float(flow_fraction)

    def times(self, n: int, like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """``[n, 2]`` interval ends ``(s, t)``, ``s <= t``: two sorted ``U(0, 1)`` draws, equal for a ``flow_fraction``
        of the rows."""
        a, b, flow = rand(n, like, generator), rand(n, like, generator), rand(n, like, generator) < self.flow_fraction
        s, t = torch.minimum(a, b), torch.maximum(a, b)
        return torch.stack([torch.where(flow, t, s), t], -1)

    def training_target(
        self,
        x1: torch.Tensor,
        cond: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        net: Network | None = None,
    ) -> TrainingTarget:
        if net is None:
            raise ValueError("MeanFlow's target depends on the network being trained: pass net(x, t, c)")
        x0 = randn_like(x1, generator)
        st = self.times(len(x1), x1, generator)
        s, t = st[:, 0], st[:, 1]
        x_s = s[:, None, None] * x1 + (1 - s[:, None, None]) * x0
        v = x1 - x0

        def average_velocity(x: torch.Tensor, s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return net(x, torch.stack([s, t], -1), cond)

        with torch.no_grad():
            _, du_ds = torch.func.jvp(average_velocity, (x_s, s, t), (v, torch.ones_like(s), torch.zeros_like(t)))
        target = v + (t - s)[:, None, None] * du_ds
        return TrainingTarget(x_s, st, target.detach(), identity_index(x1))

    def sample(self, net: Denoiser, noise: torch.Tensor, steps: int, solver: str = "euler") -> torch.Tensor:
        if solver != "euler":
            raise ValueError(f"MeanFlow steps by average velocities (solver='euler'); got {solver!r}")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"network calls must be an integer >= 1; got {steps!r}")
        x = noise
        for k in range(steps):
            s, t = k / steps, (k + 1) / steps
            st = torch.tensor([s, t], device=x.device, dtype=x.dtype).expand(len(x), 2)
            x = x + (t - s) * net(x, st)
        return x
