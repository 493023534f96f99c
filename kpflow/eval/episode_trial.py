"""Push-T's trial: one closed-loop episode of a policy in a seeded configuration.

The conditions are Table 1's splits, whose configurations are the seeded
:func:`~kpflow.tasks.pusht.scene.split_config` list (evaluation indices from 10000 on, so they differ from the
demonstrations' 0, 1, 2, ...), and Diffusion Policy's ``standard`` test protocol: its start-state draw
(:func:`~kpflow.tasks.pusht.scene.standard_config`) on seeds from 100000 (LeRobot's and DP's test seeds; 500 of
them, LeRobot's count, where DP used 50), the fixed goal and at most 300 steps. An episode runs until coverage 0.95
or the step limit; success at 0.85 means coverage reached 0.85 within the limit (the episode would have ended there
at that threshold). The standard score is the mean over episodes of max over steps of clip(coverage / 0.95, 0, 1)
(:class:`~kpflow.eval.reports.pusht.PushTReport`).
"""

from __future__ import annotations

import time

import numpy as np

from kpflow.policies.base import Policy
from kpflow.policies.settings import effective_settings
from kpflow.tasks.base import TrialResult
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import SPLITS, STANDARD_FIRST_SEED
from kpflow.tasks.pusht.task import PushTTask

THRESHOLDS = (0.85, 0.95)
FIRST_CONFIG = 10_000  # the first evaluation configuration of each split
STANDARD_EPISODES, STANDARD_MAX_STEPS = 500, 300  # Diffusion Policy's Push-T test protocol (LeRobot's 500 episodes)


def protocol_counts(n_configs: int, standard_episodes: int = STANDARD_EPISODES, standard_first_seed: int = STANDARD_FIRST_SEED):
    """``(n_trials, first_index)`` of :func:`~kpflow.eval.trials.run_trials`, per condition: ``n_configs`` configurations of each split from
    :data:`FIRST_CONFIG`, and ``standard_episodes`` standard episodes from ``standard_first_seed``."""
    n_trials = {**{s: n_configs for s in SPLITS}, "standard": standard_episodes}
    first_index = {**{s: FIRST_CONFIG for s in SPLITS}, "standard": standard_first_seed}
    return n_trials, first_index


class TimedPolicy:
    """Wraps a policy and records how long each ``act`` takes (the decision latency)."""

    def __init__(self, policy: Policy):
        self.policy, self.latencies = policy, []
        self.n_obs = getattr(policy, "n_obs", 1)  # the observation history it conditions on (run_episode reads it)

    def reset(self, seed=None):
        self.policy.reset(seed)

    def act(self, obs):
        start = time.perf_counter()
        out = self.policy.act(obs)
        self.latencies.append(time.perf_counter() - start)
        return out


class EpisodeTrial:
    """Episodes of ``policy`` (labelled ``name``) on ``task``, at most ``max_steps`` steps on the splits (300 on
    ``standard``, whatever ``max_steps`` says), scored by ``report``."""

    def __init__(self, policy: Policy, report, name: str = "policy", max_steps: int = 1200, task: PushTTask | None = None):
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.policy, self.report, self.policy_name, self.max_steps = policy, report, str(name), int(max_steps)
        self.task = task or PushTTask()
        self.name, self.conditions, self.default_conditions = self.task.name, (*SPLITS, "standard"), SPLITS

    def variants(self) -> list[dict[str, str]]:
        return [{"policy": self.policy_name}]

    def setup(self) -> None:
        """Nothing to build: each episode makes its env (the policy is inherited by forked workers)."""

    def steps_limit(self, condition: str) -> int:
        return STANDARD_MAX_STEPS if condition == "standard" else self.max_steps

    def run(self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None) -> TrialResult:
        """Episode ``index`` of ``condition`` (for ``standard`` the index is DP's env seed; the policy is reset with
        it); ``scores``: coverage, steps to each threshold and the median decision latency."""
        config = self.task.sample_scene(condition, index, seed)
        render = frames is not None
        env = self.task.make_env(condition, **({"render_size": 256, "render_mode": "rgb_array"} if render else {}))
        policy = TimedPolicy(self.policy)
        result = run_episode(env, policy, config, self.steps_limit(condition), seed=index, thresholds=THRESHOLDS, render=render)
        if render:
            frames.extend(result.frames)
        scores = {
            "success_085": result.first_step[0.85] is not None,
            "steps_085": result.first_step[0.85],
            "steps_095": result.first_step[0.95],
            "final_coverage": result.coverage,
            "max_coverage": result.max_coverage,
            "steps": result.steps,
            "latency_ms": 1e3 * float(np.median(policy.latencies)) if policy.latencies else float("nan"),
        }
        failure = None if result.success else "time limit"
        return TrialResult(condition, index, dict(variant), config.as_dict(), result.success, failure, scores, {"result": result})

    def describe(self) -> dict:
        """The policy's name and the settings it acts with (:func:`~kpflow.policies.settings.effective_settings`), and
        the step limit of each condition."""
        return {"policy": self.policy_name, "policy_settings": effective_settings(self.policy), "max_steps": {c: self.steps_limit(c) for c in self.conditions}}
