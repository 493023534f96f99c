"""The scripted stacking demonstration, and running a trajectory with its outcome.

:func:`plan_stacking` moves over the cheese block at the carrying height, descends straight onto it, seals, lifts
it, carries it over the lettuce block while turning it to the lettuce's yaw (of the two half-turn-equivalent yaws,
the nearer), lowers it onto the lettuce, releases and retreats. Trajectories are
:class:`kpflow.trajectory.Trajectory`.
"""

from __future__ import annotations

import numpy as np

from kpflow.core.task import Execution
from kpflow.geometry.angles import yaw_of
from kpflow.tasks.arm.execution import arm_failure, follow
from kpflow.tasks.arm.motion import PRESS, pointing_down, segments_to_trajectory
from kpflow.trajectory import Trajectory

LIFT = 0.12  # m: the cheese's bottom clears the lettuce's top by this much while carried
PLACE_CLEARANCE = 0.006  # m between the cheese's bottom and the lettuce's top at release
RETREAT = 0.10


def nearest_half_turn(yaw: float, reference: float) -> float:
    """``yaw`` or ``yaw + pi`` (a box looks the same), whichever is nearer ``reference``, as ``reference`` plus an
    offset in ``[-pi/2, pi/2)``."""
    return reference + (yaw - reference + np.pi / 2) % np.pi - np.pi / 2


def plan_stacking(start_pos, start_rot, cheese: tuple, lettuce: tuple) -> Trajectory:
    """The scripted demonstration from the start pose for the blocks' boxes ``(centre [3], rotation [3, 3], half
    extents [3])``."""
    (c_centre, c_rot, c_half), (l_centre, l_rot, l_half) = cheese, lettuce
    grasp_yaw = yaw_of(c_rot)
    place_yaw = nearest_half_turn(yaw_of(l_rot), grasp_yaw)
    grasp_rot, place_rot = pointing_down(grasp_yaw), pointing_down(place_yaw)
    top, height = c_centre[2] + c_half[2], 2 * c_half[2]
    lettuce_top = l_centre[2] + l_half[2]
    carry = max(top, lettuce_top + height) + LIFT
    place = lettuce_top + height + PLACE_CLEARANCE - PRESS
    (cx, cy), (lx, ly) = c_centre[:2], l_centre[:2]
    segments = [  # (phase, target position, rotation, settle steps, suction during the segment)
        ("approach", (cx, cy, carry), grasp_rot, 10, False),
        ("descend", (cx, cy, top - PRESS), grasp_rot, 10, False),
        ("seal", (cx, cy, top - PRESS), grasp_rot, 5, True),
        ("lift", (cx, cy, carry), grasp_rot, 5, True),
        ("carry", (lx, ly, carry), place_rot, 10, True),
        ("lower", (lx, ly, place), place_rot, 10, True),
        ("release", (lx, ly, place), place_rot, 15, False),
        ("retreat", (lx, ly, place + RETREAT), place_rot, 5, False),
    ]
    return segments_to_trajectory(start_pos, start_rot, segments)


def execute(
    env, trajectory: Trajectory, settle: int = 20, frames: list | None = None, frame_every: int = 2
) -> Execution:
    """Run ``trajectory`` on a :class:`~.env.StackingEnv` (after ``reset_to``) and say how it went.

    Returns the :class:`~kpflow.core.task.Execution`: :func:`~kpflow.tasks.arm.execution.follow`'s record with ``success`` (the cheese rests on the lettuce,
    :meth:`~.env.StackingEnv.stacked`) and ``failure``: None, the arm's reason
    (:func:`~kpflow.tasks.arm.execution.arm_failure`; no geoms are watched for collisions here, so never
    ``"collision"``), ``"grasped the lettuce"`` (the wrong block) or ``"missed the lettuce"``.
    """
    run = follow(env, trajectory, settle, frames=frames, frame_every=frame_every)
    success = env.stacked()
    failure = None
    if not success:
        if run["grasped"] is not None and run["grasped"] != env.grasp_object:
            failure = f"grasped the {run['grasped']}"
        else:
            failure = arm_failure(run) or "missed the lettuce"
    return Execution(success=bool(success), failure=failure, **run)
