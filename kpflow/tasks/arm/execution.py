"""Running an end-effector :class:`~kpflow.trajectory.Trajectory` on a :class:`~kpflow.tasks.arm.env.SuctionArmEnv`
and recording how the arm followed it."""

from __future__ import annotations

import numpy as np

from kpflow.trajectory import Trajectory

TRACKING_LIMIT = 0.03  # m: a larger error between target and tip means the arm could not follow
SINGULAR_LIMIT = 0.02  # smallest singular value of the arm's Jacobian below which a configuration is near-singular


def follow(
    env,
    trajectory: Trajectory,
    settle: int = 20,
    touching: set[int] = frozenset(),
    frames: list | None = None,
    frame_every: int = 2,
) -> dict:
    """Command each step of ``trajectory`` on ``env`` (after ``reset_to``), then hold the last pose ``settle`` steps.

    While ``grasp`` is on, the cup seals as soon as an object is within reach; when it goes off, the object is let
    go. Returns the measured ``tip [T, 3]``, the ``tracking_error [T]`` (m), ``grasp_step`` (None if nothing was
    sealed), ``grasped`` (the object sealed first), ``collided`` (the arm touched one of the geoms ``touching``) and
    ``min_singular_value`` (of the arm's Jacobian, over the run). Appends a side-view frame every ``frame_every``
    steps to ``frames`` if given.
    """
    if not isinstance(trajectory, Trajectory):
        raise ValueError(f"follow needs a kpflow.trajectory.Trajectory, got {type(trajectory).__name__}")
    positions, rotations, grasp = trajectory.positions, trajectory.rotations, trajectory.grasp
    tip, error = [], []
    grasp_step, grasped, collided, min_sv = None, None, False, np.inf
    for t in range(len(positions)):
        env.command(positions[t], rotations[t])
        if grasp[t] and not env.holding():
            if env.suction_on() and grasp_step is None:
                grasp_step, grasped = t, env.held_object()
        elif not grasp[t] and env.holding():
            env.suction_off()
        pos, _ = env.ee_pose()
        tip.append(pos)
        error.append(float(np.linalg.norm(pos - positions[t])))
        collided = collided or (bool(touching) and env.arm_touches(touching))
        min_sv = min(min_sv, env.arm_singular_value())
        if frames is not None and t % frame_every == 0:
            frames.append(env.render_view())
    env.hold(settle, positions[-1], rotations[-1])
    return {
        "tip": np.array(tip),
        "tracking_error": np.array(error),
        "grasp_step": grasp_step,
        "grasped": grasped,
        "collided": bool(collided),
        "min_singular_value": float(min_sv),
    }


def arm_failure(run: dict) -> str | None:
    """The arm's share of a failed run from :func:`follow`: ``"not grasped"``, ``"near-singular"`` or ``"unreachable"``
    (tracking error above ``TRACKING_LIMIT``, with or without the Jacobian getting near-singular), ``"collision"``,
    or None when the arm did what it was told."""
    if run["grasp_step"] is None:
        return "not grasped"
    if run["tracking_error"].max() > TRACKING_LIMIT:
        return "near-singular" if run["min_singular_value"] < SINGULAR_LIMIT else "unreachable"
    if run["collided"]:
        return "collision"
    return None
