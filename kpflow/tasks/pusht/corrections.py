"""Interactive corrections (data aggregation, DAgger-like): a policy runs, the scripted expert steps in when it fails.

:func:`corrected_episode` runs a policy on Push-T and hands control to :class:`PushTExpert` for a fixed number of
steps whenever the policy is stuck (no coverage progress) or drives the agent out of the training region; only the
expert's steps are recorded. :func:`collect_corrections` repeats this over rounds, each round's policy built from the
store as grown by the previous rounds, and appends the expert's segments to the store as new episodes.
"""

from __future__ import annotations

import os
from typing import Callable

import numpy as np
from tqdm import tqdm

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import Config, split_config
from kpflow.tasks.pusht.task import PushTTask

#: Correction round ``r`` uses configuration indices ``CONFIG_OFFSET * (r + 1) + e``: never a demonstration's
#: (those count up from 0) and never another round's.
CONFIG_OFFSET = 1_000_000


def _check_budgets(max_steps: int, stuck_steps: int, takeover_steps: int) -> None:
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if stuck_steps < 1 or takeover_steps < 1:
        raise ValueError(f"stuck_steps and takeover_steps must be >= 1, got {stuck_steps} and {takeover_steps}")


class Takeover:
    """The expert's override of :func:`~kpflow.tasks.pusht.rollout.run_episode` (see :func:`corrected_episode`).

    Before a policy step it takes over for ``takeover_steps`` steps when the best coverage has not risen by
    ``min_progress`` in the last ``stuck_steps`` steps (counted from the start or from its last hand-back), or when
    the agent is outside the training region. It resets the expert at each takeover (seeded from the episode's
    seed and the takeover count) and counts ``n_takeovers`` and ``steps``.
    """

    def __init__(self, expert: PushTExpert, stuck_steps: int, takeover_steps: int, min_progress: float = 0.01):
        self.expert, self.stuck_steps, self.takeover_steps, self.min_progress = (
            expert,
            stuck_steps,
            takeover_steps,
            min_progress,
        )

    def start(self, env: PushTEnv, obs: dict, info: dict, seed: int | None) -> None:
        if self.expert.workspace.name != env.workspace.name:
            raise ValueError(
                f"the expert's workspace {self.expert.workspace.name!r} is not the env's {env.workspace.name!r}"
            )
        self.region, self.seed = float(env.workspace.region), seed
        self.best = self.reference = float(info["coverage"])
        self.last_progress = 0  # step at which the best coverage last rose by min_progress (or the expert handed back)
        self.left = self.n_takeovers = self.steps = 0

    def act(self, step: int, obs: dict) -> np.ndarray | None:
        if not self.left and (_wandered(obs, self.region) or step - self.last_progress >= self.stuck_steps):
            self.expert.reset(None if self.seed is None else self.seed * 1_009 + self.n_takeovers)
            self.left, self.n_takeovers = self.takeover_steps, self.n_takeovers + 1
        if not self.left:
            return None
        action = np.asarray(self.expert.act(obs), dtype=np.float64)
        self.left -= 1
        self.steps += 1
        if not self.left:  # hand back: the policy gets a fresh stuck budget
            self.reference, self.last_progress = self.best, step + 1
        return action

    def update(self, step: int, info: dict) -> None:
        self.best = max(self.best, float(info["coverage"]))
        if self.best >= self.reference + self.min_progress:
            self.reference, self.last_progress = self.best, step + 1


def _wandered(obs: dict, region: float) -> bool:
    """The agent is outside the training region ``[0, region]^2``."""
    agent = np.asarray(obs["agent_pos"], float)
    return bool(np.any(agent < 0.0) or np.any(agent > region))


