"""MLP map: phi(x) = A x + t + sigma * g((x - m) / sigma), with g a tanh MLP whose last layer starts at zero.

The residual network g is fitted by full-batch L-BFGS on the keypoint pairs, with the zero-transport prior
g ~ 0 at anchor points over three times the keypoints' extent (weight ``prior_weight``). Nothing makes g
bijective, so the inverse is solved by Newton iterations from the affine inverse (``exact_inverse = False``).
Ensembles of MLP maps (:class:`~kpflow.maps.ensemble.EnsembleMap`) give an uncertainty from their spread.
"""

from __future__ import annotations

import torch

from kpflow.maps.affine import AlignedMap
from kpflow.maps.base import newton_inverse
from kpflow.maps.neural import anchor_points, fit_regression, smooth_mlp
from kpflow.maps.validation import scale_floor


class MLPMap(AlignedMap):
    """Affine alignment plus an MLP residual (module docstring)."""

    exact_inverse = False

    def __init__(
        self,
        alignment: str = "rigid",
        hidden: int = 64,
        depth: int = 2,
        steps: int = 200,
        prior_weight: float = 1e-2,
        seed: int = 0,
    ) -> None:
        super().__init__(alignment)
        self.hidden, self.depth, self.steps, self.prior_weight, self.seed = hidden, depth, steps, prior_weight, seed
        self.net: torch.nn.Module | None = None
        self.losses: list[float] = []

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        src, tgt = source[0], target[0]
        self._fit_alignment(source, target)
        self.centre = src.mean(0)
        self.spread = (src - self.centre).square().sum(-1).mean().sqrt().clamp_min(scale_floor(src))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed)
            self.net = smooth_mlp(src.shape[-1], src.shape[-1], self.hidden, self.depth).to(src)
        anchors = anchor_points(src.shape[-1], src, seed=self.seed)
        self.losses = fit_regression(
            self.net,
            self.net,
            (src - self.centre) / self.spread,
            (tgt - self.alignment._forward(src[None])[0]) / self.spread,
            anchors,
            torch.zeros_like(anchors),
            self.prior_weight,
            self.steps,
        )

    def _forward_flat(self, x: torch.Tensor) -> torch.Tensor:
        return self.alignment._forward(x[None])[0] + self.spread * self.net((x - self.centre) / self.spread)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        b, m, d = x.shape
        return self._forward_flat(x.reshape(-1, d)).reshape(b, m, d)

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        return newton_inverse(self._forward, self._jacobian, y, self.alignment._inverse(y))
