"""The 32 packing keypoints of the paper's Section 3.3: four boxes of eight corners.

In this order (each box: bottom face, then top face, counter-clockwise; :func:`~.perception.box_corners`):

0-7    the end effector at the start: a box of fixed size around the cup's start pose;
8-15   the object at rest: its box from the top-down RGB-D image (:func:`~.perception.object_box`);
16-23  the object after lifting: the same box ``LIFT`` higher;
24-31  the container: the corners of its outer box, from its pose (read from the simulator) and its size.
"""

from __future__ import annotations

import numpy as np

from .perception import box_corners, object_box
from .scene import CONTAINER_SIZE, TABLE_TOP

N_KEYPOINTS = 32
GROUPS = {"start": slice(0, 8), "object": slice(8, 16), "lifted": slice(16, 24), "container": slice(24, 32)}
START_BOX = (0.10, 0.10, 0.10)  # m: the end-effector box around the start pose
LIFT = 0.25  # m: how high the object is lifted before it is carried


def yaw_of(rot: np.ndarray) -> float:
    """Yaw (rad) of a rotation's x axis in the world's XY plane."""
    return float(np.arctan2(rot[1, 0], rot[0, 0]))


def packing_keypoints(env, reference_yaw: float = 0.0) -> dict:
    """The 32 keypoints ``[32, 3]`` of ``env``'s current scene and the object box they came from.

    Call it with the arm at its start pose (after ``reset_to``): the object is then in the camera's view.
    ``reference_yaw`` picks which of the object box's half-turn-symmetric yaws is used (the source's, so that
    corners correspond across scenes).
    """
    ee_pos, ee_rot = env.ee_pose()
    start = box_corners(ee_pos[:2], START_BOX[:2], yaw_of(ee_rot), ee_pos[2] - START_BOX[2] / 2, ee_pos[2] + START_BOX[2] / 2)
    box = object_box(env.render_topdown(), TABLE_TOP, reference_yaw)
    lifted = box["corners"] + np.array([0.0, 0.0, LIFT])
    pos, rot = env.container_frame()
    half = np.array(CONTAINER_SIZE[2]) / 2
    container = box_corners(pos[:2], CONTAINER_SIZE[:2], yaw_of(rot), pos[2] - half, pos[2] + half)
    keypoints = np.concatenate([start, box["corners"], lifted, container])
    return {"keypoints": keypoints, "box": box}
