"""Which demonstrated source a transporting policy follows at a decision.

With ``candidates = 1`` the source is the nearest configuration of the :class:`~kpflow.data.source_index.SourceIndex`
(deterministic). With ``candidates = k > 1`` it is drawn among the ``k`` nearest, rank ``i = 0..k-1`` with
probability ``exp(-i / temperature) / Z``, as the authors' public code does (k = 5, temperature 1.2).

Stuck detection (``stuck_decisions = n``): a deterministic choice can repeat the same chunk from the same state for
ever (a block pressed against a wall, an agent parked at a corner of the T). When the object (the index's
``reference`` keypoints, else all of them) has moved less than ``stuck_distance`` over the last ``n`` decisions, the same
few sources are being replayed without effect; the source of that decision is then drawn uniformly among the
``stuck_candidates`` nearest, which takes the policy to a different demonstrated approach. It counts as stuck again
only after another ``n`` decisions.
"""

from __future__ import annotations

import numpy as np

from ..data.source_index import SourceIndex
from ..utils.config_checks import RESET_SEED, Key


class SourceChoice:
    """The source for each decision (module docstring); ``stuck_count`` counts the episode's decisions taken as stuck.

    Args:
        index: the demonstrated configurations.
        candidates: draw the source among this many nearest (1: the nearest).
        temperature: rank temperature of the draw (``exp(-rank / temperature)``).
        stuck_decisions: detect being stuck over this many decisions (None: never).
        stuck_distance: the object moving less than this (max over its keypoints, in their unit: Push-T px) over them counts as stuck.
        stuck_candidates: draw uniformly among this many nearest when stuck.
    """

    def __init__(
        self,
        index: SourceIndex,
        candidates: int = 1,
        temperature: float = 1.2,
        stuck_decisions: int | None = None,
        stuck_distance: float = 2.0,
        stuck_candidates: int = 50,
    ):
        Key(int, lo=1).check("candidates", candidates)
        if not (np.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature must be a positive number, got {temperature!r}")
        if stuck_decisions is not None:
            Key(int, lo=1).check("stuck_decisions", stuck_decisions)
        Key(int, lo=1).check("stuck_candidates", stuck_candidates)
        if not (np.isfinite(stuck_distance) and stuck_distance >= 0):
            raise ValueError(f"stuck_distance must be a number >= 0, got {stuck_distance!r}")
        self.index, self.candidates, self.temperature = index, int(candidates), float(temperature)
        self.stuck_decisions, self.stuck_distance, self.stuck_candidates = (
            stuck_decisions,
            float(stuck_distance),
            int(stuck_candidates),
        )
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Reseed the draws with ``seed`` (an integer >= 0; 0 when None) and forget the object's track."""
        RESET_SEED.check("seed", seed)
        self.rng = np.random.default_rng(0 if seed is None else int(seed))
        self.object_track: list[np.ndarray] = []  # the object's keypoints at each decision since the last escape
        self.stuck_count = 0

    def stuck(self, target: np.ndarray) -> bool:
        """Record the object's keypoints of this decision; True when it has moved less than ``stuck_distance`` over the
        last ``stuck_decisions`` decisions (the record then starts again)."""
        if self.stuck_decisions is None:
            return False
        obj = target if self.index.reference is None else target[self.index.reference]
        self.object_track = [*self.object_track[-self.stuck_decisions :], obj]
        if len(self.object_track) <= self.stuck_decisions:
            return False
        moved = max(float(np.abs(h - obj).max()) for h in self.object_track)
        if moved >= self.stuck_distance:
            return False
        self.object_track, self.stuck_count = [obj], self.stuck_count + 1
        return True

    def choose(self, target: np.ndarray) -> int:
        """The source for the observed keypoints ``target [K, D]`` (module docstring)."""
        if self.stuck(target):
            near, _ = self.index.query_k(target, min(self.stuck_candidates, len(self.index)))
            return int(near[self.rng.integers(len(near))])
        if self.candidates == 1:
            return self.index.query(target)[0]
        near, _ = self.index.query_k(target, self.candidates)
        p = np.exp(-np.arange(len(near)) / self.temperature)
        return int(near[self.rng.choice(len(near), p=p / p.sum())])
