"""Policy transportation: the nearest demonstrated chunk, carried into the current scene by a keypoint map.

With ``S`` the nearest source's keypoints and ``T`` the observed ones, fit ``phi`` with ``phi(S) ~= T`` and execute
``phi(a_1), ..., phi(a_H)`` for the source's chunk of absolute targets ``a`` (the paper's offline transport applied
to one chunk at a time).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from ..maps import ILWRMap
from ..maps.base import TransportMap
from .source_index import SourceIndex


class TransportationPolicy:
    """Nearest source by :class:`SourceIndex`, then its chunk transported by a map from ``make_map()`` (ILWR)."""

    def __init__(self, index: SourceIndex, make_map: Callable[[], TransportMap] = ILWRMap, execute: int = 20):
        if not 1 <= execute <= index.chunks.shape[1]:
            raise ValueError(f"execute must be in 1..{index.chunks.shape[1]} (the chunk length), got {execute}")
        self.index, self.make_map, self.execute = index, make_map, execute
        self.last_source: int | None = None
        self.last_map: TransportMap | None = None

    def reset(self, seed: int | None = None) -> None:
        self.last_source, self.last_map = None, None

    def act(self, obs: dict) -> np.ndarray:
        target = np.asarray(obs["keypoints"], dtype=np.float64)
        i, _ = self.index.query(target)
        source = self.index.keypoints[i].astype(np.float64)
        phi = self.make_map().fit(torch.from_numpy(source), torch.from_numpy(target))
        chunk = torch.from_numpy(self.index.chunks[i, : self.execute].astype(np.float64))
        self.last_source, self.last_map = i, phi
        with torch.no_grad():
            return phi(chunk).numpy()
