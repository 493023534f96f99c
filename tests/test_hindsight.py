"""Hindsight goals: each demonstration's goal keypoints relabelled with its object's last keypoints."""

from pathlib import Path

import hydra
import numpy as np
import pytest

from kpflow.data.chunks import ChunkDataset
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.hindsight import HindsightGoals, fragment_episodes
from kpflow.data.source_index import SourceIndex
from kpflow.tasks.pusht.demos import PUSHT_HINDSIGHT, pusht_hindsight
from kpflow.tasks.pusht.geometry import coverage
from tests.helpers import compose_config

LENGTHS = [4, 1, 7]
PUSHT = Path(__file__).resolve().parents[2] / "shared/data/pusht_cchi_v7_replay.zarr"


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> EpisodeStore:
    store = EpisodeStore(tmp_path_factory.mktemp("hindsight") / "demos.zarr", mode="a")
    rng = np.random.default_rng(0)
    for t in LENGTHS:
        store.add_episode(
            {"keypoints": rng.normal(size=(t, 25, 2)).astype(np.float32), "action": rng.normal(size=(t, 2))}
        )
    return EpisodeStore(store.path)


def test_relabel_in_closed_form(store):
    """g_t <- o_{T-1} for every step of each episode; the object, the agent and the actions stay as recorded."""
    obs = store.field("keypoints")
    out = PUSHT_HINDSIGHT.relabel(obs, store.episode_ends)
    for e in range(store.n_episodes):
        rows = store.episode_slice(e)
        raw = obs[rows]
        np.testing.assert_array_equal(out[rows][:, 12:24], np.broadcast_to(raw[-1, :12], (len(raw), 12, 2)))
        np.testing.assert_array_equal(out[rows][:, :12], raw[:, :12])
        np.testing.assert_array_equal(out[rows][:, 24], raw[:, 24])
    assert not np.shares_memory(out, obs) and np.array_equal(
        obs, store.field("keypoints")
    )  # a copy: the input is untouched


def test_chunks_and_index_read_hindsight_goals(store):
    ds = ChunkDataset(store, [2, 0], horizon=3, hindsight=PUSHT_HINDSIGHT)
    plain = ChunkDataset(store, [2, 0], horizon=3)
    last = store.episode(2)["keypoints"][-1]
    for k in range(LENGTHS[2]):  # episode 2's items come first, in the listed order
        np.testing.assert_array_equal(ds[k]["obs"][12:24].numpy(), last[:12])
        np.testing.assert_array_equal(ds[k]["actions"].numpy(), plain[k]["actions"].numpy())
    np.testing.assert_array_equal(ds.history(np.arange(len(ds)))[:, 0, 12:24], ds.arrays()[0][:, 12:24])
    index = SourceIndex.from_store(store, 3, hindsight=PUSHT_HINDSIGHT)
    np.testing.assert_array_equal(
        index.keypoints, PUSHT_HINDSIGHT.relabel(store.field("keypoints"), store.episode_ends)
    )


