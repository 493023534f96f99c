"""``peg`` (Square's square peg): its bottom and top centres and the 4 top corners; symmetric under quarter turns.
A nut placed on it goes down to just above the table, turned by the quarter turn the arm can follow best."""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_of, yaw_rotation

from ..arm_limits import MAX_PLACE_TURN, path_cost
from .base import ObjectKind, reduced_yaw, square

# geometry (m), read from robosuite 1.5's models
PEG_HALF, PEG_HEIGHT = 0.016, 0.1  # half side, and half length (its body origin is at its middle)


class Peg(ObjectKind):
    name, symmetry = "peg", 4

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        top = pos + [0, 0, PEG_HEIGHT]
        return np.stack([pos - [0, 0, PEG_HEIGHT], top, *square(top, yaw, PEG_HALF, PEG_HALF)])

    def pose_from_box(self, box, support):
        return np.r_[np.asarray(box.centre, float), box.top - PEG_HEIGHT], yaw_rotation(box.yaw), None

    def place_goal(self, env, spec, held, goal):
        (pos, rot), (goal_pos, goal_rot) = held, goal
        target = np.array([goal_pos[0], goal_pos[1], env.env.table_offset[2] + 0.01])
        smallest = reduced_yaw(yaw_of(goal_rot), 4, yaw_of(rot)) - yaw_of(rot)
        grip, grip_rot = env.ee_pose()
        cost = path_cost(env)
        turns = smallest + np.pi / 2 * np.arange(-2, 3)
        costs = [
            cost((target + yaw_rotation(t) @ (grip - pos))[None], (yaw_rotation(t) @ grip_rot)[None]) for t in turns
        ]
        if not np.isfinite(min(costs)):
            raise ValueError(
                f"no turn aligns the nut with the peg within {MAX_PLACE_TURN:.2f} rad and the last joint's range"
            )
        return target, float(turns[int(np.argmin(costs))])


PEG = Peg()
