"""Push-T behind the task contract: the env for a split, the seeded scene (configuration) of a split and index and
the scripted demonstrator. Keypoints are the env's observation (``obs["keypoints"]``, :mod:`.geometry`) and success
its ``info["is_success"]``.

Push-T is closed loop (a :class:`~kpflow.policies.base.Policy` acts on every observation): one trial is one
:func:`~kpflow.tasks.pusht.rollout.run_episode` (:class:`~kpflow.eval.episode_trial.EpisodeTrial`).
"""

from __future__ import annotations

from kpflow.policies.base import PolicyLayout

from .demonstrator import PushTExpert
from .env import ENV_SPLITS, PushTEnv
from .geometry import N_KEYPOINTS, N_T_KEYPOINTS
from .scene import Config, split_config, standard_config


class PushTTask:
    """``conditions``: Table 1's three splits and Diffusion Policy's ``standard`` protocol."""

    name = "pusht"
    conditions = ENV_SPLITS
    #: what its learned policies observe and return: 12 block, 12 goal and the agent's keypoints (px); agent targets
    policy_layout = PolicyLayout(
        N_KEYPOINTS, 2, 2,
        groups={"block": tuple(range(N_T_KEYPOINTS)), "goal": tuple(range(N_T_KEYPOINTS, 2 * N_T_KEYPOINTS)), "agent": (N_KEYPOINTS - 1,)},
        roles={"objects": ("block",), "goals": ("goal",), "robot": ("agent",)},
    )  # fmt: skip

    def make_env(self, condition: str = "in_distribution", **kwargs) -> PushTEnv:
        """The env of ``condition``'s workspace (``kwargs``: :class:`~.env.PushTEnv`'s options)."""
        return PushTEnv(split=condition, **kwargs)

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Config:
        """Configuration ``index`` of ``condition``; for ``standard`` the index is Diffusion Policy's env seed."""
        if condition == "standard":
            return standard_config(index)
        return split_config(condition, index, seed, goal="random")

    def demonstrator(self, config: Config) -> PushTExpert:
        """The scripted expert for ``config``'s workspace."""
        return PushTExpert(config.workspace)
