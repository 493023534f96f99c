"""``cube`` (Lift, Stack): the 8 corners of the box; symmetric under quarter turns about the vertical. Picked at its
centre, the jaws along its axis nearest the home yaw; a cube placed on it sits on its top face."""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_of, yaw_rotation

from .base import ObjectKind, box, reduced_yaw


def cube_half(env, name: str, home: bool = False) -> float:
    """Half side (m) of cube ``name`` now (as the scene scaled it), from its collision geom; ``home``: as built."""
    model = env.sim.model
    body = env.object_body[name]
    geoms = [g for g in np.flatnonzero(model.geom_bodyid == body) if model.geom_contype[g]]
    sizes = env.geom_home[0] if home else model.geom_size
    return float(sizes[geoms[0]][0])


class Cube(ObjectKind):
    name, symmetry = "cube", 4

    def keypoints(self, pos, rot, yaw, reference_yaw, half):
        return box(pos, yaw, (half, half, half))

    def pose_from_box(self, box, support):
        half = float(np.mean(box.half)) if support is None or box.top <= support else (box.top - support) / 2
        return np.r_[np.asarray(box.centre, float), box.top - half], yaw_rotation(box.yaw), half

    def grasp(self, env, pos, rot, home_yaw):
        return pos, reduced_yaw(yaw_of(rot), 4, home_yaw)

    def place_goal(self, env, spec, held, goal):
        return goal[0] + [0.0, 0.0, cube_half(env, spec.grasp) + cube_half(env, spec.target)], 0.0


CUBE = Cube()
