"""The 32 packing keypoints of the paper's Section 3.3: four boxes of eight corners.

In this order (each box: bottom face, then top face, counter-clockwise; :func:`kpflow.tasks.arm.keypoints.box_corners`):

0-7    the end effector at the start: a box of fixed size around the cup's start pose;
8-15   the object at rest: its box from the top-down RGB-D image (:func:`~.perception.object_box`);
16-23  the object after lifting: the same box ``LIFT`` higher;
24-31  the container: the corners of its outer box, from its pose (read from the simulator) and its size.
"""

from __future__ import annotations

import numpy as np

from kpflow.tasks.arm.keypoints import box_corners, end_effector_box
from kpflow.tasks.arm.motion import yaw_of

from .perception import object_box
from .scene import CONTAINER_SIZE, TABLE_TOP

N_KEYPOINTS = 32
GROUPS = {"start": slice(0, 8), "object": slice(8, 16), "lifted": slice(16, 24), "container": slice(24, 32)}
LIFT = 0.25  # m: how high the object is lifted before it is carried


def packing_keypoints(env, reference_yaw: float = 0.0) -> dict:
    """The 32 keypoints ``[32, 3]`` of ``env``'s current scene and the object box they came from.

    Call it with the arm at its start pose (after ``reset_to``): the object is then in the camera's view.
    ``reference_yaw`` picks which of the object box's half-turn-symmetric yaws is used (the source's, so that
    corners correspond across scenes).
    """
    start = end_effector_box(*env.ee_pose())
    box = object_box(env.render_topdown(), TABLE_TOP, reference_yaw)
    lifted = box["corners"] + np.array([0.0, 0.0, LIFT])
    pos, rot = env.container_frame()
    half = np.array(CONTAINER_SIZE[2]) / 2
    container = box_corners(pos[:2], CONTAINER_SIZE[:2], yaw_of(rot), pos[2] - half, pos[2] + half)
    keypoints = np.concatenate([start, box["corners"], lifted, container])
    return {"keypoints": keypoints, "box": box}
