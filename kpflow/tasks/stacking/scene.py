"""Stacking scenes: where the cheese and the lettuce blocks lie; seeded samplers for the two test conditions of the
paper's Section 3.2.

* ``moved``: both blocks at new positions and yaws, each on its own side of the table as in the demonstration
  (cheese on the right, ``y < 0``; lettuce on the left);
* ``swapped``: the same, with the sides exchanged (cheese on the left, lettuce on the right).

Positions are on the table top (m, world frame: x away from the robot's base, y to its left), yaws in rad.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: block positions: x range, and the y range of each side (right: y < 0)
AREA_X = (-0.22, 0.06)
SIDE_Y = {"right": (-0.26, -0.08), "left": (0.08, 0.24)}
#: block yaws: within this many rad of the demonstration's
YAW_RANGE = 0.6
MIN_GAP = 0.17  # m between the blocks' centres
CONDITIONS = ("moved", "swapped")
_CONDITION_IDS = {"moved": 1, "swapped": 2}


@dataclass(frozen=True)
class Scene:
    """One stacking scene: the poses ``(x, y, yaw)`` of the cheese and of the lettuce block on the table."""

    cheese_pose: tuple[float, float, float]
    lettuce_pose: tuple[float, float, float]

    def __post_init__(self):
        for name in ("cheese_pose", "lettuce_pose"):
            value = getattr(self, name)
            if len(value) != 3 or not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be 3 finite numbers (x, y, yaw); got {value!r}")
        gap = float(np.hypot(self.cheese_pose[0] - self.lettuce_pose[0], self.cheese_pose[1] - self.lettuce_pose[1]))
        if gap < 0.1:
            raise ValueError(f"the blocks' centres are {gap:.3f} m apart: they would overlap (need >= 0.1 m)")

    def as_dict(self) -> dict:
        return asdict(self)


#: the scene of the one source demonstration
SOURCE_SCENE = Scene((-0.08, -0.17, 0.3), (-0.07, 0.15, -0.2))


def sample_scene(condition: str, index: int, seed: int = 0, source: Scene = SOURCE_SCENE) -> Scene:
    """The ``index``-th scene of ``condition`` (deterministic in ``seed``, ``condition`` and ``index``)."""
    if condition not in CONDITIONS:
        raise ValueError(f"unknown condition {condition!r}; choose one of {CONDITIONS}")
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    rng = np.random.default_rng([seed, _CONDITION_IDS[condition], index])
    sides = ("right", "left") if condition == "moved" else ("left", "right")
    while True:
        xy = [rng.uniform((AREA_X[0], SIDE_Y[s][0]), (AREA_X[1], SIDE_Y[s][1])) for s in sides]
        if np.linalg.norm(xy[0] - xy[1]) >= MIN_GAP:
            break
    yaws = [pose[2] + rng.uniform(-YAW_RANGE, YAW_RANGE) for pose in (source.cheese_pose, source.lettuce_pose)]
    return Scene((float(xy[0][0]), float(xy[0][1]), float(yaws[0])), (float(xy[1][0]), float(xy[1][1]), float(yaws[1])))
