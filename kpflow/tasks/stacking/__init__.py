"""Stacking with a UR5e in robosuite, with keypoints found in camera images (the paper's Section 3.2): one
demonstration puts the cheese block on the lettuce block; new scenes move or swap the blocks.

* :mod:`.objects` -- the two textured blocks.
* :mod:`.scene` -- a scene (the blocks' poses) and the seeded moved / swapped samplers.
* :mod:`.env` -- :class:`StackingEnv`: the suction arm, the blocks, a closer top-down camera, the success test.
* :mod:`.trajectory` -- the scripted demonstration and running a trajectory with its failure reason.
* :mod:`.keypoints` -- image correspondences lifted to 3-D, their ground truth, exact (oracle) pairs.
* :mod:`.trial` -- recording the source demonstration and running a transported trial.
"""

from .env import StackingEnv
from .scene import CONDITIONS, SOURCE_SCENE, Scene, sample_scene

__all__ = ["StackingEnv", "Scene", "SOURCE_SCENE", "CONDITIONS", "sample_scene"]
