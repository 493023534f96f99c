"""The scripted packing demonstration, and running a trajectory with its outcome (success, failure reason).

Trajectories are :class:`kpflow.trajectory.Trajectory`. The scripted planner (:func:`plan_packing`) moves over the object at the carrying height (``LIFT`` above its top), descends
straight onto it, seals, lifts it by ``LIFT``, carries it over the container, lowers it in, releases and retreats,
in the straight, interpolated segments of :func:`kpflow.tasks.arm.motion.interpolate`. Coming down vertically matters for tall,
narrow objects: a diagonal approach, with the controller lagging, swept the cereal box over.
"""

from __future__ import annotations

from kpflow.core.task import Execution
from kpflow.tasks.arm.execution import arm_failure, follow
from kpflow.tasks.arm.motion import PRESS, pointing_down, segments_to_trajectory
from kpflow.trajectory import Trajectory

from .keypoints import LIFT
from .scene import CONTAINER_WALL

PLACE_CLEARANCE = 0.015  # m between the object's bottom and the container's floor at release
RETREAT = 0.12


def plan_packing(
    start_pos, start_rot, box: dict, container_pos, container_yaw: float, table_height: float
) -> Trajectory:
    """The scripted demonstration for an object ``box`` (from :func:`~.perception.object_box`) and a container at
    ``container_pos`` (centre, m) with yaw ``container_yaw`` (module docstring)."""
    top, (cx, cy), yaw = box["top"], box["centre"], box["yaw"]
    height = top - table_height
    grasp_rot, place_rot = pointing_down(yaw), pointing_down(container_yaw)
    lifted = top + LIFT
    place = table_height + CONTAINER_WALL + PLACE_CLEARANCE + height
    segments = [  # (phase, target position, rotation, settle steps, suction during the segment)
        ("approach", (cx, cy, lifted), grasp_rot, 15, False),  # above the object first: nothing is swept sideways
        ("descend", (cx, cy, top - PRESS), grasp_rot, 10, False),
        ("seal", (cx, cy, top - PRESS), grasp_rot, 5, True),
        ("lift", (cx, cy, lifted), grasp_rot, 5, True),
        ("carry", (container_pos[0], container_pos[1], lifted), place_rot, 10, True),
        ("lower", (container_pos[0], container_pos[1], place), place_rot, 10, True),
        ("release", (container_pos[0], container_pos[1], place), place_rot, 15, False),
        ("retreat", (container_pos[0], container_pos[1], place + RETREAT), place_rot, 5, False),
    ]
    return segments_to_trajectory(start_pos, start_rot, segments)


def execute(
    env, trajectory: Trajectory, settle: int = 20, frames: list | None = None, frame_every: int = 2
) -> Execution:
    """Run ``trajectory`` on ``env`` (a :class:`~.env.PackingEnv` after ``reset_to``) and say how it went.

    Each step commands the pose; while ``grasp`` is on the cup seals as soon as it is within reach of the object,
    and when it goes off the object is let go. After the last step the arm holds still for ``settle`` steps.

    Returns the :class:`~kpflow.core.task.Execution`: ``success`` (the object rests in the container) and
    ``failure`` (None or the first reason: ``"not grasped"``, ``"near-singular"`` or ``"unreachable"`` (tracking
    error above ``arm.execution.TRACKING_LIMIT``, with or without the arm's Jacobian getting near-singular),
    ``"collision"`` (the arm touched the container), ``"missed container"``).
    """
    run = follow(env, trajectory, settle, env.container_geoms, frames, frame_every)
    success = env.object_in_container()
    failure = None if success else (arm_failure(run) or "missed container")
    return Execution(success=bool(success), failure=failure, **run)
