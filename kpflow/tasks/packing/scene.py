"""Packing scenes: which object, where it lies, where the container stands; seeded samplers for the two test
conditions of the paper's Section 3.3.

* ``relocation``: the source's object and container; the object at a random position and yaw;
* ``full``: another object type, a random object pose and a random container pose.

Positions are on the table top (m, world frame: x away from the robot's base, y to its left), yaws in rad.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .objects import OBJECT_TYPES

#: the table (full size, m) and the height of its top in the world
TABLE_SIZE = (0.8, 1.2, 0.05)
TABLE_TOP = 0.8
#: object positions: a 40 cm (x) by 60 cm (y) area of the table in the arm's reliable reach
OBJECT_AREA = ((-0.32, 0.08), (-0.40, 0.20))
#: container centres and yaws in the full-variation condition
CONTAINER_AREA = ((-0.22, 0.02), (0.34, 0.40))
CONTAINER_YAW = (-0.5, 0.5)
#: the container (outer size, m) and its wall thickness
CONTAINER_SIZE = (0.24, 0.24, 0.12)
CONTAINER_WALL = 0.01
CONDITIONS = ("relocation", "full")
_CONDITION_IDS = {"relocation": 1, "full": 2}


@dataclass(frozen=True)
class Scene:
    """One packing scene: ``object_type`` (a key of :data:`OBJECT_TYPES`), its pose ``(x, y, yaw)`` on the table
    and the container's pose ``(x, y, yaw)``."""

    object_type: str
    object_pose: tuple[float, float, float]
    container_pose: tuple[float, float, float]

    def __post_init__(self):
        if self.object_type not in OBJECT_TYPES:
            raise ValueError(f"unknown object type {self.object_type!r}; choose one of {sorted(OBJECT_TYPES)}")
        for name in ("object_pose", "container_pose"):
            value = getattr(self, name)
            if len(value) != 3 or not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be 3 finite numbers (x, y, yaw); got {value!r}")

    def as_dict(self) -> dict:
        return asdict(self)


#: the scene of the one source demonstration
SOURCE_SCENE = Scene("box_large", (-0.12, -0.15, 0.35), (-0.10, 0.37, 0.0))


def _clear_of_container(xy: np.ndarray, container: tuple[float, float, float], margin: float = 0.10) -> bool:
    """Whether a point is more than ``margin`` outside the container's footprint (conservative, any yaw)."""
    half = np.hypot(*CONTAINER_SIZE[:2]) / 2
    return float(np.hypot(*(xy - np.asarray(container[:2])))) > half + margin


def sample_scene(condition: str, index: int, seed: int = 0, source: Scene = SOURCE_SCENE) -> Scene:
    """The ``index``-th scene of ``condition`` (deterministic in ``seed``, ``condition`` and ``index``)."""
    if condition not in CONDITIONS:
        raise ValueError(f"unknown condition {condition!r}; choose one of {CONDITIONS}")
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    rng = np.random.default_rng([seed, _CONDITION_IDS[condition], index])
    if condition == "relocation":
        kind, container = source.object_type, source.container_pose
    else:
        others = sorted(t for t in OBJECT_TYPES if t != source.object_type)
        kind = others[rng.integers(len(others))]
        (x0, x1), (y0, y1) = CONTAINER_AREA
        container = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)), float(rng.uniform(*CONTAINER_YAW)))
    (x0, x1), (y0, y1) = OBJECT_AREA
    while True:
        xy = rng.uniform((x0, y0), (x1, y1))
        if _clear_of_container(xy, container):
            break
    return Scene(kind, (float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi))), container)
