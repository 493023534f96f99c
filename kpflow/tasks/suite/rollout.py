"""One closed-loop episode of a policy on a robosuite benchmark task.

At every control step the task's policy keypoints are observed (:func:`~.keypoints.policy_keypoints`) and the
policy acts through :class:`~kpflow.policies.base.ClosedLoop` (its observation history and action queue). Each action is an
end-effector target ``[10]``: position, 6-D rotation (:func:`kpflow.rotations.rot6d_to_matrix`) and the gripper
(closed when > 0). The episode ends at robosuite's success or after ``max_steps``.
"""

from __future__ import annotations

from dataclasses import dataclass

from kpflow.policies.base import ClosedLoop, Policy
from kpflow.rotations import rot6d_to_matrix

from .env import CLOSED, OPEN, SuiteEnv
from .keypoints import policy_keypoints

ACTION_DIM = 10


@dataclass(frozen=True)
class PolicyEpisode:
    """``success``, the control ``steps`` taken and the ``decisions`` (chunks asked for)."""

    success: bool
    steps: int
    decisions: int


def run_policy_episode(env: SuiteEnv, policy: Policy, scene, max_steps: int, seed: int = 0, frames: list | None = None,
                       frame_every: int = 2) -> PolicyEpisode:  # fmt: skip
    """Run ``policy`` in ``scene`` (module docstring)."""
    env.reset_to(scene)
    loop = ClosedLoop(policy, ACTION_DIM)
    loop.reset(seed)
    steps = 0
    while steps < max_steps:
        obs = {"keypoints": policy_keypoints(env, env.spec)}
        loop.observe(obs)
        action = loop.action(obs)
        env.command(action[:3], rot6d_to_matrix(action[3:9]), CLOSED if action[9] > 0 else OPEN)
        steps += 1
        if frames is not None and steps % frame_every == 0:
            frames.append(env.render_view())
        if env.success():
            return PolicyEpisode(True, steps, loop.decisions)
    return PolicyEpisode(False, steps, loop.decisions)
