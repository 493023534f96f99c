"""Nearest neighbour: replay the action chunk demonstrated from the most similar keypoint configuration.

Two ways to replay the chunk ``a_1..a_H`` of the nearest source ``S`` in the observed scene ``T``:

* ``relative=False``: the demonstrated absolute targets ``a_h`` as they are (the plain baseline; it only works where
  the demonstrations cover the very same workspace positions);
* ``relative=True``: the demonstrated *motion* from where the agent stands, ``x + R (a_h - s)`` with ``s`` and ``x``
  the source's and the observed agent keypoints and ``R`` the rotation of the index's search frame between them
  (the Kabsch rotation from ``S``'s reference keypoints to ``T``'s; the identity when the index searches in the
  world). Only the agent is moved: nothing of the scene deforms the chunk, which is what policy transportation adds.
"""

from __future__ import annotations

import numpy as np
import torch

from ..data.source_index import SourceIndex
from ..geometry.alignment import fit_affine


class NearestNeighbourPolicy:
    """Executes the first ``execute`` actions of the nearest source's chunk (:class:`SourceIndex`), then asks again.

    Args:
        index: the demonstrated configurations and their chunks.
        execute: actions returned per decision.
        relative: replay the chunk as motion from the observed agent, the last keypoint (module docstring).
    """

    def __init__(self, index: SourceIndex, execute: int = 20, relative: bool = False):
        if not 1 <= execute <= index.chunks.shape[1]:
            raise ValueError(f"execute must be in 1..{index.chunks.shape[1]} (the chunk length), got {execute}")
        self.index, self.execute, self.relative = index, execute, bool(relative)
        self.last_source: int | None = None

    def reset(self, seed: int | None = None) -> None:
        self.last_source = None

    def act(self, obs: dict) -> np.ndarray:
        target = np.asarray(obs["keypoints"], dtype=np.float64)
        i, _ = self.index.query(target)
        self.last_source = i
        chunk = self.index.chunks[i, : self.execute].astype(np.float64)
        if not self.relative:
            return chunk
        source = self.index.keypoints[i].astype(np.float64)
        rot = np.eye(2)
        if self.index.reference is not None:
            ref = self.index.reference
            a, _ = fit_affine(torch.from_numpy(source[None, ref]), torch.from_numpy(target[None, ref]), "rigid")
            rot = a[0].numpy()
        return target[-1] + (chunk - source[-1]) @ rot.T
