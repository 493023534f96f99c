"""Multi-frame scenes whose frames turn independently: the benchmark where a map must bend a path far from its keypoints.

A *family* is one start/goal geometry (drawn as :func:`~.scene.random_frames` draws it) shown in ``n_configs``
configurations: each configuration turns the start and the goal frame about their own origins by independent angles
uniform in ``[-max_turn / 2, max_turn / 2]`` (so two configurations differ by up to ``max_turn`` per frame) and
shifts each by up to ``shift`` per axis. In every configuration ``n_demonstrators`` demonstrators reach from start
to goal (:func:`~.demonstrator.demonstrate`); demonstrator ``k`` keeps one style across the configurations of its
family (the same random wiggle, from a generator seeded by family and demonstrator, and its own ``tangent_scale``,
uniform in ``tangent_range``). So demonstrator k's demonstration in configuration j is a held-out ground truth for
k's demonstration in configuration i carried into j's frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .demonstrator import DemonstratedMotion, demonstrate
from .frames import Frame
from .scene import moved, random_frames


@dataclass(frozen=True)
class TurnedFamily:
    """One geometry's ``configs`` (start, goal frames) and ``demos[c][k]``: demonstrator k in configuration c."""

    configs: list[tuple[Frame, Frame]]
    demos: list[list[DemonstratedMotion]]


def turned_configs(
    base: tuple[Frame, Frame], n: int, g: torch.Generator, max_turn: float, shift: float
) -> list[tuple[Frame, Frame]]:
    """``n`` configurations of the frames ``base``: each frame turned about its origin by an angle uniform in
    ``[-max_turn / 2, max_turn / 2]`` and shifted by up to ``shift`` per axis, independently (drawn from ``g``)."""
    configs = []
    for _ in range(n):
        u = torch.rand(6, generator=g, dtype=torch.float64).tolist()
        configs.append(tuple(moved(frame, shift * (2 * u[3 * i] - 1), shift * (2 * u[3 * i + 1] - 1), max_turn * (u[3 * i + 2] - 0.5))
                             for i, frame in enumerate(base)))  # fmt: skip
    return configs


def turned_families(
    n_families: int,
    n_configs: int = 4,
    n_demonstrators: int = 3,
    max_turn: float = math.radians(80.0),
    shift: float = 0.1,
    n_points: int = 200,
    wiggle: float = 0.15,
    tangent_range: tuple[float, float] = (0.7, 1.3),
    seed: int = 0,
) -> list[TurnedFamily]:
    """``n_families`` families of the module docstring, reproducible from ``seed`` (float64)."""
    if n_families < 1 or n_configs < 2 or n_demonstrators < 1:
        raise ValueError(
            f"need n_families >= 1, n_configs >= 2 and n_demonstrators >= 1; got {n_families}, {n_configs}, {n_demonstrators}"
        )
    if not 0 <= max_turn <= 2 * math.pi or shift < 0:
        raise ValueError(f"max_turn must be in [0, 2 pi] and shift >= 0; got {max_turn}, {shift}")
    low, high = (float(v) for v in tangent_range)
    if not 0 < low <= high:
        raise ValueError(f"tangent_range must be (low, high) with 0 < low <= high; got {tangent_range}")
    g = torch.Generator().manual_seed(seed)
    families = []
    for f in range(n_families):
        configs = turned_configs(random_frames(g), n_configs, g, max_turn, shift)
        tangents = (low + (high - low) * torch.rand(n_demonstrators, generator=g, dtype=torch.float64)).tolist()
        demos = [[demonstrate(start, goal, n=n_points, wiggle=wiggle, tangent_scale=tangents[k],
                              generator=torch.Generator().manual_seed(seed * 1_000_003 + f * 1009 + k)) for k in range(n_demonstrators)]
                 for start, goal in configs]  # fmt: skip
        families.append(TurnedFamily(configs, demos))
    return families
