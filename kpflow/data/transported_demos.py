"""Training data for a motion policy refit on transported demonstrations (the paper's Eq. 6): the frames task's
demonstrations from every other configuration, transported into one target configuration, as
(position, velocity) pairs. Validation holds out whole demonstrations."""

from __future__ import annotations

from typing import Callable

import lightning
import torch
from torch.utils.data import DataLoader, TensorDataset

from kpflow.maps.base import TransportMap
from kpflow.tasks.frames.scenes import lookahead_velocity, random_scenes


class TransportedDemosDataModule(lightning.LightningDataModule):
    """(x, xdot) pairs from ``n_configs - 1`` demonstrations transported into configuration ``target``.

    Args:
        make_map: factory of unfitted :class:`~kpflow.maps.base.TransportMap` (e.g. a Hydra partial).
        n_val: number of transported demonstrations held out for validation.
    """

    def __init__(
        self,
        make_map: Callable[[], TransportMap],
        n_configs: int = 8,
        target: int = 0,
        n_points: int = 200,
        frame_size: float = 0.1,
        horizon: float = 0.05,
        n_val: int = 1,
        batch_size: int = 256,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if not 0 <= target < n_configs:
            raise ValueError(f"target must index one of the {n_configs} configurations; got {target}")
        if not 1 <= n_val < n_configs - 1:
            raise ValueError(f"n_val must leave training demonstrations: 1 <= n_val < {n_configs - 1}; got {n_val}")
        self.make_map = make_map
        self.n_configs, self.target, self.n_points, self.frame_size = n_configs, target, n_points, frame_size
        self.horizon, self.n_val, self.batch_size, self.seed = horizon, n_val, batch_size, seed
        self.train_set = self.val_set = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        scenes = random_scenes(self.n_configs, self.n_points, self.seed)
        target = scenes[self.target]
        duration = float(target.demo.times[-1] - target.demo.times[0])
        pairs = []
        for j, scene in enumerate(scenes):
            if j == self.target:
                continue
            phi = self.make_map().fit(scene.keypoints(self.frame_size), target.keypoints(self.frame_size))
            x = phi(scene.demo.positions)
            pairs.append((x.float(), lookahead_velocity(x, duration, self.horizon).float()))
        val, train = pairs[: self.n_val], pairs[self.n_val :]
        self.train_set = TensorDataset(*(torch.cat(t) for t in zip(*train)))
        self.val_set = TensorDataset(*(torch.cat(t) for t in zip(*val)))

    def train_dataloader(self) -> DataLoader:
        g = torch.Generator().manual_seed(self.seed)
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, generator=g)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size)
