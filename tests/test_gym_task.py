"""A Gymnasium task of the user's own (examples/reach_task, the own-task tutorial's): the closed loop, expert
collection into a store, and the closed-loop trial, on the task contract alone (kpflow.tasks.base.GymTask)."""

import sys
from pathlib import Path

import numpy as np
import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.eval.gym_policy_trial import GymPolicyTrial, scene_seed
from kpflow.eval.reports.success import SuccessReport
from kpflow.tasks.gym_rollout import collect_gym_episodes, run_gym_episode

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "reach_task"))
from reach import ReachTask  # noqa: E402


def test_the_expert_episode_records_what_it_saw_and_did():
    task = ReachTask()
    env, frames = task.make_env("wide", render=True), []
    episode = run_gym_episode(env, task.expert(), seed=3, max_steps=task.max_steps, frames=frames)
    assert episode.success and episode.steps < task.max_steps and episode.decisions == -(-episode.steps // 8)
    assert episode.keypoints.shape == (episode.steps, 5, 2) and episode.actions.shape == (episode.steps, 2)
    assert len(frames) == episode.steps + 1 and frames[0].shape == (96, 96, 3)
    again = run_gym_episode(task.make_env("wide"), task.expert(), seed=3, max_steps=task.max_steps)
    np.testing.assert_array_equal(again.keypoints, episode.keypoints)  # the seed is the scene


def test_collection_stores_the_experts_successes(tmp_path):
    summary = collect_gym_episodes(ReachTask(), tmp_path / "demos.zarr", 4, progress=False)
    store = EpisodeStore(tmp_path / "demos.zarr")
    assert summary["episodes"] == store.n_episodes == 4 and summary["successes"] == summary["attempts"] == 4
    assert store.field("keypoints").shape[1:] == (5, 2) and dict(store.attrs) == {"task": "reach", "condition": "default"}


def test_the_trial_scores_a_policy_on_evaluation_seeds():
    task = ReachTask()
    trial = GymPolicyTrial(task, task.expert(), SuccessReport(), name="expert")
    result = trial.run("default", 2, {"policy": "expert"}, seed=0)
    assert result.success and result.failure is None and result.scene == {"seed": scene_seed(0, 1, 2)}
    streams = {(s, c, i): scene_seed(s, c, i) for s in range(3) for c in (1, 2) for i in range(3)}
    assert len(set(streams.values())) == len(streams)  # seed 1's scene 0 is not seed 0's scene 1; conditions apart
    assert min(streams.values()) > 1000  # far from the collection seeds (0, 1, 2, ...)
    with pytest.raises(ValueError, match="has no condition 'far'"):
        task.make_env("far")
    with pytest.raises(ValueError, match="runs Gymnasium tasks"):
        GymPolicyTrial(object(), task.expert(), SuccessReport())
