"""A Gymnasium task of the user's own (the template reach_task, the own-task tutorial's): the closed loop, expert
collection into a store, and the closed-loop trial, on the task contract alone (kpflow.core.task.GymTask)."""

import sys

import numpy as np
import pytest

from kpflow.core.rollout import StopEpisode, rollout
from kpflow.core.task import scene_seed
from kpflow.data.episode_store import EpisodeStore
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.success import SuccessReport
from kpflow.eval.trials import run_trials
from kpflow.examples import TEMPLATES
from kpflow.tasks.collection import CollectRequest, collect_episodes

sys.path.insert(0, str(TEMPLATES / "reach_task"))  # as a project folder copied by kpflow-example
from reach import ReachTask  # noqa: E402


def test_the_expert_episode_records_what_it_saw_and_did():
    task = ReachTask()
    env = task.make_env("wide", render=True)
    episode = rollout(env, task.expert(), task.max_steps, 3, {"seed": 3}, ("keypoints",), render=True, action_dim=2)
    assert episode.success and episode.steps < task.max_steps and episode.decisions == -(-episode.steps // 8)
    assert episode.records["keypoints"].shape == (episode.steps, 5, 2) and episode.records["action"].shape == (
        episode.steps,
        2,
    )
    assert len(episode.frames) == episode.steps + 1 and episode.frames[0].shape == (96, 96, 3)
    again = rollout(task.make_env("wide"), task.expert(), task.max_steps, 3, {"seed": 3}, ("keypoints",))
    np.testing.assert_array_equal(again.records["keypoints"], episode.records["keypoints"])  # the seed is the scene


class _StopAfter:
    """A policy that walks right and ends the episode at its ``n``-th decision (a person pressing Enter)."""

    n_obs = 1

    def __init__(self, n: int):
        self.n, self.calls = n, 0

    def reset(self, seed=None):
        self.calls = 0

    def act(self, obs):
        self.calls += 1
        if self.calls == self.n:
            raise StopEpisode
        return obs["keypoints"][-1][None] + [[0.01, 0.0]]


class _TakeOver:
    """An override that takes steps 2 and 3 (the expert correcting), holding the agent where it is."""

    def start(self, env, obs, info, seed):
        self.started = True

    def act(self, step, obs):
        return obs["keypoints"][-1] if step in (2, 3) else None

    def update(self, step, info):
        pass


def test_the_loop_ends_on_a_stop_and_marks_what_an_override_took():
    task = ReachTask()
    stopped = rollout(task.make_env("default"), _StopAfter(4), 50, 0, {"seed": 0}, ("keypoints",))
    assert stopped.steps == 3 and stopped.decisions == 3 and not stopped.success  # one step per decision, then Enter
    override = _TakeOver()
    taken = rollout(task.make_env("default"), _StopAfter(6), 50, 0, {"seed": 0}, override=override)
    assert override.started and taken.overridden.tolist() == [
        False,
        False,
        True,
        True,
        False,
        False,
        False,
    ]  # 5 decisions
    with pytest.raises(ValueError, match="max_steps must be >= 1"):
        rollout(task.make_env("default"), _StopAfter(2), 0)


def test_collection_stores_the_experts_successes(tmp_path):
    summary = collect_episodes(ReachTask(), tmp_path / "demos.zarr", CollectRequest(4, progress=False))
    store = EpisodeStore(tmp_path / "demos.zarr")
    assert summary["episodes"] == store.n_episodes == 4 and summary["successes"] == summary["attempts"] == 4
    assert store.field("keypoints").shape[1:] == (5, 2) and dict(store.attrs) == {
        "task": "reach",
        "condition": "default",
    }


def test_the_generic_collection_refuses_what_it_cannot_honour_by_name(tmp_path):
    """kpflow-collect's one path: a task without a collector of its own gets the expert in one process; a policy,
    worker processes, videos or a task option are refused, naming them, before anything is written."""
    request = CollectRequest(2, workers=2, videos=1, options={"goal": "fixed"}, progress=False)
    with pytest.raises(ValueError, match="reach's collection .* takes no videos, workers, options.goal: drop them"):
        collect_episodes(ReachTask(), tmp_path / "demos.zarr", request)
    assert not (tmp_path / "demos.zarr").exists()
    with pytest.raises(ValueError, match="collects a Gymnasium task with an expert"):
        collect_episodes(object(), tmp_path / "demos.zarr", CollectRequest(2))


def test_the_trial_scores_a_policy_on_evaluation_seeds():
    task = ReachTask()
    trial = PolicyTrial(task, task.expert(), SuccessReport(), name="expert")
    result = trial.run("default", 2, {"policy": "expert"}, seed=0)
    assert result.success and result.failure is None and result.scene == {"seed": scene_seed(0, 1, 2)}
    streams = {(s, c, i): scene_seed(s, c, i) for s in range(3) for c in (1, 2) for i in range(3)}
    assert len(set(streams.values())) == len(streams)  # seed 1's scene 0 is not seed 0's scene 1; conditions apart
    assert min(streams.values()) > 1000  # far from the collection seeds (0, 1, 2, ...)
    with pytest.raises(ValueError, match="has no condition 'far'"):
        task.make_env("far")
    with pytest.raises(ValueError, match="runs Gymnasium tasks"):
        PolicyTrial(object(), task.expert(), SuccessReport())


def test_success_within_a_shorter_horizon_counts_the_episodes_that_succeeded_by_then(tmp_path):
    """One run reports success at another protocol's shorter horizon beside its own (MimicGen's 400 steps beside
    kpflow's 500): an episode ends at its success, so success within h is success in at most h steps."""
    task = ReachTask()
    first = run_trials(tmp_path / "all", PolicyTrial(task, task.expert(), SuccessReport(), name="expert"), "default", n_trials=6,
                       workers=1, videos=0, progress=False)  # fmt: skip
    steps = sorted(t["steps"] for t in first["trials"])
    h = steps[2]  # the third fastest: at least 3 of 6 succeeded by then
    report = SuccessReport(within=[h, steps[-1]])
    out = run_trials(tmp_path / "within", PolicyTrial(task, task.expert(), report, name="expert"), "default", n_trials=6, workers=1,
                     videos=0, progress=False)  # fmt: skip
    (row,) = out["summary"]
    assert row["successes"] == 6 and row[f"successes_within_{steps[-1]}"] == 6
    assert (
        row[f"successes_within_{h}"] == sum(s <= h for s in steps) < 6
        and row[f"success_within_{h}"] == row[f"successes_within_{h}"] / 6
    )
    assert out["metrics"][f"default/expert/success_within_{h}"] == row[f"success_within_{h}"]
    assert f"within {h} steps [95% CI]" in out["table"] and f"| {sum(s <= h for s in steps)}/6 = " in out["table"]
    with pytest.raises(ValueError, match="at least 1 control step"):
        SuccessReport(within=[0])
