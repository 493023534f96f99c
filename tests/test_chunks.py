"""ChunkDataset, split_episodes and ChunkDataModule on a real episode store."""

from pathlib import Path

import numpy as np
import pytest
import torch

from kpflow.data.chunks import ChunkDataModule, ChunkDataset, split_episodes
from kpflow.data.episode_store import EpisodeStore

LENGTHS = [5, 2, 30, 9, 14, 6, 11, 3, 8, 20]
H = 4


@pytest.fixture(scope="module")
def store_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("chunks") / "demos.zarr"
    store = EpisodeStore(path, mode="a")
    rng = np.random.default_rng(0)
    for t in LENGTHS:
        store.add_episode(
            {"keypoints": rng.normal(size=(t, 25, 2)).astype(np.float32), "action": rng.normal(size=(t, 2))}
        )
    return path


@pytest.fixture(scope="module")
def store(store_path) -> EpisodeStore:
    return EpisodeStore(store_path)


def test_chunk_equals_raw_slice(store):
    ds = ChunkDataset(store, [2], horizon=H)
    raw = store.episode(2)
    item = ds[7]
    assert (item["episode"], item["t"]) == (2, 7)
    assert item["obs"].dtype == torch.float32 and item["obs"].shape == (25, 2)
    torch.testing.assert_close(item["obs"], torch.from_numpy(raw["keypoints"][7]))
    torch.testing.assert_close(item["actions"], torch.from_numpy(raw["action"][7 : 7 + H]).float())
    assert item["actions"].dtype == torch.float32 and item["mask"].dtype == torch.bool and item["mask"].all()


def test_padding_repeats_the_last_action(store):
    ds = ChunkDataset(store, [0], horizon=H)
    raw = torch.from_numpy(store.episode(0)["action"]).float()
    item = ds[3]  # t = 3 of 5: two real actions, two padded
    assert item["mask"].tolist() == [True, True, False, False]
    torch.testing.assert_close(item["actions"][:2], raw[3:5])
    torch.testing.assert_close(item["actions"][2:], raw[4].expand(2, 2))
    short = ChunkDataset(store, [1], horizon=6)[0]  # an episode shorter than the horizon
    assert short["mask"].tolist() == [True, True] + [False] * 4
    torch.testing.assert_close(
        short["actions"][2:], torch.from_numpy(store.episode(1)["action"][-1]).float().expand(4, 2)
    )


def test_items_never_cross_episode_boundaries(store):
    episodes = [3, 0, 1, 7]
    ds = ChunkDataset(store, episodes, horizon=H)
    assert len(ds) == sum(LENGTHS[i] for i in episodes)
    seen = []
    for k in range(len(ds)):
        item = ds[k]
        e, t = item["episode"], item["t"]
        raw = store.episode(e)["action"]
        want = raw[np.minimum(np.arange(t, t + H), len(raw) - 1)]
        torch.testing.assert_close(item["actions"], torch.from_numpy(want).float())
        assert item["mask"].tolist() == (np.arange(t, t + H) < len(raw)).tolist()
        torch.testing.assert_close(item["obs"], torch.from_numpy(store.episode(e)["keypoints"][t]))
        seen.append((e, t))
    assert seen == [(e, t) for e in episodes for t in range(LENGTHS[e])]
    assert ds[-1]["episode"] == 7 and ds[-1]["t"] == LENGTHS[7] - 1
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_dataset_validation(store):
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        ChunkDataset(store, [0], horizon=0)
    with pytest.raises(ValueError, match=r"episode indices \[10\] out of range 0..9"):
        ChunkDataset(store, [0, 10])
    with pytest.raises(ValueError, match=r"field 'state' not in .*available fields: \('action', 'keypoints'\)"):
        ChunkDataset(store, [0], obs_key="state")


