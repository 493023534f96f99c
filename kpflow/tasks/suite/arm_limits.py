"""What the Panda can follow: one rating of a path of grip-site poses, for the scripted place's turn, the
generator's choice of a symmetric correspondence and the online policy's check of every chunk it sends.

:func:`arm_path_cost` is infinite when the path turns the jaws past ``max_turn`` on the way, when the turn takes the
Panda's last joint past ``WRIST_LIMIT`` (turning the jaws by +t turns that joint by about -t), or when a target lies
farther than ``reach`` from the robot's base in the plane; else it is the path's end's distance from the base in the
plane (the Panda's reach ends just past the peg, so nearer is easier). The turn is summed step by step (the first
step, from the jaws now, by the shorter way), so a path that turns the long way round is seen to.

:func:`path_cost` rates paths from a simulator's state (the scripted demonstrations and the generator, with no
reach bound: their numbers in results/generation.md are unchanged); :class:`SuiteArmLimits` rates a policy's chunk
from what it observes (the arm's joints, ``obs["joints"]``, and the jaws' yaw from the finger pads' keypoints), with
the reach bound :data:`REACH` (an :class:`~kpflow.core.symmetry.ArmLimits`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from kpflow.geometry.angles import wrap_angle, yaw_of
from kpflow.geometry.rotations import rot6d_to_matrix

MAX_PLACE_TURN = 0.75 * np.pi  # rad the wrist may turn the nut to align it with the peg
WRIST_LIMIT = 2.65  # rad: the Panda's last joint stops at +-2.9
#: m in the plane from the robot's base beyond which no target is sent: the generated Square d1 demonstrations'
#: grip targets reach 0.82 m (99th percentile) and 0.88 m at most (ilwr family, 64,335 steps)
REACH = 0.90
#: the robot's base in the world (robosuite's table tasks put the Panda's base here; tests/test_suite_tasks.py rates a chunk
#: against the simulator's own base position)
BASE_XY = (-0.56, 0.0)


def arm_path_cost(wrist: float, yaw: float, base_xy, positions: np.ndarray, rotations: np.ndarray,
                  max_turn: float = MAX_PLACE_TURN, reach: float = np.inf) -> float:  # fmt: skip
    """How hard the path ``positions [T, 3]``, ``rotations [T, 3, 3]`` is for the arm whose last joint is at
    ``wrist`` (rad) with the jaws at ``yaw`` (module docstring)."""
    yaws = np.array([yaw, *(yaw_of(r) for r in rotations)])
    turn = float(np.sum(wrap_angle(np.diff(yaws))))
    if abs(turn) > max_turn or abs(wrist - turn) > WRIST_LIMIT:
        return np.inf
    planar = np.linalg.norm(np.asarray(positions)[:, :2] - np.asarray(base_xy)[:2], axis=1)
    if planar.max() > reach:
        return np.inf
    return float(planar[-1])


def path_cost(env) -> Callable[[np.ndarray, np.ndarray], float]:
    """:func:`arm_path_cost` from the state of ``env`` (a :class:`~.env.SuiteEnv`) now, without a reach bound."""
    wrist, yaw, base = float(env.arm_joints()[6]), yaw_of(env.ee_pose()[1]), env.base_position()

    def cost(positions: np.ndarray, rotations: np.ndarray) -> float:
        return arm_path_cost(wrist, yaw, base, positions, rotations)

    return cost


class SuiteArmLimits:
    """The Panda's limits for a policy's chunk (module docstring): ``pads`` are the finger pads' keypoint indices in
    the observation (the jaws' yaw is the direction from the first to the second, less a half turn)."""

    def __init__(self, pads: tuple[int, int], base_xy=BASE_XY, reach: float = REACH):
        self.pads, self.base_xy, self.reach = tuple(int(p) for p in pads), np.asarray(base_xy, float), float(reach)

    def cost(self, obs: dict, chunk: np.ndarray) -> float:
        """:func:`arm_path_cost` of ``chunk [H, 10]`` (position, 6-D rotation, gripper) from ``obs``."""
        if "joints" not in obs:
            raise ValueError(
                "checking a chunk against the arm needs the arm's joints in the observation (obs['joints'] [7])"
            )
        joints, keypoints = np.asarray(obs["joints"], float), np.asarray(obs["keypoints"], float)
        a, b = keypoints[self.pads[0]], keypoints[self.pads[1]]
        yaw = float(np.arctan2(a[1] - b[1], a[0] - b[0]) + np.pi)  # the pads lie across the jaws
        chunk = np.asarray(chunk, float)
        return arm_path_cost(
            float(joints[6]), yaw, self.base_xy, chunk[:, :3], rot6d_to_matrix(chunk[:, 3:9]), np.inf, self.reach
        )
