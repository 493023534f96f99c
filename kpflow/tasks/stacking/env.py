"""Stacking in robosuite: the suction arm (:class:`~kpflow.tasks.arm.env.SuctionArmEnv`) and two blocks, a cheese
block to pick and a lettuce block to put it on.

The top-down camera is lower and narrower than packing's, so the blocks fill more of the image: what the image
features see is what the keypoints are made of.
"""

from __future__ import annotations

import numpy as np

from kpflow.tasks.arm.env import SuctionArmEnv

from .objects import BLOCKS, CHEESE, LETTUCE
from .scene import Scene

STACK_TOLERANCE = 0.012  # m: the cheese's bottom lies within this of the lettuce's top when it rests on it


class StackingEnv(SuctionArmEnv):
    """The suction arm with the cheese and lettuce blocks of :data:`BLOCKS` (module docstring).

    Args:
        camera_size: ``(height, width)`` of the top-down images.
        seed: robosuite's seed (the scene itself comes from :meth:`reset_to`).
        **kwargs: passed to robosuite's ``ManipulationEnv``.
    """

    camera_pos = (-0.02, -0.01, 1.62)
    camera_fovy = 48.0
    scene: Scene | None

    def _make_objects(self):
        return {name: make() for name, make in BLOCKS.items()}

    def _arrange(self, scene: Scene) -> None:
        self.place_object(CHEESE, *scene.cheese_pose)
        self.place_object(LETTUCE, *scene.lettuce_pose)

    @property
    def grasp_object(self) -> str:
        return CHEESE

    def reward(self, action=None) -> float:
        return float(self.scene is not None and self.stacked())

    def stacked(self) -> bool:
        """Whether the cheese rests on the lettuce: its centre above the lettuce's top face, its bottom on that face
        (within ``STACK_TOLERANCE``), upright, and let go."""
        c_centre, c_rot, c_half = self.object_box(CHEESE)
        l_centre, l_rot, l_half = self.object_box(LETTUCE)
        local = l_rot.T @ (c_centre - l_centre)
        on_face = bool(np.all(np.abs(local[:2]) < l_half[:2]))
        bottom, top = c_centre[2] - c_half[2], l_centre[2] + l_half[2]
        upright = c_rot[2, 2] > np.cos(np.deg2rad(15))
        return on_face and abs(bottom - top) < STACK_TOLERANCE and upright and not self.holding()
