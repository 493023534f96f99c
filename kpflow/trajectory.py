"""What a demonstration is carried as, from the tasks that record it to the policies that transport it: an
end-effector :class:`Trajectory` and the :class:`Keypoints` of its source scene and of the scene now."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """An end-effector trajectory, one row per 20 Hz control step: ``positions [T, 3]`` and ``rotations [T, 3, 3]``
    of the cup's tip or the jaws' grip site (absolute targets for the operational-space controller), ``grasp [T]`` (holding: the suction cup's vacuum on, or the jaws closed),
    ``phases [T]`` (the segment each step belongs to: approach, descend, seal, ...) and, once transported, ``std
    [T, 3]`` (the map's uncertainty at each position)."""

    positions: np.ndarray
    rotations: np.ndarray
    grasp: np.ndarray
    phases: np.ndarray
    std: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.positions)
        shapes = (
            np.shape(self.positions)[1:],
            np.shape(self.rotations)[1:],
            len(self.rotations),
            len(self.grasp),
            len(self.phases),
        )
        if shapes != ((3,), (3, 3), n, n, n):
            raise ValueError(
                "a trajectory needs positions [T, 3], rotations [T, 3, 3], grasp [T] and phases [T] of one length T; got"
                f" {np.shape(self.positions)}, {np.shape(self.rotations)}, {np.shape(self.grasp)}, {np.shape(self.phases)}"
            )
        if not (np.isfinite(self.positions).all() and np.isfinite(self.rotations).all()):
            raise ValueError("the trajectory contains NaN or inf")
        if self.std is not None and np.shape(self.std) != (n, 3):
            raise ValueError(f"std must be [T, 3] = [{n}, 3], got {np.shape(self.std)}")

    def __len__(self) -> int:
        return len(self.positions)

    def step_of(self, phase: str) -> int:
        """The first step of ``phase`` (``ValueError`` if the trajectory has none)."""
        steps = np.flatnonzero(self.phases == phase)
        if not len(steps):
            raise ValueError(f"the trajectory has no {phase!r} step (phases: {sorted(set(self.phases.tolist()))})")
        return int(steps[0])

    def moved(self, positions: np.ndarray, rotations: np.ndarray, std: np.ndarray) -> Trajectory:
        """The same grasp and phases at new poses (a transported copy)."""
        return replace(self, positions=positions, rotations=rotations, std=std)


@dataclass(frozen=True)
class Keypoints:
    """Corresponding keypoints of the source scene and of the scene now (``source``, ``target`` ``[N, 3]``), the
    input of a transportation map."""

    source: np.ndarray
    target: np.ndarray

    def __post_init__(self) -> None:
        if np.shape(self.source) != np.shape(self.target) or np.ndim(self.source) != 2:
            raise ValueError(
                f"source and target keypoints must both be [N, D]; got {np.shape(self.source)} and {np.shape(self.target)}"
            )
