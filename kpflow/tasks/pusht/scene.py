"""Seeded reset configurations of Push-T: in-distribution, robot out of distribution, object out of distribution.

Each split is a reproducible list: configuration ``i`` of a split depends only on ``(seed, split, i)``.

* ``in_distribution`` -- standard 512-px workspace; agent uniform in [50, 450]^2, block origin in [100, 400]^2 with
  a uniform angle (the standard env's ranges), goal random in the training region.
* ``robot_ood`` -- large 1024-px workspace; the agent's disc lies completely outside the training region (the
  top-left 512-px square), block as in distribution, goal in the training region.
* ``object_ood`` -- large workspace; the block origin is uniform in [100, 924]^2 and the T lies completely or
  partially outside the training region; agent in [50, 450]^2; goal in the training region.

``standard_config(seed)`` is Diffusion Policy's own start-state draw (its test protocol, and gym-pusht's reset):
fixed goal, no redraws, seeds from :data:`STANDARD_FIRST_SEED`.

Unlike the standard env, a split's configuration is redrawn when the block would overlap a wall (every T vertex stays 5 px
inside the walls), when the agent touches the block (5 px clearance), or when the block already covers 85% of the
goal, so that no episode starts solved at either success threshold.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import shapely

from .geometry import AGENT_RADIUS, OUTLINE, coverage, t_polygon, to_world
from .workspace import get_workspace

SPLITS = ("in_distribution", "robot_ood", "object_ood")
GOAL_MODES = ("random", "fixed")
FIXED_GOAL = (256.0, 256.0, np.pi / 4)  # the standard env's goal
GOAL_MARGIN = 40.0  # goal T vertices stay this far inside the training region: the agent fits between it and a wall
_WORKSPACE = {"in_distribution": "standard", "robot_ood": "large", "object_ood": "large", "standard": "standard"}


def split_workspace(split: str) -> str:
    """The workspace (``"standard"`` 512 px or ``"large"`` 1024 px) whose configurations ``split`` draws."""
    if split not in _WORKSPACE:
        raise ValueError(f"unknown Push-T split {split!r}; choose one of {tuple(_WORKSPACE)}")
    return _WORKSPACE[split]


@dataclass(frozen=True)
class Config:
    """One reset: agent position, block and goal poses ``(x, y, theta)``, and the workspace name."""

    agent_pos: tuple[float, float]
    block_pose: tuple[float, float, float]
    goal_pose: tuple[float, float, float]
    workspace: str = "standard"

    def as_dict(self) -> dict:
        return asdict(self)


def _random_goal(rng: np.random.Generator, region: float) -> tuple[float, float, float]:
    while True:
        pose = (*rng.uniform(100.0, region - 112.0, 2), rng.uniform(-np.pi, np.pi))
        corners = to_world(pose, OUTLINE)
        if np.all((corners >= GOAL_MARGIN) & (corners <= region - GOAL_MARGIN)):
            return tuple(float(v) for v in pose)


def sample_config(split: str, rng: np.random.Generator, goal: str = "random") -> Config:
    """Draw one configuration of ``split`` (see the module docstring) with ``rng``."""
    if split not in SPLITS:
        raise ValueError(f"unknown Push-T split {split!r}; choose one of {SPLITS}")
    if goal not in GOAL_MODES:
        raise ValueError(f"unknown goal mode {goal!r}; choose one of {GOAL_MODES}")
    ws = get_workspace(_WORKSPACE[split])
    goal_pose = FIXED_GOAL if goal == "fixed" else _random_goal(rng, ws.region)
    while True:
        if split == "robot_ood":
            agent = rng.uniform(50.0, ws.size - 50.0, 2)
            if np.all(agent < ws.region + AGENT_RADIUS):
                continue
        else:
            agent = rng.uniform(50.0, 450.0, 2)
        hi = ws.size - 100.0 if split == "object_ood" else 400.0
        block = (*rng.uniform(100.0, hi, 2), rng.uniform(-np.pi, np.pi))
        outline = to_world(block, OUTLINE)
        if not ws.in_walls(outline, margin=5.0).all():
            continue
        if split == "object_ood" and ws.in_region(outline).all():
            continue
        if shapely.distance(t_polygon(block), shapely.Point(agent)) < AGENT_RADIUS + 5.0:
            continue
        if coverage(block, goal_pose) >= 0.85:
            continue
        return Config(
            agent_pos=(float(agent[0]), float(agent[1])),
            block_pose=tuple(float(v) for v in block),
            goal_pose=goal_pose,
            workspace=ws.name,
        )


STANDARD_FIRST_SEED = 100_000  # the first test seed of Diffusion Policy's Push-T evaluation (LeRobot's too)


def standard_config(seed: int) -> Config:
    """Diffusion Policy's start state for ``seed`` (``PushTEnv.reset`` there, and gym-pusht's): with
    ``rs = np.random.RandomState(seed)``, in this order,

        agent = (rs.randint(50, 450), rs.randint(50, 450)),
        block = (rs.randint(100, 400), rs.randint(100, 400), rs.randn() * 2 pi - pi),

    and the fixed goal (256, 256, pi/4) in the 512-px workspace. Nothing is redrawn: the block may start against a
    wall or the agent, or already near the goal, exactly as there."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise ValueError(f"seed must be an integer in [0, 2**32); got {seed!r}")
    rs = np.random.RandomState(seed=int(seed))
    agent = (float(rs.randint(50, 450)), float(rs.randint(50, 450)))
    block = (float(rs.randint(100, 400)), float(rs.randint(100, 400)), float(rs.randn() * 2 * np.pi - np.pi))
    return Config(agent_pos=agent, block_pose=block, goal_pose=FIXED_GOAL, workspace="standard")


def split_config(split: str, i: int, seed: int = 0, goal: str = "random") -> Config:
    """Configuration ``i`` of ``split`` for ``seed``, drawn from its own generator seeded by ``(seed, split, i)``."""
    if split not in SPLITS:
        raise ValueError(f"unknown Push-T split {split!r}; choose one of {SPLITS}")
    return sample_config(split, np.random.default_rng((seed, SPLITS.index(split) + 1, i)), goal)


def make_split(split: str, n: int = 200, seed: int = 0, goal: str = "random") -> list[Config]:
    """The first ``n`` configurations of ``split`` for ``seed``; configuration ``i`` is the same for every ``n``."""
    if split not in SPLITS:
        raise ValueError(f"unknown Push-T split {split!r}; choose one of {SPLITS}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    return [split_config(split, i, seed, goal) for i in range(n)]
