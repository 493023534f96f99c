"""A policy's trial on a Gymnasium task: one closed-loop episode in a seeded evaluation scene.

``kpflow-evaluate`` runs it for Push-T (``experiment=pusht``) and for any :class:`~kpflow.core.task.GymTask` of
your own (``experiment=gym_policy task=<task>``). The task says everything task-specific
(:class:`~kpflow.core.task.GymTask`): which scene an index of a condition is and how the env is reset to it
(:meth:`~kpflow.core.task.GymTask.evaluation_scene`: by default the held-out seed stream, Push-T's configurations),
how many steps an episode may take and how it is scored; the episode is the one closed loop,
:func:`~kpflow.core.rollout.rollout`. Every episode gets a fresh env from the task, and the decisions are timed (``latency_ms``, the median). The scene recorded is the task's record with what the env
says of it at reset (``info["scene"]``, where it says anything).
"""

from __future__ import annotations

import time

import numpy as np

from kpflow.core.policy import Policy
from kpflow.core.rollout import rollout
from kpflow.core.task import GymTask, TrialResult
from kpflow.policies.settings import effective_settings


class TimedPolicy:
    """Wraps a policy and records how long each ``act`` takes (the decision latency)."""

    def __init__(self, policy: Policy):
        self.policy, self.latencies = policy, []
        self.n_obs = getattr(policy, "n_obs", 1)  # the observation history it conditions on (the loop reads it)

    def reset(self, seed=None):
        self.policy.reset(seed)

    def act(self, obs):
        start = time.perf_counter()
        out = self.policy.act(obs)
        self.latencies.append(time.perf_counter() - start)
        return out


class PolicyTrial:
    """Episodes of ``policy`` (labelled ``name``) on ``task``, scored by ``report``; at most ``max_steps`` steps
    (None: the task's own limit; a task may hold a condition to its protocol's, as Push-T's ``standard``)."""

    def __init__(self, task: GymTask, policy: Policy, report, name: str = "policy", max_steps: int | None = None):
        if not isinstance(task, GymTask):
            raise ValueError(
                f"a policy trial runs Gymnasium tasks (kpflow.core.task.GymTask), not {type(task).__name__}"
            )
        if max_steps is not None and max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.task, self.policy, self.report, self.policy_name = task, policy, report, str(name)
        self.max_steps = None if max_steps is None else int(max_steps)
        self.name, self.conditions, self.default_conditions = (
            task.name,
            tuple(task.conditions),
            tuple(task.default_conditions),
        )

    def variants(self) -> list[dict[str, str]]:
        return [{"policy": self.policy_name}]

    def setup(self) -> None:
        """One torch thread per worker (each episode makes its own env)."""
        import torch

        torch.set_num_threads(1)

    def run(
        self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None
    ) -> TrialResult:
        """Episode ``index`` of ``condition``; ``scores``: the task's (:meth:`~kpflow.core.task.GymTask.score`) and
        the median decision latency."""
        scene = self.task.evaluation_scene(condition, index, seed)
        env = self.task.make_env(condition, render=frames is not None)
        policy = TimedPolicy(self.policy)
        episode = rollout(env, policy, self.task.steps_limit(condition, self.max_steps), scene.policy_seed, scene.reset,
                          render=frames is not None, track=self.task.tracked, action_dim=int(np.prod(env.action_space.shape)))  # fmt: skip
        env.close()
        if frames is not None:
            frames.extend(episode.frames)
        success, failure, scores = self.task.score(episode)
        scores["latency_ms"] = 1e3 * float(np.median(policy.latencies)) if policy.latencies else float("nan")
        record = {**scene.record, **episode.first_info.get("scene", {})}
        return TrialResult(condition, index, dict(variant), record, success, failure, scores, {"episode": episode})

    def describe(self) -> dict:
        """The policy's name, the settings it acts with (:func:`~kpflow.policies.settings.effective_settings`),
        a transported one's resolved transport options (:class:`~kpflow.policies.config.TransportConfig`; nearest
        neighbour's and policy transportation's resolved search and fit under ``resolved``), each
        condition's step limit and the task's own description (:meth:`~kpflow.core.task.GymTask.describe`)."""
        limits = {c: self.task.steps_limit(c, self.max_steps) for c in self.conditions}
        out = {"policy": self.policy_name, "policy_settings": effective_settings(self.policy), "max_steps": limits}
        config = getattr(self.policy, "policy_config", None)  # a policy built from a checkpoint: what it resolved
        if config is not None and config.transport is not None:
            out["transport"] = config.transport.record()
        if resolved := getattr(self.policy, "resolved", None):  # a transporting policy's search and fit, as resolved
            out["resolved"] = dict(resolved)
        return {**out, **self.task.describe()}
