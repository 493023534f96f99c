"""Ensemble of maps: members fitted on the same keypoints with different seeds (and, optionally, on bootstrap
resamples of the keypoints). phi(x) = mean_k phi_k(x); the variance across members is the uncertainty;
``sample`` returns members' maps; J is the mean of the members' Jacobians.
"""

from __future__ import annotations

from typing import Callable

import torch

from kpflow.maps.base import TransportMap, newton_inverse


class EnsembleMap(TransportMap):
    """Mean and spread of ``n_members`` maps made by ``factory(seed)`` (module docstring).

    Args:
        factory: called with ``seed=k`` to make member k, e.g. ``functools.partial(MLPMap, steps=300)``.
        bootstrap: fit each member on a resample (with replacement) of the keypoint pairs.
    """

    exact_inverse = False

    def __init__(
        self, factory: Callable[..., TransportMap], n_members: int = 5, bootstrap: bool = False, seed: int = 0
    ):
        super().__init__()
        if n_members < 2:
            raise ValueError(f"an ensemble needs at least 2 members; got {n_members}")
        self.factory, self.n_members, self.bootstrap, self.seed = factory, n_members, bootstrap, seed
        self.members = torch.nn.ModuleList()

    def required_points(self, dim: int) -> int:
        return self.factory(seed=self.seed).required_points(dim)

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        gen = torch.Generator().manual_seed(self.seed)
        n = source.shape[1]
        members = []
        for k in range(self.n_members):
            src, tgt = source[0], target[0]
            if self.bootstrap:
                idx = torch.randint(n, (n,), generator=gen).to(source.device)
                idx = torch.unique(idx)  # repeated pairs add nothing but duplicates
                src, tgt = src[idx], tgt[idx]
            members.append(self.factory(seed=self.seed + k).fit(src, tgt))
        self.members = torch.nn.ModuleList(members)

    def _stack(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([m._forward(x) for m in self.members])  # [K, B, M, D]

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._stack(x).mean(0)

    def _predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ys = self._stack(x)
        return ys.mean(0), ys.var(0, unbiased=True)

    def _jacobian(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([m._jacobian(x) for m in self.members]).mean(0)

    def _sample(self, x: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
        ys = self._stack(x)
        idx = torch.randint(len(self.members), (n,), generator=generator).to(x.device)
        return ys[idx]

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        x0 = self.members[0]._inverse(y) if self.members[0].exact_inverse else y
        return newton_inverse(self._forward, self._jacobian, y, x0)
