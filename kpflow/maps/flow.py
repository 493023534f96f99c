"""Bijective flow map: a normflows stack of masked affine coupling layers (RealNVP; Dinh et al. 2017, Eq. 9)

    z' = b * z + (1 - b) * (z * exp(s(b * z)) + t(b * z)),

with alternating masks b, tanh networks s and t whose last layers start at zero (so the flow starts as the
identity), composed after an affine alignment in normalised coordinates:

    phi(x) = u^-1(F(u(A x + t))),  u(x) = (x - m) / sigma   (m, sigma: the target keypoints' mean and spread).

F is fitted by full-batch L-BFGS on mean |phi(source) - target|^2 plus ``prior_weight`` times the same error
at fixed anchor points over three times the keypoints' extent whose targets are themselves: the zero-transport
prior, which keeps the map rigid where no keypoint says otherwise. The inverse is exact (each coupling inverts in closed form) and
``log_det_jacobian`` comes from the flow.
"""

from __future__ import annotations

import normflows as nf
import torch

from kpflow.maps.affine import AlignedMap
from kpflow.maps.neural import anchor_points, fit_regression, smooth_mlp
from kpflow.maps.validation import scale_floor


class FlowMap(AlignedMap):
    """normflows coupling flow on top of an affine alignment (module docstring)."""

    def __init__(
        self,
        alignment: str = "rigid",
        n_layers: int = 4,
        hidden: int = 32,
        depth: int = 2,
        steps: int = 200,
        prior_weight: float = 1e-2,
        seed: int = 0,
    ) -> None:
        super().__init__(alignment)
        self.n_layers, self.hidden, self.depth = n_layers, hidden, depth
        self.steps, self.prior_weight, self.seed = steps, prior_weight, seed
        self.flows: torch.nn.ModuleList | None = None
        self.losses: list[float] = []

    def _build(self, d: int, like: torch.Tensor) -> torch.nn.ModuleList:
        gen = torch.random.fork_rng(devices=[]) if like.device.type == "cpu" else torch.random.fork_rng()
        with gen:
            torch.manual_seed(self.seed)
            layers = []
            for k in range(self.n_layers):
                b = ((torch.arange(d) + k) % 2).to(like)
                s = smooth_mlp(d, d, self.hidden, self.depth)
                t = smooth_mlp(d, d, self.hidden, self.depth)
                layers.append(nf.flows.MaskedAffineFlow(b, t=t, s=s))
        return torch.nn.ModuleList(layers).to(like)

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        src, tgt = source[0], target[0]
        self._fit_alignment(source, target)
        self.centre = tgt.mean(0)
        self.spread = (tgt - self.centre).square().sum(-1).mean().sqrt().clamp_min(scale_floor(tgt))
        self.flows = self._build(src.shape[-1], src)
        u_src = (self.alignment._forward(source)[0] - self.centre) / self.spread
        u_tgt = (tgt - self.centre) / self.spread
        anchors = anchor_points(src.shape[-1], src, seed=self.seed)
        self.losses = fit_regression(
            self.flows, self._flow_forward, u_src, u_tgt, anchors, anchors, self.prior_weight, self.steps
        )

    def _flow_forward(self, u: torch.Tensor) -> torch.Tensor:
        for layer in self.flows:
            u, _ = layer(u)
        return u

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        b, m, d = x.shape
        u = (self.alignment._forward(x).reshape(-1, d) - self.centre) / self.spread
        return (self._flow_forward(u) * self.spread + self.centre).reshape(b, m, d)

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        b, m, d = y.shape
        u = (y.reshape(-1, d) - self.centre) / self.spread
        for layer in reversed(self.flows):
            u, _ = layer.inverse(u)
        return self.alignment._inverse((u * self.spread + self.centre).reshape(b, m, d))

    def log_det_jacobian(self, x) -> torch.Tensor:
        """log |det J(x)| ``[...]`` from the flow's own log-determinants plus the affine part."""
        flat, shape = self._flatten(x)
        u = (self.alignment._forward(flat).reshape(-1, self.dim) - self.centre) / self.spread
        total = torch.zeros(u.shape[0], dtype=u.dtype, device=u.device)
        for layer in self.flows:
            u, ld = layer(u)
            total = total + ld
        total = total + torch.linalg.slogdet(self.alignment.A[0]).logabsdet
        return total.reshape(shape[:-1])
