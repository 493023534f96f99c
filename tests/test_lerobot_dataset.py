"""LeRobot v3.0 datasets written from an episode store and read back, in the real layout with pyarrow: every field of
meta/info.json checked against the data files, the episodes and tasks tables, the statistics, file and chunk
rollover, an exact round trip, and clear errors for what is not such a dataset. (The ``lerobot`` package itself
cannot be installed beside torch 2.13: lerobot 0.4.4 requires torch < 2.11.)"""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.lerobot_dataset import DATA_PATH, EPISODES_PATH, export_lerobot, import_lerobot, read_info
from tests.helpers import WALK_EPISODES, WALK_LEN, walk_to_block_store

FPS = 10.0


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("lerobot") / "demos.zarr"
    walk_to_block_store(path)
    return EpisodeStore(path)


@pytest.fixture(scope="module")
def dataset(store, tmp_path_factory):
    """Exported with tiny files and chunks so that episodes spread over several files and chunks."""
    root = tmp_path_factory.mktemp("lerobot_out") / "pusht_walk"
    return export_lerobot(
        store, root, fps=FPS, task="push the T", robot_type="pusht", data_files_size_in_mb=0.01, chunks_size=3
    )


def data_table(root):
    info = read_info(root)
    files = sorted(root.glob("data/*/*.parquet"))
    return info, files, [pq.read_table(f) for f in files]


def test_info_json_describes_the_data(store, dataset):
    info, files, tables = data_table(dataset)
    assert info["codebase_version"] == "v3.0" and info["robot_type"] == "pusht" and info["fps"] == FPS
    assert info["total_episodes"] == WALK_EPISODES == store.n_episodes and info["total_tasks"] == 1
    assert info["total_frames"] == WALK_EPISODES * WALK_LEN == sum(t.num_rows for t in tables)
    assert info["splits"] == {"train": f"0:{WALK_EPISODES}"} and info["video_path"] is None
    assert info["chunks_size"] == 3 and info["data_files_size_in_mb"] == 0.01
    # the path template names exactly the files there are, chunk by chunk
    indices = [(int(f.parent.name.split("-")[1]), int(f.stem.split("-")[1])) for f in files]
    assert [dataset / DATA_PATH.format(chunk_index=c, file_index=i) for c, i in indices] == files
    assert len(files) > 3 and max(i for _, i in indices) == 2 and max(c for c, _ in indices) >= 1  # rolled over
    features = info["features"]
    assert list(features)[-5:] == ["timestamp", "frame_index", "episode_index", "index", "task_index"]
    for table in tables:
        assert table.column_names == list(features)
        for name, feature in features.items():
            column = table[name].type
            if feature["shape"] == [1]:
                assert str(column) == {"float32": "float", "int64": "int64"}[feature["dtype"]]
            else:
                assert column.list_size == feature["shape"][0] and str(column.value_type) == "float"
    assert features["observation.state"]["shape"] == [50] and features["observation.state"]["names"][:3] == [
        "k0.x",
        "k0.y",
        "k1.x",
    ]
    assert features["action"] == {"dtype": "float32", "shape": [2], "names": None}
    rows = {
        k: np.concatenate([t[k].to_numpy() for t in tables])
        for k in ("index", "episode_index", "frame_index", "timestamp")
    }
    np.testing.assert_array_equal(rows["index"], np.arange(info["total_frames"]))
    np.testing.assert_array_equal(rows["episode_index"], np.repeat(np.arange(WALK_EPISODES), WALK_LEN))
    np.testing.assert_array_equal(rows["frame_index"], np.tile(np.arange(WALK_LEN), WALK_EPISODES))
    np.testing.assert_allclose(rows["timestamp"], rows["frame_index"] / FPS, rtol=1e-6)


def test_episodes_tasks_and_stats_tables(store, dataset):
    episodes = pq.read_table(dataset / EPISODES_PATH.format(chunk_index=0, file_index=0)).to_pydict()
    assert episodes["episode_index"] == list(range(WALK_EPISODES)) and episodes["length"] == [WALK_LEN] * WALK_EPISODES
    assert episodes["tasks"] == [["push the T"]] * WALK_EPISODES
    assert episodes["dataset_from_index"] == [e * WALK_LEN for e in range(WALK_EPISODES)]
    assert episodes["dataset_to_index"] == [(e + 1) * WALK_LEN for e in range(WALK_EPISODES)]
    for e in range(WALK_EPISODES):  # each episode's rows are in the file its row says
        path = dataset / DATA_PATH.format(
            chunk_index=episodes["data/chunk_index"][e], file_index=episodes["data/file_index"][e]
        )
        assert (pq.read_table(path)["episode_index"].to_numpy() == e).sum() == WALK_LEN
    first = store.episode(0)["action"].astype(np.float64)
    np.testing.assert_allclose(episodes["stats/action/mean"][0], first.mean(0))
    np.testing.assert_allclose(episodes["stats/action/q50"][0], np.median(first, 0))
    tasks = pq.read_table(dataset / "meta" / "tasks.parquet")
    assert tasks["task_index"].to_pylist() == [0] and tasks["__index_level_0__"].to_pylist() == ["push the T"]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == [
        "__index_level_0__"
    ]  # lerobot reads it with pandas
    stats = json.loads((dataset / "meta" / "stats.json").read_text())
    keypoints = store.field("keypoints").reshape(len(store.field("keypoints")), -1).astype(np.float64)
    np.testing.assert_allclose(stats["observation.state"]["min"], keypoints.min(0))
    np.testing.assert_allclose(stats["observation.state"]["std"], keypoints.std(0))
    assert stats["index"]["count"] == [WALK_EPISODES * WALK_LEN] and stats["episode_index"]["max"] == [
        WALK_EPISODES - 1
    ]
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


def test_round_trip_restores_the_store_exactly(store, dataset, tmp_path):
    back = import_lerobot(dataset, tmp_path / "back.zarr")
    assert back.fields == store.fields
    np.testing.assert_array_equal(back.episode_ends, store.episode_ends)
    for field in store.fields:
        np.testing.assert_array_equal(back.field(field), store.field(field))
    assert back.field("keypoints").shape[1:] == (25, 2)
    flat = import_lerobot(dataset, tmp_path / "flat.zarr", columns={"observation.state": "state"})
    assert flat.fields == ("state",) and flat.field("state").shape[1:] == (50,)


def test_bad_datasets_and_targets_are_clear_errors(store, dataset, tmp_path):
    with pytest.raises(FileExistsError, match="exists already"):
        export_lerobot(store, dataset)
    with pytest.raises(ValueError, match="not in the store"):
        export_lerobot(store, tmp_path / "x", fields=("images",))
    with pytest.raises(FileNotFoundError, match="no meta/info.json"):
        import_lerobot(tmp_path, tmp_path / "a.zarr")
    with pytest.raises(ValueError, match="no features"):
        import_lerobot(dataset, tmp_path / "b.zarr", columns={"observation.images": "images"})
    old = tmp_path / "old"
    (old / "meta").mkdir(parents=True)
    (old / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v2.1"}))
    with pytest.raises(ValueError, match="v2.1"):
        import_lerobot(old, tmp_path / "c.zarr")
    assert not any(tmp_path.glob("*.zarr"))  # a refused import leaves no store behind
