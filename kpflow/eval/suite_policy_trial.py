"""A robosuite benchmark task's policy trial: one closed-loop episode of a trained policy in a seeded scene.

The conditions are the task's variants (``d0``: robosuite's placement as it ships; ``wide``). Scenes come from
the evaluation seed stream ``EVAL_SEED + seed``, which neither the source demonstrations (``SOURCE_SEED``) nor the
generated ones (``seed``) use. Success is robosuite's own check within ``max_steps`` control steps. The objects'
keypoints come from the task's perception (``keypoints=sim`` or ``keypoints=camera``).
"""

from __future__ import annotations

from kpflow.policies.base import Policy
from kpflow.policies.settings import effective_settings
from kpflow.tasks.base import TrialResult
from kpflow.tasks.suite.rollout import run_policy_episode
from kpflow.tasks.suite.task import SuiteTask

EVAL_SEED = 20_000


class SuitePolicyTrial:
    """Episodes of ``policy`` (labelled ``name``) on ``task``, at most ``max_steps`` steps, scored by ``report``."""

    def __init__(self, task: SuiteTask, policy: Policy, report, name: str = "policy", max_steps: int = 500):
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.task, self.policy, self.report, self.policy_name, self.max_steps = task, policy, report, str(name), int(max_steps)
        self.name, self.conditions, self.default_conditions = task.name, tuple(task.variants), tuple(task.variants)
        self.env = None

    def variants(self) -> list[dict[str, str]]:
        return [{"policy": self.policy_name}]

    def setup(self) -> None:
        import torch

        torch.set_num_threads(1)
        self.env = self.task.make_env(render=True)

    def run(self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None) -> TrialResult:
        scene = self.task.sample_scene(self.env, condition, index, EVAL_SEED + seed)
        episode = run_policy_episode(self.env, self.policy, scene, self.max_steps, seed=index, frames=frames, perception=self.task.perception)
        scores = {"steps": episode.steps, "decisions": episode.decisions, "unseen_reads": episode.unseen}
        failure = episode.failure
        return TrialResult(condition, index, dict(variant), scene.as_dict(), episode.success, failure, scores)

    def describe(self) -> dict:
        return {"policy": self.policy_name, "policy_settings": effective_settings(self.policy), "max_steps": self.max_steps,
                "keypoints": self.task.keypoints.kind}  # fmt: skip
