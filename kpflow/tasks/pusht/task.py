"""Push-T behind the task contract (:class:`~kpflow.core.task.GymTask`): the env for a condition, the seeded
configuration of a condition and index, the scripted demonstrator, and how an episode is scored.

The conditions are Table 1's splits, whose configurations are the seeded :func:`~.scene.split_config` list
(evaluation indices from :data:`FIRST_CONFIG` on, so they differ from the demonstrations' 0, 1, 2, ...), and
Diffusion Policy's ``standard`` test protocol: its start-state draw (:func:`~.scene.standard_config`) on seeds from
100000 (LeRobot's and DP's test seeds; 500 of them, LeRobot's count, where DP used 50), the fixed goal and at most
300 steps. An episode runs until coverage 0.95 or the step limit; success at 0.85 means coverage reached 0.85 within
the limit (the episode would have ended there at that threshold). The standard score is the mean over episodes of max
over steps of clip(coverage / 0.95, 0, 1) (:class:`~kpflow.eval.reports.pusht.PushTReport`). Keypoints are the
env's observation (``obs["keypoints"]``, :mod:`.geometry`) and success its ``info["is_success"]``.
"""

from __future__ import annotations

from kpflow.core.policy import PolicyLayout
from kpflow.core.rollout import Episode
from kpflow.core.task import EvaluationScene, GymTask

from .demonstrator import PushTExpert
from .env import ENV_SPLITS, PushTEnv
from .geometry import N_KEYPOINTS, N_T_KEYPOINTS
from .registration import registered_steps
from .rollout import coverage_summary
from .scene import SPLITS, STANDARD_FIRST_SEED, Config, split_config, standard_config

THRESHOLDS = (0.85, 0.95)  # coverage: Table 1's success, and Diffusion Policy's
FIRST_CONFIG = 10_000  # the first evaluation configuration of each split
STANDARD_EPISODES = (
    500  # Diffusion Policy's Push-T test protocol (LeRobot's 500 episodes; 300 steps each: registration.py)
)


def protocol_counts(
    n_configs: int, standard_episodes: int = STANDARD_EPISODES, standard_first_seed: int = STANDARD_FIRST_SEED
):
    """``(n_trials, first_index)`` of :func:`~kpflow.eval.trials.run_trials`, per condition: ``n_configs``
    configurations of each split from :data:`FIRST_CONFIG`, and ``standard_episodes`` standard episodes from
    ``standard_first_seed``."""
    n_trials = {**{s: n_configs for s in SPLITS}, "standard": standard_episodes}
    first_index = {**{s: FIRST_CONFIG for s in SPLITS}, "standard": standard_first_seed}
    return n_trials, first_index


class PushTTask(GymTask):
    """``conditions``: Table 1's three splits (the default ones) and Diffusion Policy's ``standard`` protocol."""

    name = "pusht"
    conditions = ENV_SPLITS
    default_conditions = SPLITS
    max_steps = registered_steps(
        "in_distribution"
    )  # on the splits (the registered ids'); ``standard``: its own, whatever is asked
    tracked = ("coverage",)
    #: what its learned policies observe and return: 12 block, 12 goal and the agent's keypoints (px); agent targets
    policy_layout = PolicyLayout(
        N_KEYPOINTS, 2, 2,
        groups={"block": tuple(range(N_T_KEYPOINTS)), "goal": tuple(range(N_T_KEYPOINTS, 2 * N_T_KEYPOINTS)), "agent": (N_KEYPOINTS - 1,)},
        roles={"objects": ("block",), "goals": ("goal",), "robot": ("agent",)},
        transport={"fit_on": ["objects", "robot"], "search": {"stuck_decisions": 5}},  # the map on the block and the agent (the goal is
        # matched by the search); a block that moved < 2 px over 5 decisions counts as stuck (results/pusht_standard.md)
    )  # fmt: skip

    def make_env(self, condition: str = "in_distribution", render: bool = False, **kwargs) -> PushTEnv:
        """The env of ``condition``'s workspace (``render``: 256-px RGB frames; ``kwargs``: :class:`~.env.PushTEnv`'s
        options)."""
        return PushTEnv(
            split=condition, **({"render_size": 256, "render_mode": "rgb_array"} if render else {}), **kwargs
        )

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Config:
        """Configuration ``index`` of ``condition``; for ``standard`` the index is Diffusion Policy's env seed."""
        if condition == "standard":
            return standard_config(index)
        return split_config(condition, index, seed, goal="random")

    def evaluation_scene(self, condition: str, index: int, seed: int) -> EvaluationScene:
        """Configuration ``index`` of ``condition`` (:meth:`sample_scene`), the policy reset with ``index`` (for
        ``standard``: Diffusion Policy's env seed)."""
        config = self.sample_scene(condition, index, seed)
        return EvaluationScene({"options": {"config": config}}, index, config.as_dict())

    def steps_limit(self, condition: str, max_steps: int | None = None) -> int:
        """The registered limit on ``standard`` (Diffusion Policy's protocol: 300), else ``max_steps`` (None: the
        split's registered limit, 1200; :func:`~.registration.registered_steps`)."""
        if condition == "standard" or max_steps is None:
            return registered_steps(condition)
        return int(max_steps)

    def score(self, episode: Episode) -> tuple[bool, str | None, dict]:
        """Success, and the coverage scores: whether 0.85 was reached, the first step reaching each threshold (None:
        never), the final and the largest coverage, the steps taken."""
        first, final, best = coverage_summary(episode, THRESHOLDS)
        scores = {
            "success_085": first[0.85] is not None,
            "steps_085": first[0.85],
            "steps_095": first[0.95],
            "final_coverage": final,
            "max_coverage": best,
            "steps": episode.steps,
        }
        return episode.success, None if episode.success else "time limit", scores

    def demonstrator(self, config: Config) -> PushTExpert:
        """The scripted expert for ``config``'s workspace."""
        return PushTExpert(config.workspace)

    def collect(self, store_path, request) -> dict:
        """Push-T's collector (:func:`~.collection.collect_pusht`, for :func:`~kpflow.tasks.collection.collect_episodes`):
        the condition is the split (None: ``in_distribution``; ``standard`` with a policy), ``options.goal``
        ``random`` (default) or ``fixed``; ``max_steps`` 600, ``workers`` 2 and ``videos`` 2 where the request
        leaves them None. An unknown option is refused by name."""
        from .collection import collect_pusht

        options = {k: v for k, v in dict(request.options).items() if v is not None}
        if unknown := sorted(set(options) - {"goal"}):
            raise ValueError(
                f"Push-T's collection has no option {', '.join(unknown)}; its option is goal (random | fixed)"
            )
        return collect_pusht(
            store_path,
            n_episodes=request.n_episodes,
            split=request.condition or "in_distribution",
            goal=options.get("goal", "random"),
            seed=request.seed,
            max_steps=600 if request.max_steps is None else request.max_steps,
            workers=2 if request.workers is None else request.workers,
            keep_failures=request.keep_failures,
            videos=2 if request.videos is None else request.videos,
            video_dir=request.video_dir,
            progress=request.progress,
            policy=request.policy,
            source=request.source,
            first_index=request.first_index,
        )
