"""Frames-task keypoint pairs for the learned map: the ten keypoints of two start/goal configurations."""

from __future__ import annotations

import numpy as np
import torch

from kpflow.tasks.frames.frames import scene_keypoints
from kpflow.tasks.frames.scene import random_frames


class FramesPairs:
    """Pair sampler ``(n, rng) -> (source, target) [n, 10, 2]``: source and target are each a start and goal frame
    drawn as :func:`~kpflow.tasks.frames.scene.random_scenes` draws them (without their demonstrations), with
    keypoints ``frame_size`` from each origin (``kpflow/conf/task/frames.yaml``'s 0.1)."""

    def __init__(self, frame_size: float = 0.1, min_distance: float = 0.8) -> None:
        if not frame_size > 0:
            raise ValueError(f"frame_size must be > 0, got {frame_size}")
        self.frame_size, self.min_distance = float(frame_size), float(min_distance)

    def _keypoints(self, g: torch.Generator) -> np.ndarray:
        return scene_keypoints(random_frames(g, self.min_distance), self.frame_size).numpy()

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        g = torch.Generator().manual_seed(int(rng.integers(2**63 - 1)))
        source = np.stack([self._keypoints(g) for _ in range(n)])
        target = np.stack([self._keypoints(g) for _ in range(n)])
        return source, target
