"""The 32 packing keypoints of the paper's Section 3.3: four boxes of eight corners.

In this order (each box: bottom face, then top face, counter-clockwise; :func:`kpflow.tasks.arm.keypoints.box_corners`):

0-7    the end effector at the start: a box of fixed size around the cup's start pose;
8-15   the object at rest: its box from the top-down RGB-D image (:func:`~.perception.object_box`), or from the
       simulator (``keypoints=sim``: :func:`~.perception.true_object_box`);
16-23  the object after lifting: the same box ``LIFT`` higher;
24-31  the container: the corners of its outer box, from its pose (the simulator's, or the camera's:
       :func:`~.perception.container_pose`) and its size.
"""

from __future__ import annotations

import numpy as np

from kpflow.tasks.arm.keypoints import box_corners, end_effector_box

from .scene import CONTAINER_SIZE

N_KEYPOINTS = 32
GROUPS = {"start": slice(0, 8), "object": slice(8, 16), "lifted": slice(16, 24), "container": slice(24, 32)}
LIFT = 0.25  # m: how high the object is lifted before it is carried


def packing_keypoints(
    start_pose: tuple[np.ndarray, np.ndarray], box: dict, container_centre: np.ndarray, container_yaw: float
) -> np.ndarray:
    """The 32 keypoints ``[32, 3]`` (module docstring) of a scene whose end effector is at ``start_pose`` (position,
    rotation), whose object has ``box`` (:func:`~.perception.object_box`'s or :func:`~.perception.true_object_box`'s
    dict) and whose container's volume is centred at ``container_centre [3]``, turned by ``container_yaw``."""
    start = end_effector_box(*start_pose)
    lifted = box["corners"] + np.array([0.0, 0.0, LIFT])
    half = CONTAINER_SIZE[2] / 2
    centre = np.asarray(container_centre, float)
    container = box_corners(centre[:2], CONTAINER_SIZE[:2], container_yaw, centre[2] - half, centre[2] + half)
    return np.concatenate([start, box["corners"], lifted, container])