def _segments(episode: dict[str, np.ndarray], overridden: np.ndarray) -> list[dict[str, np.ndarray]]:
    """The contiguous runs of overridden steps of a recorded episode, each ``{field: [T, ...]}``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], overridden.astype(np.int8), [0]])))
    return [{k: v[a:b] for k, v in episode.items()} for a, b in zip(edges[::2], edges[1::2])]


def corrected_episode(
    env: PushTEnv,
    policy,
    expert: PushTExpert,
    config: Config,
    max_steps: int,
    stuck_steps: int = 30,
    takeover_steps: int = 40,
    min_progress: float = 0.01,
    seed: int | None = None,
) -> tuple[list[dict[str, np.ndarray]], dict]:
    """Run ``policy`` on ``config`` with the expert taking over when it fails; record the expert's steps.

    The episode is :func:`~kpflow.tasks.pusht.rollout.run_episode`'s, with a :class:`Takeover` as its override:
    the policy's chunks are executed open loop; before each policy step, the expert takes over for
    ``takeover_steps`` steps when

    * the policy is stuck: the best coverage so far has not risen by ``min_progress`` in the last ``stuck_steps``
      steps (counted from the start, or from the expert's last hand-back), or
    * the agent is outside the training region ``[0, workspace.region]^2`` (a policy wandering off; a
      configuration that starts there is handed to the expert at once).

    The expert is reset (seeded from ``seed`` and the takeover count) at each takeover; on hand-back the rest of
    the policy's chunk is dropped. The episode stops at success (``env`` terminated) or after ``max_steps``.

    Returns:
        ``segments``: the expert's contiguous runs of steps, each ``{field: float32 [T, ...]}`` with the
        observation before each action (``RECORDED_FIELDS``) and ``action``; back-to-back takeovers (no policy
        step in between) share one segment. ``info``: ``success``, ``steps``, ``n_takeovers``,
        ``expert_steps``, ``coverage`` (final) and ``max_coverage``.
    """
    _check_budgets(max_steps, stuck_steps, takeover_steps)
    takeover = Takeover(expert, stuck_steps, takeover_steps, min_progress)
    result = run_episode(env, policy, config, max_steps, seed=seed, record=True, override=takeover)
    info = {
        "success": result.success,
        "steps": result.steps,
        "n_takeovers": takeover.n_takeovers,
        "expert_steps": takeover.steps,
        "coverage": result.coverage,
        "max_coverage": result.max_coverage,
    }
    return _segments(result.episode, result.overridden), info


def _next_round(store: EpisodeStore) -> int:
    """One past the last correction round already in ``store`` (0 for a store of demonstrations only)."""
    rounds = [store.episode_attrs(i).get("round", -1) for i in range(len(store))]
    sources = [store.episode_attrs(i).get("source") for i in range(len(store))]
    return 1 + max((r for r, s in zip(rounds, sources) if s == "correction"), default=-1)


def collect_corrections(
    store_path: str | os.PathLike,
    make_policy: Callable[[EpisodeStore], object],
    rounds: int,
    episodes_per_round: int,
    split: str = "in_distribution",
    goal: str = "random",
    seed: int = 0,
    max_steps: int = 600,
    stuck_steps: int = 30,
    takeover_steps: int = 40,
    progress: bool = True,
) -> list[dict]:
    """Grow the store at ``store_path`` with expert corrections of a policy trained on it, round by round.

    Each round builds the policy once from the store's current data (``make_policy(store)``), runs
    ``episodes_per_round`` :func:`corrected_episode` on fresh configurations of ``split`` (indices
    ``CONFIG_OFFSET * (round + 1) + e``; rounds continue numbering after those already in the store), and appends
    every expert segment of at least 2 steps as a new episode (attrs ``source="correction"``, ``round``,
    ``config_index``, ``segment``, ``success``).

    Returns one dict per round: ``round``, ``episodes``, ``successes`` (policy plus expert),
    ``policy_successes`` (no takeover), ``takeovers``, ``expert_steps``, ``episodes_added``, ``chunks_added``
    (expert steps added to the store, one action chunk each) and ``dataset_steps`` after the round.
    """
    if rounds < 1 or episodes_per_round < 1:
        raise ValueError(f"rounds and episodes_per_round must be >= 1, got {rounds} and {episodes_per_round}")
    store = EpisodeStore(store_path, mode="a")
    if not len(store):
        raise ValueError(f"{store_path} holds no episodes: collect demonstrations first")
    env = PushTEnv(split=split, goal=goal)
    first = _next_round(store)
    reports = []
    bar = tqdm(total=rounds * episodes_per_round, desc="corrections", unit="ep", disable=not progress)
    try:
        for r in range(first, first + rounds):
            policy = make_policy(store)
            report = dict(
                round=r,
                episodes=0,
                successes=0,
                policy_successes=0,
                takeovers=0,
                expert_steps=0,
                episodes_added=0,
                chunks_added=0,
            )
            for e in range(episodes_per_round):
                index = CONFIG_OFFSET * (r + 1) + e
                config = split_config(split, index, seed, goal)
                expert = PushTTask().demonstrator(config)
                ep_seed = seed * 100_003 + index
                segments, info = corrected_episode(
                    env, policy, expert, config, max_steps, stuck_steps, takeover_steps, seed=ep_seed
                )
                for k, segment in enumerate(segments):
                    n = len(segment["action"])
                    if n < 2:
                        continue
                    attrs = {
                        "source": "correction",
                        "round": r,
                        "config_index": index,
                        "segment": k,
                        "success": info["success"],
                        "steps": n,
                    }
                    store.add_episode(segment, attrs=attrs)
                    report["episodes_added"] += 1
                    report["chunks_added"] += n
                report["episodes"] += 1
                report["successes"] += info["success"]
                report["policy_successes"] += info["success"] and not info["n_takeovers"]
                report["takeovers"] += info["n_takeovers"]
                report["expert_steps"] += info["expert_steps"]
                bar.update(1)
                bar.set_postfix(round=r, success=f"{report['successes']}/{report['episodes']}", steps=store.n_steps)
            report["dataset_steps"] = store.n_steps
            reports.append(report)
    finally:
        bar.close()
        store.close()  # the next round (or caller) opens the store for writing again
    return reports
