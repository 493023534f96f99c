"""Frames-task keypoint pairs for the learned map: the ten keypoints of two start/goal configurations."""

from __future__ import annotations

import math

import numpy as np
import torch

from kpflow.tasks.frames.frames import scene_keypoints
from kpflow.tasks.frames.scene import random_frames
from kpflow.tasks.frames.turns import turned_configs


class FramesPairs:
    """Pair sampler ``(n, rng) -> (source, target) [n, 10, 2]`` with keypoints ``frame_size`` from each origin
    (``kpflow/conf/task/frames.yaml``'s 0.1).

    ``max_turn_deg`` None: source and target are each a start and goal frame drawn as
    :func:`~kpflow.tasks.frames.scene.random_scenes` draws them (without their demonstrations), independently.
    Otherwise both are configurations of one geometry whose frames turn independently by up to ``max_turn_deg``
    (:func:`~kpflow.tasks.frames.turns.turned_configs`, the multi-frame benchmark's distribution)."""

    def __init__(
        self, frame_size: float = 0.1, min_distance: float = 0.8, max_turn_deg: float | None = None, shift: float = 0.1
    ) -> None:
        if not frame_size > 0:
            raise ValueError(f"frame_size must be > 0, got {frame_size}")
        if max_turn_deg is not None and not 0 <= max_turn_deg <= 360:
            raise ValueError(f"max_turn_deg must be in [0, 360] or None, got {max_turn_deg}")
        self.frame_size, self.min_distance, self.max_turn_deg, self.shift = (
            float(frame_size),
            float(min_distance),
            max_turn_deg,
            float(shift),
        )

    def _keypoints(self, configs) -> np.ndarray:
        return scene_keypoints(list(configs), self.frame_size).numpy()

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        g = torch.Generator().manual_seed(int(rng.integers(2**63 - 1)))
        if self.max_turn_deg is None:  # all sources, then all targets (the draws of the sampler before max_turn_deg)
            source = np.stack([self._keypoints(random_frames(g, self.min_distance)) for _ in range(n)])
            return source, np.stack([self._keypoints(random_frames(g, self.min_distance)) for _ in range(n)])
        turn = math.radians(self.max_turn_deg)
        pairs = [turned_configs(random_frames(g, self.min_distance), 2, g, turn, self.shift) for _ in range(n)]
        return np.stack([self._keypoints(p[0]) for p in pairs]), np.stack([self._keypoints(p[1]) for p in pairs])
