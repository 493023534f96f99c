"""Policy transportation: a near demonstrated chunk, carried into the current scene by a keypoint map.

With ``S`` the chosen source's keypoints and ``T`` the observed ones, fit ``phi`` with ``phi(S) ~= T`` and execute
``phi(a_1), ..., phi(a_H)`` for the source's chunk of absolute targets ``a`` (the paper's offline transport applied
to one chunk at a time).

Choosing the source. With ``candidates = 1`` it is the nearest (deterministic). With ``candidates = k > 1`` it is
drawn among the ``k`` nearest, rank ``i = 0..k-1`` with probability ``exp(-i / temperature) / Z``, as the authors'
public code does (k = 5, temperature 1.2): a deterministic choice can repeat the same chunk from the same state for
ever (an agent parked at a corner of the T), a draw gets it out. ``max_step_px`` clips each executed step: target
``j`` moves at most that far per axis from target ``j - 1`` (from the agent for the first), as their code clips
actions to +-5 px.

Stuck detection (``stuck_decisions = n``): when the object (the index's ``reference`` keypoints, else all of them)
has moved less than ``stuck_px`` over the last ``n`` decisions, the same few sources are being replayed without
effect. The policy then draws its source uniformly among ``stuck_candidates`` nearest for that decision, which
takes it to a different demonstrated approach; it counts as stuck again only after another ``n`` decisions.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from ..data.source_index import SourceIndex
from ..maps import ILWRMap
from ..maps.base import TransportMap
from ..utils.config_checks import Key


def clip_steps(start: np.ndarray, targets: np.ndarray, max_step: float) -> np.ndarray:
    """Targets ``[H, A]`` with each step clipped per axis: ``c_0 = start + clip(t_0 - start, -m, m)``,
    ``c_j = c_{j-1} + clip(t_j - c_{j-1}, -m, m)``."""
    out, prev = np.empty_like(targets), np.asarray(start, dtype=targets.dtype)
    for j, t in enumerate(targets):
        prev = prev + np.clip(t - prev, -max_step, max_step)
        out[j] = prev
    return out


class TransportPolicy:
    """A source chosen by :class:`SourceIndex` (module docstring), then its chunk transported by a map from
    ``make_map()`` (ILWR).

    Args:
        execute: how many of the chunk's targets :meth:`act` returns.
        candidates: draw the source among this many nearest (1: the nearest).
        temperature: rank temperature of the draw (``exp(-rank / temperature)``).
        max_step_px: clip every executed step to this many px per axis (None: no clipping).
        stuck_decisions: detect being stuck over this many decisions (None: never).
        stuck_px: the object moving less than this (max over its keypoints, px) over them counts as stuck.
        stuck_candidates: draw uniformly among this many nearest when stuck.

    ``stuck_count`` counts the decisions of the episode taken as stuck.
    """

    def __init__(
        self,
        index: SourceIndex,
        make_map: Callable[[], TransportMap] = ILWRMap,
        execute: int = 20,
        candidates: int = 1,
        temperature: float = 1.2,
        max_step_px: float | None = None,
        stuck_decisions: int | None = None,
        stuck_px: float = 2.0,
        stuck_candidates: int = 50,
    ):
        if not 1 <= execute <= index.chunks.shape[1]:
            raise ValueError(f"execute must be in 1..{index.chunks.shape[1]} (the chunk length), got {execute}")
        Key(int, lo=1).check("candidates", candidates)
        if not (np.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature must be a positive number, got {temperature!r}")
        if max_step_px is not None and not (np.isfinite(max_step_px) and max_step_px > 0):
            raise ValueError(f"max_step_px must be a positive number or None, got {max_step_px!r}")
        if stuck_decisions is not None:
            Key(int, lo=1).check("stuck_decisions", stuck_decisions)
        Key(int, lo=1).check("stuck_candidates", stuck_candidates)
        if not (np.isfinite(stuck_px) and stuck_px >= 0):
            raise ValueError(f"stuck_px must be a number >= 0, got {stuck_px!r}")
        self.index, self.make_map, self.execute = index, make_map, execute
        self.stuck_decisions, self.stuck_px, self.stuck_candidates = stuck_decisions, float(stuck_px), int(stuck_candidates)
        self.object_track: list[np.ndarray] = []  # the object's keypoints at each decision since the last escape
        self.stuck_count = 0
        self.candidates, self.temperature, self.max_step_px = int(candidates), float(temperature), max_step_px
        self.rng = np.random.default_rng(0)
        self.last_source: int | None = None
        self.last_map: TransportMap | None = None

    def reset(self, seed: int | None = None) -> None:
        """Reseed the source draw with ``seed`` (0 when None)."""
        self.rng = np.random.default_rng(0 if seed is None else int(seed))
        self.last_source, self.last_map = None, None
        self.object_track, self.stuck_count = [], 0

    def stuck(self, target: np.ndarray) -> bool:
        """Record the object's keypoints of this decision; True when it has moved less than ``stuck_px`` over the
        last ``stuck_decisions`` decisions (the record then starts again)."""
        if self.stuck_decisions is None:
            return False
        obj = target if self.index.reference is None else target[self.index.reference]
        self.object_track = [*self.object_track[-self.stuck_decisions :], obj]
        if len(self.object_track) <= self.stuck_decisions:
            return False
        moved = max(float(np.abs(h - obj).max()) for h in self.object_track)
        if moved >= self.stuck_px:
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

    def act(self, obs: dict) -> np.ndarray:
        target = np.asarray(obs["keypoints"], dtype=np.float64)
        i = self.choose(target)
        source = self.index.keypoints[i].astype(np.float64)
        phi = self.make_map().fit(torch.from_numpy(source), torch.from_numpy(target))
        chunk = torch.from_numpy(self.index.chunks[i, : self.execute].astype(np.float64))
        self.last_source, self.last_map = i, phi
        with torch.no_grad():
            moved = phi(chunk).numpy()
        if self.max_step_px is not None:
            moved = clip_steps(np.asarray(obs["agent_pos"], np.float64), moved, self.max_step_px)
        return moved
