"""The square nut (Square), three kinds of keypoints on one body:

* ``nut``: the ring's centre, its 4 outer corners and the handle's two ends: the handle fixes the yaw. Picked at
  the handle (``NUT_GRASP`` along its x axis; of the two ways round, the one nearer the home yaw).
* ``nut_handle``: the 4 corners of the handle's top face and its centre, what the jaws close on; symmetric under
  half turns about the handle, like the jaws themselves, so a grasp never turns the wrist by more than 90 degrees.
* ``nut_ring``: the ring alone (centre and corners; symmetric under quarter turns), what the peg holds.

All three are seen by a camera the same way: the handle's end tells the ring's (:meth:`Nut.pose_from_box`).
"""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_of, yaw_rotation

from .base import ObjectKind, reduced_yaw, square

# geometry (m), read from robosuite 1.5's models
NUT_RING_HALF = 0.0543  # centre to the ring's outer edge
NUT_HANDLE = (0.029, 0.079)  # the handle's extent along the nut's x axis
NUT_GRASP = 0.054  # where the jaws close on the handle (its centre), along the nut's x axis
NUT_HANDLE_HALF = (0.025, 0.0159, 0.01)  # half extents of the handle bar (the last: its top above its centre)
NUT_TOP = 0.01  # the nut's top above its body origin (robosuite 1.5's SquareNut is 2 cm thick)


class Nut(ObjectKind):
    name, symmetry = "nut", 1

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        handle = [pos + yaw_rotation(yaw) @ np.array([x, 0.0, 0.0]) for x in NUT_HANDLE]
        return np.stack([pos, *square(pos, yaw, NUT_RING_HALF, NUT_RING_HALF), *handle])

    def pose_from_box(self, box, support):
        centre = np.asarray(box.centre, float)
        axis = box.axis
        s = (box.voxels[:, :2] - centre) @ axis  # along the handle
        across = (box.voxels[:, :2] - centre) @ np.array([-axis[1], axis[0]])
        ends = (s > 0.5 * box.half[0], s < -0.5 * box.half[0])
        spread = [np.ptp(across[e]) if e.sum() > 1 else 0.0 for e in ends]
        sign = 1.0 if spread[0] > spread[1] else -1.0  # +axis points to the ring's end
        ring = centre + sign * (box.half[0] - box.half[1]) * axis  # the ring is square: its half side is the short one
        yaw = float(np.arctan2(-sign * axis[1], -sign * axis[0]))  # the nut's x axis points from the ring to the handle
        return np.r_[ring, box.top - NUT_TOP], yaw_rotation(yaw), None

    def grasp(self, env, pos, rot, home_yaw):
        handle = pos + rot @ np.array([NUT_GRASP, 0.0, 0.0])
        return handle + [0.0, 0.0, 0.004], reduced_yaw(yaw_of(rot) + np.pi / 2, 2, home_yaw)


class NutHandle(Nut):
    name, symmetry = "nut_handle", 2

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        centre = pos + yaw_rotation(yaw_of(rot)) @ np.array([NUT_GRASP, 0.0, 0.0])
        return np.stack([centre, *square(centre, yaw, *NUT_HANDLE_HALF)])

    def grasp(self, env, pos, rot, home_yaw):
        return ObjectKind.grasp(self, env, pos, rot, home_yaw)


class NutRing(Nut):
    name, symmetry = "nut_ring", 4

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        return np.stack([pos, *square(pos, yaw, NUT_RING_HALF, NUT_RING_HALF)])

    def grasp(self, env, pos, rot, home_yaw):
        return ObjectKind.grasp(self, env, pos, rot, home_yaw)


NUT, NUT_HANDLE_KIND, NUT_RING = Nut(), NutHandle(), NutRing()
