"""``bin`` (PickPlaceCan's target bin): the 4 corners of its rim; symmetric under half turns. A can placed in it goes
to the quarter compartment ``CAN_COMPARTMENT``, in the bin's frame."""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_rotation

from .base import ObjectKind, square

BIN_HALF = (0.195, 0.245)  # half extents of its rim (m)
BIN_RIM = 0.1  # the bin's rim above its body origin
#: where the can goes in its quarter of the target bin (from the bin's centre): the quarter's corner nearest the robot,
#: kept one can's radius and 1 cm from its walls; the quarter is at the Panda's reach, and 1.5 cm further out (the
#: first choice, (0.05, 0.065)) the elbow often ended a place at its stop
CAN_COMPARTMENT = (0.035, 0.045, 0.0)


class Bin(ObjectKind):
    name, symmetry = "bin", 2

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        return np.stack(square(pos, yaw, *BIN_HALF))

    def pose_from_box(self, box, support):
        # its longer sides run along its y
        return np.r_[np.asarray(box.centre, float), box.top - BIN_RIM], yaw_rotation(box.yaw - np.pi / 2), None

    def place_goal(self, env, spec, held, goal):
        goal_pos, goal_rot = goal
        return goal_pos + goal_rot @ np.array(CAN_COMPARTMENT), 0.0


BIN = Bin()
