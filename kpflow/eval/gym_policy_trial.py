"""A Gymnasium task's policy trial: one closed-loop episode of a policy in a seeded scene of a
:class:`~kpflow.tasks.base.GymTask` (``kpflow-evaluate experiment=gym_policy task=<task> policy=kcfm ...``).

Scene ``i`` of a condition is the env's ``reset(seed=s)`` with ``s`` 32 bits of numpy's ``SeedSequence((EVAL_SEED +
seed, c, i))``, ``c`` the condition's number (from 1): the same key Push-T's splits and the robosuite tasks seed their
scenes with (:func:`scene_seed`). Each run seed has its own stream (seed 1's scene 0 is not seed 0's scene 1), each
condition its own, and none meets the seeds ``kpflow-collect`` draws demonstrations with (0, 1, 2, ...) but by a
2^-32 chance. Success is the env's ``info["is_success"]`` within the task's ``max_steps``.
"""

from __future__ import annotations

import numpy as np

from kpflow.policies.base import Policy
from kpflow.policies.settings import effective_settings
from kpflow.tasks.base import GymTask, TrialResult
from kpflow.tasks.rollout import rollout

EVAL_SEED = 1_000_000


def scene_seed(seed: int, condition: int, index: int) -> int:
    """The reset seed of evaluation scene ``index`` of condition number ``condition`` for run ``seed`` (module
    docstring)."""
    return int(np.random.SeedSequence([EVAL_SEED + int(seed), int(condition), int(index)]).generate_state(1)[0])


class GymPolicyTrial:
    """Episodes of ``policy`` (labelled ``name``) on ``task``, scored by ``report`` (at most ``max_steps`` steps; the
    task's own limit when None)."""

    def __init__(self, task: GymTask, policy: Policy, report, name: str = "policy", max_steps: int | None = None):
        if not isinstance(task, GymTask):
            raise ValueError(f"experiment=gym_policy runs Gymnasium tasks (kpflow.tasks.base.GymTask), not {type(task).__name__}")
        self.task, self.policy, self.report, self.policy_name = task, policy, report, str(name)
        self.max_steps = int(task.max_steps if max_steps is None else max_steps)
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        self.name, self.conditions, self.default_conditions = task.name, tuple(task.conditions), tuple(task.conditions)
        self.envs: dict = {}

    def variants(self) -> list[dict[str, str]]:
        return [{"policy": self.policy_name}]

    def setup(self) -> None:
        import torch

        torch.set_num_threads(1)

    def run(self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None) -> TrialResult:
        key = (condition, frames is not None)
        if key not in self.envs:
            self.envs[key] = self.task.make_env(condition, render=frames is not None)
        reset_seed = scene_seed(seed, self.conditions.index(condition) + 1, index)
        env = self.envs[key]
        episode = rollout(env, self.policy, self.max_steps, reset_seed, {"seed": reset_seed}, render=frames is not None,
                          action_dim=int(np.prod(env.action_space.shape)))  # fmt: skip
        if frames is not None:
            frames.extend(episode.frames)
        failure = None if episode.success else "time limit"
        scores = {"steps": episode.steps, "decisions": episode.decisions}
        return TrialResult(condition, index, dict(variant), {"seed": reset_seed}, episode.success, failure, scores)

    def describe(self) -> dict:
        return {"policy": self.policy_name, "policy_settings": effective_settings(self.policy), "max_steps": self.max_steps}
