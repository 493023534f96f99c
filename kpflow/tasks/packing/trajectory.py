"""End-effector trajectories for packing: the scripted source demonstration, and running one in the simulator.

A trajectory is a dict of per-control-step arrays: ``positions [T, 3]`` and ``rotations [T, 3, 3]`` of the cup's tip
(absolute targets for the operational-space controller) and ``suction [T]`` (whether the vacuum is on). The scripted
planner (:func:`plan_packing`) moves over the object at the carrying height (``LIFT`` above its top), descends
straight onto it, seals, lifts it by ``LIFT``, carries it over the container, lowers it in, releases and retreats,
in straight segments of at most ``MAX_STEP`` / ``MAX_TURN`` per step. Coming down vertically matters for tall,
narrow objects: a diagonal approach, with the controller lagging, swept the cereal box over.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .keypoints import LIFT
from .scene import CONTAINER_WALL

MAX_STEP, MAX_TURN = 0.015, 0.1  # m and rad per control step (20 Hz): larger jumps can flip the UR5e's elbow
DOWN = Rotation.from_euler("x", np.pi).as_matrix()  # the cup pointing down
PRESS = 0.004  # m: the contact target lies this far below the top, so the cup touches it
PLACE_CLEARANCE = 0.015  # m between the object's bottom and the container's floor at release
RETREAT = 0.12
TRACKING_LIMIT = 0.03  # m: a larger error between target and tip means the arm could not follow
SINGULAR_LIMIT = 0.02  # smallest singular value of the arm's Jacobian below which a configuration is near-singular


def cup_down(yaw: float) -> np.ndarray:
    """The cup pointing down, turned by ``yaw`` about the world's z axis."""
    return Rotation.from_euler("z", yaw).as_matrix() @ DOWN


def interpolate(p0, r0, p1, r1) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints ``[n, 3]``, ``[n, 3, 3]`` from ``(p0, r0)`` (excluded) to ``(p1, r1)`` (included): a straight line and
    a slerp, with ``n`` the fewest steps of at most ``MAX_STEP`` and ``MAX_TURN``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    turn = (Rotation.from_matrix(r1) * Rotation.from_matrix(r0).inv()).magnitude()
    n = max(1, int(np.ceil(max(np.linalg.norm(p1 - p0) / MAX_STEP, turn / MAX_TURN))))
    a = np.arange(1, n + 1) / n
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([r0, r1])))(a).as_matrix()
    return p0 + a[:, None] * (p1 - p0), rots


def plan_packing(start_pos, start_rot, box: dict, container_pos, container_yaw: float, table_height: float) -> dict:
    """The scripted demonstration for an object ``box`` (from :func:`~.perception.object_box`) and a container at
    ``container_pos`` (centre, m) with yaw ``container_yaw``: a trajectory (module docstring) with ``phases [T]``
    naming each step's segment."""
    top, (cx, cy), yaw = box["top"], box["centre"], box["yaw"]
    height = top - table_height
    grasp_rot, place_rot = cup_down(yaw), cup_down(container_yaw)
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
    pos, rot = np.asarray(start_pos, float), np.asarray(start_rot, float)
    out = {"positions": [], "rotations": [], "suction": [], "phases": []}
    for phase, target, target_rot, settle, suction in segments:
        target = np.asarray(target, float)
        ps, rs = interpolate(pos, rot, target, target_rot) if phase not in ("seal", "release") else (np.empty((0, 3)), np.empty((0, 3, 3)))
        ps = np.concatenate([ps, np.repeat(target[None], settle, 0)])
        rs = np.concatenate([rs, np.repeat(target_rot[None], settle, 0)])
        out["positions"].append(ps)
        out["rotations"].append(rs)
        out["suction"].append(np.full(len(ps), suction))
        out["phases"] += [phase] * len(ps)
        pos, rot = target, target_rot
    return {k: (np.concatenate(v) if k != "phases" else np.array(v)) for k, v in out.items()}


def execute(env, trajectory: dict, settle: int = 20, frames: list | None = None, frame_every: int = 2) -> dict:
    """Run ``trajectory`` on ``env`` (a :class:`~.env.PackingEnv` after ``reset_to``) and say how it went.

    Each step commands the pose; while ``suction`` is on the cup seals as soon as it is within reach of the object,
    and when it goes off the object is let go. After the last step the arm holds still for ``settle`` steps.

    Returns ``success`` (the object rests in the container), ``failure`` (None or the first reason:
    ``"not grasped"``, ``"near-singular"`` or ``"unreachable"`` (tracking error above ``TRACKING_LIMIT``, with or
    without the arm's Jacobian getting near-singular), ``"collision"`` (the arm touched the container),
    ``"missed container"``), the measured ``tip [T, 3]``, the ``tracking_error [T]``
    (m), ``grasp_step`` and ``min_singular_value`` (of the arm's position Jacobian, over the run).
    """
    positions, rotations, suction = trajectory["positions"], trajectory["rotations"], trajectory["suction"]
    if not (len(positions) == len(rotations) == len(suction)) or positions.shape[1:] != (3,) or rotations.shape[1:] != (3, 3):
        raise ValueError("a trajectory needs positions [T, 3], rotations [T, 3, 3] and suction [T] of one length T")
    if not (np.isfinite(positions).all() and np.isfinite(rotations).all()):
        raise ValueError("the trajectory contains NaN or inf")
    tip, error = [], []
    grasp_step, collided, min_sv = None, False, np.inf
    for t in range(len(positions)):
        env.command(positions[t], rotations[t])
        if suction[t] and not env.holding():
            if env.suction_on() and grasp_step is None:
                grasp_step = t
        elif not suction[t] and env.holding():
            env.suction_off()
        pos, _ = env.ee_pose()
        tip.append(pos)
        error.append(float(np.linalg.norm(pos - positions[t])))
        collided = collided or env.arm_touches_container()
        min_sv = min(min_sv, env.arm_singular_value())
        if frames is not None and t % frame_every == 0:
            frames.append(env.render_view())
    env.hold(settle, positions[-1], rotations[-1])
    error = np.array(error)
    success = env.object_in_container()
    failure = None
    if not success:
        if grasp_step is None:
            failure = "not grasped"
        elif error.max() > TRACKING_LIMIT:
            failure = "near-singular" if min_sv < SINGULAR_LIMIT else "unreachable"
        elif collided:
            failure = "collision"
        else:
            failure = "missed container"
    return {
        "success": bool(success),
        "failure": failure,
        "tip": np.array(tip),
        "tracking_error": error,
        "grasp_step": grasp_step,
        "collided": bool(collided),
        "min_singular_value": float(min_sv),
    }
