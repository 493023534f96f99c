"""Scenes of the frames task: a start frame, a goal frame and a demonstration between them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kpflow.tasks.frames.demonstrator import DemonstratedMotion, demonstrate
from kpflow.tasks.frames.frames import Frame, scene_keypoints


@dataclass
class Scene:
    start: Frame
    goal: Frame
    demo: DemonstratedMotion

    def keypoints(self, size: float) -> torch.Tensor:
        """The ten keypoints of the start and goal frames ``[10, D]``."""
        return scene_keypoints([self.start, self.goal], size)

    def as_dict(self) -> dict:
        """The two frames' positions and rotations as lists (the demonstration is left out)."""
        return {
            f"{name}_{part}": getattr(getattr(self, name), part).tolist()
            for name in ("start", "goal")
            for part in ("position", "rotation")
        }


def moved(frame: Frame, dx: float, dy: float, dtheta: float) -> Frame:
    """A 2-D frame translated by (dx, dy) and turned by dtheta."""
    return Frame.from_2d(
        float(frame.position[0]) + dx, float(frame.position[1]) + dy, float(frame.theta) + dtheta, dtype=frame.dtype
    )


def random_scenes(n: int, n_points: int, seed: int, min_distance: float = 0.8, wiggle: float = 0.15) -> list[Scene]:
    """``n`` 2-D start/goal configurations in [-1, 1]^2 (at least ``min_distance`` apart, headings within
    +-0.8 rad of the start-goal direction) with one demonstration each, reproducible from ``seed``."""
    g = torch.Generator().manual_seed(seed)
    scenes = []
    while len(scenes) < n:
        start, goal = random_frames(g, min_distance)
        scenes.append(Scene(start, goal, demonstrate(start, goal, n=n_points, generator=g, wiggle=wiggle)))
    return scenes


def random_frames(g: torch.Generator, min_distance: float = 0.8) -> tuple[Frame, Frame]:
    """One start and goal frame of :func:`random_scenes` (drawn from ``g``, redrawn until ``min_distance`` apart)."""
    while True:
        p = torch.rand(4, generator=g, dtype=torch.float64) * 2 - 1
        if (p[:2] - p[2:]).norm() >= min_distance:
            break
    heading = math.atan2(float(p[3] - p[1]), float(p[2] - p[0]))
    th = heading + (torch.rand(2, generator=g, dtype=torch.float64) - 0.5) * 1.6
    start = Frame.from_2d(float(p[0]), float(p[1]), float(th[0]), dtype=torch.float64)
    goal = Frame.from_2d(float(p[2]), float(p[3]), float(th[1]), dtype=torch.float64)
    return start, goal


def lookahead_velocity(x: torch.Tensor, duration: float, fraction: float = 0.05) -> torch.Tensor:
    """Arc-length look-ahead velocity along a path ``x [T, D]``:

        v(s) = (x(s + ds) - x(s)) * (L / duration) / ds,   ds = fraction * L,

    with x(.) interpolated in arc length s (L the path length) and x(s + ds) clamped at the end. It points along
    the path at its mean speed, is not zero where a demonstration starts at rest (so a first-order policy rolled
    out from the start does not stall there), and falls linearly to zero over the last ``ds`` before the goal.
    """
    seg = (x[1:] - x[:-1]).norm(dim=-1)
    s = torch.cat([seg.new_zeros(1), seg.cumsum(0)])  # [T]
    length = float(s[-1])
    if length <= 0:
        return torch.zeros_like(x)
    ds = fraction * length
    ahead = (s + ds).clamp_max(length)
    j = torch.searchsorted(s, ahead).clamp(1, len(s) - 1)
    u = ((ahead - s[j - 1]) / (s[j] - s[j - 1]).clamp_min(1e-12)).clamp(0, 1)[:, None]
    x_ahead = x[j - 1] + u * (x[j] - x[j - 1])
    return (x_ahead - x) * (length / duration) / ds
