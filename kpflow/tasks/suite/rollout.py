"""One closed-loop episode of a policy on a robosuite benchmark task.

At every control step the task's policy keypoints are observed (:func:`~.keypoints.policy_keypoints`): the
gripper's from the robot, the objects' from ``perception`` (the simulator's at every step; a camera's at the steps
whose observations a decision reads, the last ``n_obs`` before the action queue runs dry, held in between; an
object the cameras cannot place in a read keeps its last seen pose; the object picked, once the jaws close on it, is
carried with them from where it was last seen) and the policy acts through :class:`~kpflow.policies.base.ClosedLoop` (its observation history and action queue). Each action is an
end-effector target ``[10]``: position, 6-D rotation (:func:`kpflow.geometry.rotations.rot6d_to_matrix`) and the gripper
(closed when > 0). The episode ends at robosuite's success or after ``max_steps``.
"""

from __future__ import annotations

from dataclasses import dataclass

from kpflow.geometry.rotations import rot6d_to_matrix
from kpflow.policies.base import ClosedLoop, Policy

from .env import CLOSED, OPEN, SuiteEnv
from .keypoints import SimulatorPoses, policy_keypoints, policy_objects

ACTION_DIM = 10


@dataclass(frozen=True)
class PolicyEpisode:
    """``success``, the control ``steps`` taken, the ``decisions`` (chunks asked for), the ``unseen`` reads that
    could not place an object (the poses last seen were kept) and the ``failure`` (None, ``"time limit"``, or
    ``"not perceived"``: the objects were never placed)."""

    success: bool
    steps: int
    decisions: int
    unseen: int = 0
    failure: str | None = None


def run_policy_episode(env: SuiteEnv, policy: Policy, scene, max_steps: int, seed: int = 0, frames: list | None = None,
                       frame_every: int = 2, perception=None) -> PolicyEpisode:  # fmt: skip
    """Run ``policy`` in ``scene`` (module docstring); ``perception`` reads the objects' poses
    (:class:`~.keypoints.SimulatorPoses` when None; reseeded with ``seed``)."""
    env.reset_to(scene)
    perception = SimulatorPoses() if perception is None else perception
    perception.reseed(seed)
    loop = ClosedLoop(policy, ACTION_DIM)
    loop.reset(seed)
    steps, poses, names, unseen, closed = 0, None, policy_objects(env.spec), 0, False
    while steps < max_steps:
        if poses is None or perception.per_step or len(loop.queue) < loop.n_obs:
            try:
                poses = perception.poses(env, env.spec, names)
            except ValueError:  # an object hidden (by the arm, the jaws) in this read: keep what was seen last
                unseen += 1
                if poses is None:
                    return PolicyEpisode(False, steps, loop.decisions, unseen, "not perceived")
        obs = {"keypoints": policy_keypoints(env, env.spec, poses)}
        loop.observe(obs)
        action = loop.action(obs)
        closing, target = bool(action[9] > 0), (action[:3], rot6d_to_matrix(action[3:9]))
        if closing and not closed:  # the jaws close on the object to pick: a camera carries its pose with them
            perception.grasped(env, env.spec.grasp, target)
        elif closed and not closing:
            perception.released(env.spec.grasp)
        closed = closing
        env.command(*target, CLOSED if closing else OPEN)
        steps += 1
        if frames is not None and steps % frame_every == 0:
            frames.append(env.render_view())
        if env.success():
            return PolicyEpisode(True, steps, loop.decisions, unseen)
    return PolicyEpisode(False, steps, loop.decisions, unseen, "time limit")
