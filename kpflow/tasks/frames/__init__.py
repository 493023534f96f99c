"""Frames task: reaching between reference frames described by keypoints.

* :mod:`.frames` -- :class:`Frame` poses, their five keypoints, random poses.
* :mod:`.demonstrator` -- synthetic minimum-jerk reaching demonstrations.
* :mod:`.lasa` -- LASA handwriting demonstrations with frames at their ends.
* :mod:`.scene` -- start/goal configurations with a demonstration each.
"""

from .demonstrator import DemonstratedMotion, demonstrate, minimum_jerk
from .frames import Frame, frame_keypoints, random_frame, scene_keypoints
from .lasa import LASA_SHAPES, end_heading, lasa_frames, load_lasa
from .scene import Scene, lookahead_velocity, moved, random_scenes

__all__ = [
    "Frame",
    "frame_keypoints",
    "scene_keypoints",
    "random_frame",
    "DemonstratedMotion",
    "demonstrate",
    "minimum_jerk",
    "LASA_SHAPES",
    "load_lasa",
    "lasa_frames",
    "end_heading",
    "Scene",
    "lookahead_velocity",
    "moved",
    "random_scenes",
]
