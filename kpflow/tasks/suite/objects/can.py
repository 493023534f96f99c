"""``can`` (PickPlaceCan): the centres of its top and bottom and 4 points on the rim in fixed world directions: a
cylinder has no yaw to see, so none is transported. Picked a little above its middle, the jaws at the home yaw."""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_rotation

from .base import ObjectKind

# geometry (m), read from robosuite 1.5's models
CAN_RADIUS, CAN_HALF_HEIGHT = 0.025, 0.0407


class Can(ObjectKind):
    name, symmetry = "can", 0

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        ring = [
            pos + yaw_rotation(reference_yaw) @ (CAN_RADIUS * np.array([np.cos(a), np.sin(a), 0.0]))
            for a in np.arange(4) * np.pi / 2
        ]
        return np.stack([pos + [0, 0, CAN_HALF_HEIGHT], pos - [0, 0, CAN_HALF_HEIGHT], *ring])

    def pose_from_box(self, box, support):
        return np.r_[np.asarray(box.centre, float), box.top - CAN_HALF_HEIGHT], np.eye(3), None

    def grasp(self, env, pos, rot, home_yaw):
        return pos + [0.0, 0.0, 0.2 * CAN_HALF_HEIGHT], home_yaw


CAN = Can()
