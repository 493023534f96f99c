"""Push-T keypoint pairs for the learned map: observed scenes and the demonstrated scene a policy would transport.

A target ``T`` is a 25-keypoint observation (block T, goal T, agent) of one of two kinds, drawn at random:

* a reset of one of ``splits`` (:func:`~kpflow.tasks.pusht.scene.sample_config`; both workspaces by default), with
  probability ``contact`` the agent moved next to the block (a uniform direction, 25-90 px from the block's origin,
  outside the T) as it is during an episode;
* a step of a demonstration with the block moved by up to ``jitter_px`` / ``jitter_rad`` and the agent by up to
  ``jitter_px``.

Its source ``S`` is what the policies fit a map from: one of the ``candidates`` nearest demonstrated steps of the
store in the block's frame (:class:`~kpflow.data.source_index.SourceIndex`, the weights of ``kpflow/conf/policy/transport``).
"""

from __future__ import annotations

import numpy as np
import shapely
from tqdm import tqdm

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.geometry.angles import planar_rotation
from kpflow.tasks.pusht.demos import ensure_pusht_demos
from kpflow.tasks.pusht.geometry import (
    AGENT_RADIUS,
    N_T_KEYPOINTS,
    PUSHT_BLOCK,
    observation_keypoints,
    pusht_weights,
    t_polygon,
)
from kpflow.tasks.pusht.scene import SPLITS, sample_config


class PushTPairs:
    """Pair sampler ``(n, rng) -> (source, target) [n, 25, 2]`` (module docstring) over the store at ``path``
    (collected on first use, as ``data=pusht_expert`` does, with ``n_episodes``, ``seed`` and ``workers``; with
    ``n_episodes=None`` any existing store). The pairs themselves are drawn from the ``rng`` each call is given."""

    def __init__(
        self,
        path: str,
        n_episodes: int | None = 200,
        splits: tuple[str, ...] = SPLITS,
        demo_fraction: float = 0.5,
        contact: float = 0.5,
        jitter_px: float = 30.0,
        jitter_rad: float = 0.5,
        candidates: int = 5,
        weights: dict | None = None,
        seed: int = 0,
        workers: int = 2,
    ) -> None:
        for name, p in (("demo_fraction", demo_fraction), ("contact", contact)):
            if not 0 <= p <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {p}")
        bad = [s for s in splits if s not in SPLITS]
        if bad or not splits:
            raise ValueError(f"splits must be a non-empty subset of {SPLITS}; got {list(splits)}")
        ensure_pusht_demos(path, n_episodes, seed, workers)
        w = pusht_weights(**(weights or {"agent": 4.0}))
        self.index = SourceIndex.from_store(EpisodeStore(path), 1, w, PUSHT_BLOCK)
        self.splits, self.demo_fraction, self.contact = tuple(splits), demo_fraction, contact
        self.jitter_px, self.jitter_rad, self.candidates = jitter_px, jitter_rad, candidates

    def _reset(self, rng: np.random.Generator) -> np.ndarray:
        cfg = sample_config(self.splits[rng.integers(len(self.splits))], rng)
        agent = np.asarray(cfg.agent_pos)
        if rng.random() < self.contact:
            block = t_polygon(cfg.block_pose)
            for _ in range(20):
                angle, r = rng.uniform(-np.pi, np.pi), rng.uniform(25.0, 90.0)
                p = np.asarray(cfg.block_pose[:2]) + r * np.array([np.cos(angle), np.sin(angle)])
                if shapely.distance(block, shapely.Point(p)) >= AGENT_RADIUS:
                    agent = p
                    break
        return observation_keypoints(cfg.block_pose, cfg.goal_pose, agent)

    def _demo_step(self, rng: np.random.Generator) -> np.ndarray:
        kp = self.index.keypoints[rng.integers(len(self.index))].astype(np.float64)
        block = kp[:N_T_KEYPOINTS]
        centre = block.mean(0)
        a = rng.uniform(-self.jitter_rad, self.jitter_rad)
        rot = planar_rotation(a)
        out = kp.copy()
        out[:N_T_KEYPOINTS] = (block - centre) @ rot.T + centre + rng.uniform(-self.jitter_px, self.jitter_px, 2)
        out[-1] += rng.uniform(-self.jitter_px, self.jitter_px, 2)
        return out

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        target = np.stack(
            [self._demo_step(rng) if rng.random() < self.demo_fraction else self._reset(rng) for _ in range(n)]
        )
        source = np.empty_like(target)
        for i, t in enumerate(tqdm(target, desc="Push-T pairs: nearest sources", disable=n < 1000)):
            near, _ = self.index.query_k(t, self.candidates)
            source[i] = self.index.keypoints[near[rng.integers(len(near))]]
        return source, target
