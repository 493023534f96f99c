"""robosuite 1.5's own benchmark tasks (Lift, Stack, PickPlaceCan, NutAssemblySquare) with the Panda's parallel-jaw
gripper, for generating demonstrations by keypoint transport.

* :mod:`.specs` -- each task's environment, objects, fixtures, segments and wide-variant ranges.
* :mod:`.env` -- :class:`SuiteEnv`: the robosuite environment on absolute OSC poses; scenes set by pose.
* :mod:`.scene` -- scenes drawn by robosuite's placement initializers, seeded (``d0``, ``wide``).
* :mod:`.keypoints` -- object keypoints from pose and geometry, symmetric ones ordered by the smallest turn.
* :mod:`.demonstrator` -- the scripted pick and place segments.
* :mod:`.task` -- :class:`SuiteTask`: demonstrate, observe a segment's start, run a segment, success.
"""

from .env import SuiteEnv
from .task import SuiteTask

__all__ = ["SuiteEnv", "SuiteTask"]
