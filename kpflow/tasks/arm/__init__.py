"""The robot shared by the robosuite tasks: a UR5e with a suction cup over a table, seen by a top-down RGB-D camera.

* :mod:`.gripper` -- the suction cup (a 0-DoF gripper whose grasp is a weld).
* :mod:`.motion` -- cup orientations and interpolated straight-line waypoints.
* :mod:`.env` -- :class:`SuctionArmEnv`: absolute-pose control, suction, the camera; tasks subclass it.
* :mod:`.execution` -- running a trajectory and the arm's failure reasons.
* :mod:`.keypoints` -- box corners and the end effector's start box.

A recorded trajectory is carried into a new scene by :class:`kpflow.policies.demo_transport.DemoTransportPolicy`.
"""

from .env import SuctionArmEnv

__all__ = ["SuctionArmEnv"]
