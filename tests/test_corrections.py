"""Interactive corrections on Push-T: expert takeovers, recorded segments, and rounds that grow the store."""

import numpy as np
import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.policies.nearest import NearestNeighbourPolicy
from kpflow.tasks.pusht import PushTEnv, split_config
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.corrections import CONFIG_OFFSET, collect_corrections, corrected_episode
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.geometry import PUSHT_BLOCK, pusht_weights
from kpflow.tasks.pusht.rollout import RECORDED_FIELDS


class HoldStill:
    """Does nothing: targets the agent's own position, one step at a time."""

    def reset(self, seed=None):
        pass

    def act(self, obs):
        return np.asarray(obs["agent_pos"], float)[None]


class GoTo:
    """Drives the agent towards a fixed point, in chunks of 8."""

    def __init__(self, point):
        self.point = np.asarray(point, float)

    def reset(self, seed=None):
        pass

    def act(self, obs):
        return np.repeat(self.point[None], 8, axis=0)


def _check_segments(segments, info):
    assert sum(len(s["action"]) for s in segments) == info["expert_steps"]
    for s in segments:
        assert set(s) == {*RECORDED_FIELDS, "action"}
        assert len({len(v) for v in s.values()}) == 1
        assert all(v.dtype == np.float32 for v in s.values())
        np.testing.assert_array_equal(s["keypoints"][:, -1], s["agent_pos"])  # the observation before each action


def test_expert_takes_over_a_policy_that_does_nothing():
    config = split_config("in_distribution", 500)
    segments, info = corrected_episode(
        PushTEnv(render_mode=None), HoldStill(), PushTExpert(), config, 600, stuck_steps=10, takeover_steps=40, seed=0
    )
    assert info["success"] and info["n_takeovers"] >= 1
    _check_segments(segments, info)
    assert all(len(s["action"]) <= 40 for s in segments)
    assert len(segments) == info["n_takeovers"]  # the policy holds still between takeovers: one segment each
    # Before each takeover the policy held still for at least stuck_steps.
    assert info["steps"] >= info["expert_steps"] + 10 * info["n_takeovers"]
    # Nothing but the (stuck) policy: no takeover before stuck_steps.
    segments, info = corrected_episode(
        PushTEnv(render_mode=None), HoldStill(), PushTExpert(), config, 10, stuck_steps=10, seed=0
    )
    assert segments == [] and info["n_takeovers"] == info["expert_steps"] == 0 and not info["success"]


def test_leaving_the_training_region_triggers_a_takeover():
    config = split_config("object_ood", 0)
    env = PushTEnv("object_ood", render_mode=None)
    assert env.reset(options={"config": config})[0]["agent_pos"].max() < env.workspace.region
    segments, info = corrected_episode(
        env, GoTo((1000.0, 1000.0)), PushTExpert("large"), config, 60, stuck_steps=1000, takeover_steps=20, seed=0
    )
    assert info["n_takeovers"] >= 1 and info["expert_steps"] >= 20
    _check_segments(segments, info)
    assert segments[0]["agent_pos"][0].max() > env.workspace.region  # the expert starts where the policy went
    with pytest.raises(ValueError, match="workspace"):
        corrected_episode(env, GoTo((0.0, 0.0)), PushTExpert("standard"), config, 10)


@pytest.mark.slow
def test_collect_corrections_grows_a_readable_store(tmp_path):
    path = tmp_path / "demos.zarr"
    collect_pusht(path, 3, workers=1, progress=False)
    store = EpisodeStore(path)
    n_demos, demo_steps = len(store), store.n_steps
    seen, held = [], []

    def make_policy(store):
        seen.append(store.n_steps)
        held.append(store)  # a policy may keep the store it was built from: the lock must not live on with it
        index = SourceIndex.from_store(store, 20, pusht_weights(agent=4.0), PUSHT_BLOCK)
        return NearestNeighbourPolicy(index, execute=8)

    reports = collect_corrections(
        path,
        make_policy,
        rounds=2,
        episodes_per_round=2,
        max_steps=150,
        stuck_steps=15,
        takeover_steps=30,
        progress=False,
    )
    with EpisodeStore(path, mode="a", wait=0):  # writable again at once: `kpflow-correct` reopens it
        pass
    assert [r["round"] for r in reports] == [0, 1]
    assert sum(r["takeovers"] for r in reports) > 0
    steps = demo_steps
    for r in reports:
        assert r["episodes"] == 2 and 0 <= r["policy_successes"] <= r["successes"] <= 2
        assert r["chunks_added"] <= r["expert_steps"]
        assert r["dataset_steps"] == steps + r["chunks_added"]
        steps = r["dataset_steps"]
    assert steps > demo_steps
    assert seen == [demo_steps, reports[0]["dataset_steps"]]  # each round's policy learns from the grown store

    store = EpisodeStore(path)  # reopened from disk
    assert store.n_steps == steps
    assert len(store) == n_demos + sum(r["episodes_added"] for r in reports)
    configs = set()
    for i in range(n_demos, len(store)):
        episode, attrs = store.episode(i), store.episode_attrs(i)
        assert len({len(v) for v in episode.values()}) == 1 and len(episode["action"]) >= 2
        assert attrs["source"] == "correction" and attrs["round"] in (0, 1)
        assert attrs["config_index"] >= CONFIG_OFFSET and attrs["steps"] == len(episode["action"])
        configs.add((attrs["round"], attrs["config_index"]))
    assert len({c for _, c in configs}) == len(configs)  # configurations do not repeat across rounds

    # A second call continues the round numbering.
    more = collect_corrections(
        path, lambda s: HoldStill(), 1, 1, max_steps=40, stuck_steps=5, takeover_steps=10, progress=False
    )
    assert more[0]["round"] == 2 and more[0]["chunks_added"] > 0


def test_takeover_is_an_override_of_the_one_episode_loop():
    """The expert's takeovers run through run_episode: the overridden steps are exactly the recorded segments."""
    from kpflow.tasks.pusht.corrections import Takeover, _segments
    from kpflow.tasks.pusht.rollout import run_episode

    config = split_config("in_distribution", 4)
    takeover = Takeover(PushTExpert(), stuck_steps=10, takeover_steps=15)
    result = run_episode(PushTEnv(), HoldStill(), config, 60, seed=0, record=True, override=takeover)
    assert result.overridden.shape == (result.steps,) and result.overridden.sum() == takeover.steps > 0
    assert (
        not result.overridden[:10].any() and result.overridden[10:25].all()
    )  # stuck from the start: 10 steps, then 15
    segments = _segments(result.episode, result.overridden)
    assert sum(len(s["action"]) for s in segments) == takeover.steps and len(segments) <= takeover.n_takeovers
    np.testing.assert_array_equal(segments[0]["action"], result.episode["action"][10 : 10 + len(segments[0]["action"])])
