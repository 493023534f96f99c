"""A suction gripper for robosuite arms, like the paper's vacuum gripper.

robosuite has no suction gripper, so this is a 0-DoF gripper model (a cup on a shaft, no actuators: the arm's action
stays the 6-D pose) whose grasp is a MuJoCo weld equality between the cup's ``eef`` body and the object, switched
on at run time by :meth:`kpflow.tasks.arm.env.SuctionArmEnv.suction_on` when the cup touches the object (as a
vacuum seals on contact) and off by ``suction_off``. A weld holds the object at the pose it had when it was
switched on, as a sealed cup does. Registered with robosuite as ``gripper_types="SuctionGripper"``.
"""

from __future__ import annotations

from pathlib import Path

from robosuite.models.grippers import GripperModel, register_gripper

ASSET = Path(__file__).parent / "assets" / "suction_gripper.xml"


@register_gripper
class SuctionGripper(GripperModel):
    """The cup of ``assets/suction_gripper.xml``; no actuators, so it adds no action dimension."""

    def __init__(self, idn=0):
        super().__init__(str(ASSET), idn=idn)

    def format_action(self, action):
        return action

    @property
    def init_qpos(self):
        return None

    @property
    def _important_geoms(self):
        return {"cup": ["cup_collision"]}