def test_split_by_episode():
    train, val = split_episodes(50, val_fraction=0.2, seed=3)
    assert len(val) == 10 and sorted(train + val) == list(range(50)) and not set(train) & set(val)
    assert (train, val) == split_episodes(50, val_fraction=0.2, seed=3)
    assert val != split_episodes(50, val_fraction=0.2, seed=4)[1]
    assert split_episodes(2, 0.1) in [([0], [1]), ([1], [0])]  # rounds up to one validation episode
    assert split_episodes(2, 0.9)[0] != []  # always keeps a training episode
    assert split_episodes(1, 0.5) == ([0], [])
    assert split_episodes(5, 0.0) == ([0, 1, 2, 3, 4], [])
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes(5, 1.0)
    with pytest.raises(ValueError, match="at least one episode"):
        split_episodes(0)


def batches(dm: ChunkDataModule) -> list[dict]:
    return list(dm.train_dataloader())


def test_datamodule_batches_and_determinism(store_path):
    dm = ChunkDataModule(store_path, horizon=H, val_fraction=0.2, batch_size=16, seed=1)
    with pytest.raises(RuntimeError, match="setup"):
        dm.train_dataloader()
    dm.setup()
    assert len(dm.val_episodes) == 2 and sorted(dm.train_episodes + dm.val_episodes) == list(range(len(LENGTHS)))
    first = next(iter(dm.train_dataloader()))
    assert first["obs"].shape == (16, 25, 2) and first["actions"].shape == (16, H, 2) and first["mask"].shape == (16, H)
    assert first["obs"].dtype == torch.float32 and first["mask"].dtype == torch.bool
    assert set(first["episode"].tolist()) <= set(dm.train_episodes)
    val = list(dm.val_dataloader())
    assert sum(len(b["t"]) for b in val) == sum(LENGTHS[i] for i in dm.val_episodes)
    assert set(torch.cat([b["episode"] for b in val]).tolist()) == set(dm.val_episodes)

    same = ChunkDataModule(store_path, horizon=H, val_fraction=0.2, batch_size=16, seed=1)
    same.setup()
    a, b = batches(dm), batches(same)
    assert all(
        torch.equal(x["episode"], y["episode"]) and torch.equal(x["t"], y["t"]) for x, y in zip(a, b, strict=True)
    )
    assert torch.equal(torch.cat([x["actions"] for x in a]), torch.cat([y["actions"] for y in b]))

    other = ChunkDataModule(store_path, horizon=H, val_fraction=0.2, batch_size=16, seed=2)
    other.setup()
    assert not torch.equal(torch.cat([x["t"] for x in a]), torch.cat([y["t"] for y in batches(other)]))


def test_datamodule_max_episodes(store_path):
    dm = ChunkDataModule(store_path, horizon=H, val_fraction=0.25, max_episodes=4)
    dm.setup()
    assert sorted(dm.train_episodes + dm.val_episodes) == [0, 1, 2, 3] and len(dm.val_episodes) == 1
    assert len(dm.train_set) + len(dm.val_set) == sum(LENGTHS[:4])


def test_observation_history_repeats_the_first_frame_at_episode_starts(store):
    ds = ChunkDataset(store, [3, 2], horizon=H, n_obs=3)
    raw = {i: store.episode(i)["keypoints"] for i in (2, 3)}
    first = ds[0]  # episode 3, t = 0: the first frame three times
    assert (first["episode"], first["t"]) == (3, 0) and first["history"].shape == (3, 25, 2)
    for frame in first["history"]:
        torch.testing.assert_close(frame, torch.from_numpy(raw[3][0]))
    second = ds[1]  # t = 1: [o0, o0, o1]
    torch.testing.assert_close(second["history"], torch.from_numpy(raw[3][[0, 0, 1]]))
    later = ds[5]  # t = 5: [o3, o4, o5], never reaching into another episode
    torch.testing.assert_close(later["history"], torch.from_numpy(raw[3][3:6]))
    start_of_next = ds[LENGTHS[3]]  # episode 2's first item: its own first frame, not episode 3's last
    assert start_of_next["episode"] == 2
    torch.testing.assert_close(start_of_next["history"], torch.from_numpy(raw[2][[0, 0, 0]]))
    torch.testing.assert_close(later["history"][-1], later["obs"])  # the last frame is the current observation
    assert ChunkDataset(store, [2], horizon=H)[4]["history"].shape == (1, 25, 2)
    with pytest.raises(ValueError, match="n_obs must be >= 1"):
        ChunkDataset(store, [2], n_obs=0)
