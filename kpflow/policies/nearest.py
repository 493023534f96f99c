"""Nearest neighbour: replay the action chunk demonstrated from the most similar keypoint configuration."""

from __future__ import annotations

import numpy as np

from .source_index import SourceIndex


class NearestNeighbourPolicy:
    """Executes the first ``execute`` actions of the nearest source's chunk (:class:`SourceIndex`), then asks again."""

    def __init__(self, index: SourceIndex, execute: int = 20):
        if not 1 <= execute <= index.chunks.shape[1]:
            raise ValueError(f"execute must be in 1..{index.chunks.shape[1]} (the chunk length), got {execute}")
        self.index, self.execute = index, execute
        self.last_source: int | None = None

    def reset(self, seed: int | None = None) -> None:
        self.last_source = None

    def act(self, obs: dict) -> np.ndarray:
        i, _ = self.index.query(obs["keypoints"])
        self.last_source = i
        return self.index.chunks[i, : self.execute].astype(np.float64)
