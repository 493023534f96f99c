"""One closed-loop episode of a policy on a robosuite benchmark task.

At every control step the task's policy keypoints are observed (:func:`~.keypoints.policy_keypoints`); when the
last chunk is used up, the policy (:class:`~kpflow.tasks.base.Policy`) is asked for the next from the last
``n_obs`` observations, oldest first (the first one repeated at the start, as in training). Each action is an
end-effector target ``[10]``: position, 6-D rotation (:func:`kpflow.rotations.rot6d_to_matrix`) and the gripper
(closed when > 0). The episode ends at robosuite's success or after ``max_steps``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from kpflow.rotations import rot6d_to_matrix
from kpflow.tasks.base import Policy

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
    policy.reset(seed)
    n_obs = int(getattr(policy, "n_obs", 1))
    history: deque = deque(maxlen=n_obs)
    steps = decisions = 0
    chunk: list = []
    while steps < max_steps:
        keypoints = policy_keypoints(env, env.spec)
        history.append(keypoints)
        if not chunk:
            frames_seen = [history[0]] * (n_obs - len(history)) + list(history)
            actions = np.asarray(policy.act({"keypoints": keypoints, "keypoints_history": np.stack(frames_seen)}), float)
            if actions.ndim != 2 or actions.shape[1] != ACTION_DIM or not np.isfinite(actions).all():
                raise ValueError(f"a robosuite policy returns finite chunks [H, {ACTION_DIM}]; got {actions.shape}")
            chunk, decisions = list(actions), decisions + 1
        action = chunk.pop(0)
        env.command(action[:3], rot6d_to_matrix(action[3:9]), CLOSED if action[9] > 0 else OPEN)
        steps += 1
        if frames is not None and steps % frame_every == 0:
            frames.append(env.render_view())
        if env.success():
            return PolicyEpisode(True, steps, decisions)
    return PolicyEpisode(False, steps, decisions)
