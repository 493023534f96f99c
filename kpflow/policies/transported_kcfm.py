"""Online transport of a K-CFM policy (the paper's Eq. 5): ``a = phi(f(phi^-1(x)))``.

At every decision, with ``x = T`` the observed keypoints:

1. ``S``: the nearest configuration the K-CFM was trained on (a :class:`SourceIndex` over its training data);
2. ``phi``: a keypoint map fitted so that ``phi(S) ~= T`` (rigid by default, see below);
3. ``phi^-1(T)``: the observation pulled back next to ``S``, a configuration the K-CFM has seen. All 25 observed
   keypoints are pulled back rather than ``S`` itself being used: where the map reproduces ``phi(S) = T`` exactly the
   two agree, and whatever the map leaves unfitted (its residual; the agent's own offset, for a map that fits the
   agent keypoint loosely) stays in the K-CFM's input, so the agent keeps its place relative to the scene;
4. ``f``: the K-CFM samples a chunk of absolute targets there;
5. ``phi``: the chunk is pushed forward into the observed scene.

This addresses the failure modes of its two ingredients:

* policy transportation (:class:`~kpflow.policies.transportation.TransportationPolicy`) replays the chunk of one
  nearest source and relies on the map alone to adapt it, so the map has to deform that single demonstration hard
  whenever the scene (the agent's position above all) differs from the source, and the chunk's shape is only ever
  that of the one demonstration;
* the K-CFM generalises from all its training data but is only reliable near it: on unseen inputs (a block
  elsewhere in the workspace, a rotated scene) its chunks become noisy and wrong.

Here the K-CFM is only ever queried next to its training data, and the chunk that the map carries is not one
stored demonstration but the K-CFM's prediction at that configuration, which draws on all the training data.

Which map: a K-CFM chunk is a sample, some 17 px (median, over its first 8 targets) from the chunk demonstrated
at the same configuration, and a map that is exact at 25 keypoints may stretch space between them. Measured on
120 held-out expert states (``phi`` fitted from the nearest of 180 training episodes), the transported chunk's
median / p90 error against the demonstrated one was 47 / 186 px with ILWR, 27 / 348 px with the GP map and
19 / 41 px with a rigid map, against 18 / 39 px for the K-CFM queried at the observation itself. Closed loop on 20
configurations per split, ILWR gave 0 / 0 / 0% and the rigid map 85 / 95 / 20%. Hence ``AffineMap("rigid")`` is the
default; any map with an inverse can be passed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..maps import AffineMap
from ..maps.base import TransportMap
from .kcfm import KCFM
from .kcfm_policy import KCFMPolicy
from .source_index import SourceIndex


class TransportedKCFMPolicy:
    """K-CFM transported online by a keypoint map: ``act(obs) = phi(f(phi^-1(T)))`` (module docstring, Eq. 5).

    Args:
        model: a trained K-CFM.
        index: its training configurations (e.g. ``SourceIndex.from_store(store, episodes=train_episodes,
            reference=PUSHT_BLOCK)``); only their keypoints are used.
        make_map: builds an unfitted map with an inverse (default ``AffineMap``, rigid: module docstring).
        steps: Euler steps of the flow.
        execute: how many actions of the chunk :meth:`act` returns.

    After :meth:`act`, ``last_source`` (index of ``S``), ``last_map`` (``phi``) and ``last_pullback``
    (``phi^-1(T)``, the K-CFM's input) describe the decision.
    """

    def __init__(
        self,
        model: KCFM,
        index: SourceIndex,
        make_map: Callable[[], TransportMap] = AffineMap,
        steps: int = 10,
        execute: int = 8,
    ) -> None:
        self.policy = KCFMPolicy(model, steps, execute)  # validates steps and execute
        k = int(model.hparams.n_keypoints)
        if index.keypoints.shape[1:] != (k, 2):
            raise ValueError(f"the index holds keypoints {index.keypoints.shape[1:]}; the model takes ({k}, 2)")
        self.index, self.make_map = index, make_map
        self.last_source: int | None = None
        self.last_map: TransportMap | None = None
        self.last_pullback: np.ndarray | None = None

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        index: SourceIndex,
        make_map: Callable[[], TransportMap] = AffineMap,
        steps: int = 10,
        execute: int = 8,
    ) -> "TransportedKCFMPolicy":
        """The transported policy of a K-CFM Lightning checkpoint, loaded on the CPU."""
        base = KCFMPolicy.from_checkpoint(path, steps, execute)
        return cls(base.model, index, make_map, steps, execute)

    @property
    def model(self) -> KCFM:
        return self.policy.model

    @property
    def steps(self) -> int:
        return self.policy.steps

    @property
    def execute(self) -> int:
        return self.policy.execute

    def reset(self, seed: int | None = None) -> None:
        """Reseed the K-CFM's sampling noise with ``seed`` (0 when None) and forget the last decision."""
        self.policy.reset(seed)
        self.last_source, self.last_map, self.last_pullback = None, None, None

    def act(self, obs: dict) -> np.ndarray:
        """The first ``execute`` actions ``[execute, 2]`` (float64, px) of ``phi(f(phi^-1(T)))`` for ``T = obs["keypoints"]``."""
        target = np.asarray(obs["keypoints"], dtype=np.float64)
        i, _ = self.index.query(target)  # validates the shape and finiteness of the observation
        target_t = torch.from_numpy(target)
        source_t = torch.from_numpy(self.index.keypoints[i].astype(np.float64))
        phi = self.make_map().fit(source_t, target_t)
        with torch.no_grad():
            pullback = phi.inverse(target_t).to(torch.float64)
        chunk = self.policy.act({"keypoints": pullback})
        with torch.no_grad():
            out = phi(torch.from_numpy(chunk)).to(torch.float64).numpy()
        self.last_source, self.last_map, self.last_pullback = i, phi, pullback.numpy()
        return out
