"""Training data for a motion policy refit on transported demonstrations (the paper's Eq. 6): the frames task's
demonstrations from every other configuration, transported into one target configuration, as
(position, velocity) pairs. Validation holds out whole demonstrations."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import lightning
import torch
from torch.utils.data import DataLoader, TensorDataset

from kpflow.maps.base import TransportMap
from kpflow.tasks.frames.scene import Scene, lookahead_velocity, random_scenes
from kpflow.transport import TransportedTrajectory, transport_trajectory


@dataclass(frozen=True)
class TransportedDemo:
    """Scene ``source``'s demonstration carried into the target scene: the ``trajectory`` (positions with the map's
    std, velocities, orientations) and the arc-length look-ahead ``velocities`` a first-order policy is fitted on."""

    source: int
    trajectory: TransportedTrajectory
    velocities: torch.Tensor


def transport_into(
    scenes: list[Scene], target: int, make_map: Callable[[], TransportMap], frame_size: float, horizon: float
) -> list[TransportedDemo]:
    """The paper's Eq. 6: every demonstration but the target's, transported into scene ``target``.

    For each other scene j, phi_j is fitted from j's frame keypoints to the target's (phi_j(S_j) ~= S_target) and
    j's demonstration goes through it (:func:`kpflow.transport.transport_trajectory`: x -> phi_j(x), v -> J v,
    R -> polar(J) R). The policy's training velocities are the look-ahead velocities of the transported path at the
    target demonstration's duration (:func:`~kpflow.tasks.frames.scene.lookahead_velocity`, ``horizon`` of its
    length). A map family that fits batches (ILWR, affine, learned) fits every phi_j at once and carries every
    demonstration in one pass.
    """
    goal = scenes[target]
    target_kp = goal.keypoints(frame_size)
    duration = float(goal.demo.times[-1] - goal.demo.times[0])
    others = [j for j in range(len(scenes)) if j != target]
    if make_map().supports_batch and len({len(scenes[j].demo) for j in others}) == 1:  # one fit for all of them
        demos = [scenes[j].demo for j in others]
        sources = torch.stack([scenes[j].keypoints(frame_size) for j in others])
        phi = make_map().fit(sources, target_kp.expand_as(sources))
        batch = transport_trajectory(
            phi, *(torch.stack([getattr(d, f) for d in demos]) for f in ("positions", "velocities", "orientations"))
        )
        moved = [
            TransportedTrajectory(batch.positions[i], batch.std[i], batch.velocities[i], batch.orientations[i])
            for i in range(len(others))
        ]
    else:
        moved = []
        for j in others:
            scene = scenes[j]
            phi = make_map().fit(scene.keypoints(frame_size), target_kp)
            moved.append(
                transport_trajectory(phi, scene.demo.positions, scene.demo.velocities, scene.demo.orientations)
            )
    return [TransportedDemo(j, m, lookahead_velocity(m.positions, duration, horizon)) for j, m in zip(others, moved)]


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
        moved = transport_into(scenes, self.target, self.make_map, self.frame_size, self.horizon)
        pairs = [(d.trajectory.positions.detach().float(), d.velocities.detach().float()) for d in moved]
        val, train = pairs[: self.n_val], pairs[self.n_val :]
        self.train_set = TensorDataset(*(torch.cat(t) for t in zip(*train)))
        self.val_set = TensorDataset(*(torch.cat(t) for t in zip(*val)))

    def train_dataloader(self) -> DataLoader:
        g = torch.Generator().manual_seed(self.seed)
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, generator=g)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size)
