"""A goal within reach: a policy is shown its goal no farther from the object than ``reach``, on the way to the real one.

A policy learned from demonstrations has seen the goal only so far from the object (in the Push-T Table 1 store,
centroids 379 px apart at the 99th percentile of its chunks), while Push-T's object-OOD split starts the block up
to 953 px from the goal (median 494 px). Before the wrapped policy acts, the observation's goal keypoints ``g_j``
are translated towards the object, keeping the goal's orientation:

    g_j' = g_j + (min(1, r / |c_g - c_o|) - 1) (c_g - c_o),

with ``c_o`` and ``c_g`` the centroids of the object's and the goal's keypoints in the current observation and ``r``
the reach: the subgoal's centroid lies ``r`` from the object's on the line to the goal's. As the object comes within
``r`` of the goal the subgoal is the goal, and the policy acts exactly as it would unwrapped. With an observation
history, every frame's goal is moved by the current frame's translation (the goal does not move in an episode).
"""

from __future__ import annotations

import numpy as np

from ..tasks.base import Policy


def subgoal_shift(keypoints: np.ndarray, object: tuple[int, ...], goal: tuple[int, ...], reach: float) -> np.ndarray:
    """The translation ``[D]`` that brings the goal of one observation ``keypoints [K, D]`` to within ``reach`` of its
    object (zero when it is already): ``(min(1, r / |c_g - c_o|) - 1) (c_g - c_o)`` (module docstring)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    delta = kp[list(goal)].mean(0) - kp[list(object)].mean(0)
    distance = float(np.linalg.norm(delta))
    return (reach / distance - 1.0) * delta if distance > reach else np.zeros_like(delta)


class SubgoalPolicy:
    """``policy`` acting on observations whose goal is moved to within ``reach`` of the object (:func:`subgoal_shift`).

    Args:
        policy: the wrapped policy; it receives ``obs`` with ``"keypoints"`` (and ``"keypoints_history"`` when
            present) replaced, and nothing else changed.
        object: indices of the object's keypoints in an observation ``[K, D]``.
        goal: indices of the goal's keypoints.
        reach: the largest object-goal centroid distance the policy is shown (> 0, observation units: px in Push-T).
    """

    def __init__(self, policy: Policy, object: tuple[int, ...], goal: tuple[int, ...], reach: float) -> None:
        if isinstance(reach, bool) or not isinstance(reach, (int, float)) or not np.isfinite(reach) or reach <= 0:
            raise ValueError(f"reach must be a positive finite distance; got {reach!r}")
        if not object or not goal or set(object) & set(goal):
            raise ValueError(f"object and goal need >= 1 keypoint each and none in common; got {object} and {goal}")
        self.policy, self.object, self.goal, self.reach = policy, tuple(object), tuple(goal), float(reach)
        self.n_obs = int(getattr(policy, "n_obs", 1))  # the observation history the rollout must hand over

    def reset(self, seed: int | None = None) -> None:
        self.policy.reset(seed)

    def act(self, obs: dict) -> np.ndarray:
        """The wrapped policy's chunk for ``obs`` with its goal within reach."""
        current = obs["keypoints"] if "keypoints" in obs else np.asarray(obs["keypoints_history"])[-1]
        shift = subgoal_shift(current, self.object, self.goal, self.reach)
        shown = dict(obs)
        for key in ("keypoints", "keypoints_history"):
            if key in obs:
                shown[key] = np.array(obs[key], dtype=np.float64)
                shown[key][..., list(self.goal), :] += shift
        return self.policy.act(shown)
