"""One demonstration, transported zero-shot: record it in the source scene, then run it in new scenes.

:func:`record_source` runs the scripted planner in the source scene and keeps its 32 keypoints and the commanded
end-effector trajectory (positions, orientations, suction). :func:`run_trial` extracts the 32 keypoints of a new
scene, fits a map ``phi`` from the source's keypoints to them, transports the trajectory (positions through
``phi``, orientations through the polar factor of its Jacobian, :mod:`kpflow.tasks.arm.transfer`) and
executes it with the operational-space controller on absolute poses.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from kpflow.maps.base import TransportMap
from kpflow.tasks.arm import transfer
from kpflow.tasks.arm.motion import yaw_of

from .env import PackingEnv
from .keypoints import packing_keypoints
from .scene import SOURCE_SCENE, TABLE_TOP, Scene
from .trajectory import execute, plan_packing


def record_source(env: PackingEnv, scene: Scene = SOURCE_SCENE) -> dict:
    """The source demonstration in ``scene``: ``keypoints [32, 3]``, ``box`` (the object's, from the camera),
    ``trajectory`` (commanded positions, rotations, suction, phases) and ``result`` (of running it, see
    :func:`~.trajectory.execute`)."""
    env.reset_to(scene)
    kp = packing_keypoints(env, reference_yaw=scene.object_pose[2])
    container_pos, container_rot = env.container_frame()
    trajectory = plan_packing(*env.ee_pose(), kp["box"], container_pos, yaw_of(container_rot), TABLE_TOP)
    result = execute(env, trajectory)
    return {"scene": scene, "keypoints": kp["keypoints"], "box": kp["box"], "trajectory": trajectory, "result": result}


def transport_source(source: dict, target_keypoints: np.ndarray, make_map: Callable[[], TransportMap]) -> dict:
    """The source's trajectory carried by a map fitted from its 32 keypoints to ``target_keypoints [32, 3]``
    (:func:`kpflow.tasks.arm.transfer.transport_demo`)."""
    return transfer.transport_demo(source["trajectory"], source["keypoints"], target_keypoints, make_map)


def run_trial(
    env: PackingEnv, source: dict, scene: Scene, make_map: Callable[[], TransportMap], frames: list | None = None
) -> dict:
    """Set up ``scene``, transport the source demonstration into it and execute it.

    Returns the execution's ``success``/``failure``/``min_singular_value``, the keypoints, the transported
    ``trajectory``, the measured ``tip`` path and ``box_error_mm``: the mean distance from the camera's object-box corners to the simulator's
    (matched one to one), a check of the perception.
    """
    env.reset_to(scene)
    kp = packing_keypoints(env, reference_yaw=source["box"]["yaw"])
    box_error = box_corner_error(kp["box"]["corners"], env.object_box())  # before anything moves
    moved = transport_source(source, kp["keypoints"], make_map)
    result = execute(env, moved, frames=frames)
    return {
        "scene": scene.as_dict(),
        "success": result["success"],
        "failure": result["failure"],
        "min_singular_value": result["min_singular_value"],
        "max_tracking_error": float(result["tracking_error"].max()),
        "box_error_mm": 1e3 * box_error,
        "max_std": float(moved["std"].max()),
        "keypoints": kp["keypoints"],
        "trajectory": moved,
        "tip": result["tip"],
    }


def box_corner_error(corners: np.ndarray, truth: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """Mean distance (m) between estimated box corners ``[8, 3]`` and the true box ``(centre, rotation, half)``,
    corners matched one to one (Hungarian assignment, scipy)."""
    from scipy.optimize import linear_sum_assignment

    centre, rot, half = truth
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    true = centre + (signs * half) @ rot.T
    d = np.linalg.norm(np.asarray(corners)[:, None] - true[None], axis=-1)
    rows, cols = linear_sum_assignment(d)
    return float(d[rows, cols].mean())