def test_correction_takeovers_keep_their_recorded_goals(tmp_path):
    """A takeover stored by corrections is part of a longer episode: it stops wherever the block then is, so for
    learning its goal stays as recorded; whole demonstrations around it are relabelled."""
    store = EpisodeStore(tmp_path / "corrected.zarr", mode="a")
    rng = np.random.default_rng(1)
    for t, attrs in zip(LENGTHS, [{}, {"source": "correction", "round": 0}, {"source": "demo"}]):
        store.add_episode(
            {"keypoints": rng.normal(size=(t, 25, 2)).astype(np.float32), "action": rng.normal(size=(t, 2))},
            attrs=attrs,
        )
    store = EpisodeStore(store.path)
    np.testing.assert_array_equal(fragment_episodes(store), [False, True, False])
    obs = store.field("keypoints")
    out = PUSHT_HINDSIGHT.relabel(obs, store.episode_ends, fragment_episodes(store))
    np.testing.assert_array_equal(out[store.episode_slice(1)], obs[store.episode_slice(1)])  # the takeover: as recorded
    for e in (0, 2):
        rows = store.episode_slice(e)
        np.testing.assert_array_equal(out[rows][:, 12:24], np.broadcast_to(obs[rows][-1, :12], (LENGTHS[e], 12, 2)))
    ds = ChunkDataset(store, range(3), horizon=2, hindsight=PUSHT_HINDSIGHT)
    np.testing.assert_array_equal(ds.obs, out)  # learning reads it that way
    # A source index relabels the takeover too: it is then a source that ends exactly on its goal.
    everything = PUSHT_HINDSIGHT.relabel(obs, store.episode_ends)
    np.testing.assert_array_equal(SourceIndex.from_store(store, 2, hindsight=PUSHT_HINDSIGHT).keypoints, everything)
    np.testing.assert_array_equal(
        ChunkDataset(store, range(3), 2, hindsight=PUSHT_HINDSIGHT, relabel_fragments=True).obs, everything
    )
    assert not np.array_equal(everything, out)
    with pytest.raises(ValueError, match="fragments must be one bool per episode"):
        PUSHT_HINDSIGHT.relabel(obs, store.episode_ends, np.array([True, False]))
    # The data node says which reading a learned policy trains on: data.relabel_fragments (default: as recorded).
    for relabel, want in ((False, out), (True, everything)):
        overrides = [
            "~experiment",
            "data=pusht_store",
            f"data.path={store.path}",
            f"data.relabel_fragments={str(relabel).lower()}",
        ]
        dm = hydra.utils.instantiate(compose_config("train", overrides, tmp_path).data)
        dm.setup()
        np.testing.assert_array_equal(dm.train_set.obs, want)  # the store's rows, whichever episodes train


def test_bad_hindsight_input_is_refused():
    with pytest.raises(ValueError, match="same number"):
        HindsightGoals(object=(0, 1), goal=(2,))
    with pytest.raises(ValueError, match="both"):
        HindsightGoals(object=(0, 1), goal=(1, 2))
    goals = HindsightGoals(object=(0,), goal=(1,))
    with pytest.raises(ValueError, match="keypoints 0..1"):
        goals.relabel(np.zeros((4, 1, 2)), [4])
    with pytest.raises(ValueError, match="episode_ends"):
        goals.relabel(np.zeros((4, 2, 2)), [3])  # does not end at the last row
    with pytest.raises(ValueError, match="episode_ends"):
        goals.relabel(np.zeros((4, 2, 2)), [2, 2, 4])  # an empty episode
    with pytest.raises(ValueError, match="goals must be one of"):
        pusht_hindsight("final")
    assert pusht_hindsight("recorded") is None and pusht_hindsight("hindsight") is PUSHT_HINDSIGHT


def test_human_demonstrations_reach_their_goals_only_in_hindsight(tmp_path):
    """Diffusion Policy's 206 human demonstrations stop short of coverage 0.95 of the goal they were given (0.77-0.90);
    read in hindsight, each one ends exactly on its goal: the relabelled goal keypoints are a T at the block's last
    pose (coverage 1)."""
    if not PUSHT.exists():
        pytest.skip(f"standard Push-T dataset not found at {PUSHT}")
    import torch

    from kpflow.geometry.alignment import fit_affine
    from kpflow.tasks.pusht.geometry import T_KEYPOINTS
    from kpflow.tasks.pusht.replay_import import import_pusht_replay

    store = import_pusht_replay(PUSHT, tmp_path / "human.zarr", progress=False)
    obs = PUSHT_HINDSIGHT.relabel(store.field("keypoints"), store.episode_ends)
    last = store.episode_ends - 1
    blocks, goals = (
        store.field("block_pose")[last].astype(np.float64),
        store.field("goal_pose")[last].astype(np.float64),
    )
    recorded = np.array([coverage(b, g) for b, g in zip(blocks, goals)])
    assert store.n_episodes == 206 and recorded.max() < 0.95
    goal_kp = torch.from_numpy(obs[last, 12:24].astype(np.float64))
    rot, origin = fit_affine(torch.from_numpy(T_KEYPOINTS).expand_as(goal_kp), goal_kp, "rigid")  # the goal T's pose
    angle = torch.atan2(rot[:, 1, 0], rot[:, 0, 0]).numpy()
    reached = [coverage(b, (*o, a)) for b, o, a in zip(blocks, origin.numpy(), angle)]
    np.testing.assert_allclose(reached, 1.0, atol=1e-4)
