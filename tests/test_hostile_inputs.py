"""Issue 57's hostile inputs, each planted: lock files that are links, damaged store metadata, LeRobot datasets that
do not hold what they say, a broken YAML under --config-dir and an unknown camera. Each is refused with one line
naming the file or key, and nothing is written through a link."""

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import LOCK_NAME, EpisodeStore, UnverifiedStoreWarning
from kpflow.data.lerobot_dataset import export_lerobot, import_lerobot
from kpflow.utils.file_lock import UnsafeLockFile
from kpflow.utils.run import RUN_LOCK, claim_run_folder
from tests.helpers import walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def store(tmp_path):
    path = tmp_path / "demos.zarr"
    walk_to_block_store(path)
    return path


@pytest.fixture()
def dataset(store, tmp_path):
    with EpisodeStore(store) as s:
        return export_lerobot(s, tmp_path / "lerobot", fps=10.0, task="push the T", robot_type="pusht")


def _precious(tmp_path) -> Path:
    target = tmp_path / "precious.txt"
    target.write_text("do not touch")
    return target


# 8, 9: lock files that are symbolic links are refused by name, and nothing is written through them
def test_a_store_lock_that_is_a_link_is_refused_and_its_target_untouched(store, tmp_path):
    target = _precious(tmp_path)
    (store / LOCK_NAME).unlink(missing_ok=True)
    (store / LOCK_NAME).symlink_to(target)
    with pytest.raises(UnsafeLockFile, match=rf"{LOCK_NAME} is a symbolic link: a lock file is never followed"):
        EpisodeStore(store, mode="a")  # what kpflow-verify seal=true opens
    assert target.read_text() == "do not touch"
    done = subprocess.run([sys.executable, "-m", "kpflow.cli.verify", f"store={store}", "seal=true"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1 and "is a symbolic link" in done.stderr and len(done.stderr.strip().splitlines()) == 2, done.stderr
    assert target.read_text() == "do not touch"


def test_a_run_folder_lock_that_is_a_link_is_refused_and_its_target_untouched(tmp_path):
    target = _precious(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    (run / RUN_LOCK).symlink_to(target)
    with pytest.raises(UnsafeLockFile, match=rf"{RUN_LOCK} is a symbolic link"):
        claim_run_folder(run)  # what kpflow-evaluate claims
    assert target.read_text() == "do not touch"
    (run / RUN_LOCK).unlink()
    os.mkfifo(run / RUN_LOCK)
    with pytest.raises(UnsafeLockFile, match="is not a regular file"):
        claim_run_folder(run)


# 11: a store's field record damaged; a sealed store that lost its checksums; an unsealed one read
def _zattrs(store: Path) -> tuple[Path, dict]:
    path = store / "meta" / ".zattrs"
    return path, json.loads(path.read_text())


def test_a_damaged_field_record_is_named(store):
    path, attrs = _zattrs(store)
    attrs["fields"] = {name: "float32" for name in attrs["fields"]}  # each spec damaged to a string
    path.write_text(json.dumps(attrs))
    with pytest.raises(ValueError, match=r"demos.zarr: meta/.zattrs' field record is damaged: it must map each field to \{dtype, shape\}"):
        EpisodeStore(store)
    attrs["fields"] = "keypoints"
    path.write_text(json.dumps(attrs))
    with pytest.raises(ValueError, match="field record is damaged"):
        EpisodeStore(store)


def test_a_sealed_store_that_lost_its_checksums_is_refused_saying_how_to_seal_it(store):
    path, attrs = _zattrs(store)
    del attrs["checksums"]
    path.write_text(json.dumps(attrs))
    with pytest.raises(ValueError, match=r"lost its checksums: the store was sealed .* kpflow-verify seal=true store="):
        EpisodeStore(store)


def test_reading_an_unsealed_store_says_it_is_unverified(store, tmp_path):
    path, attrs = _zattrs(store)
    del attrs["checksums"], attrs["fields"]  # as a store written before kpflow recorded them
    path.write_text(json.dumps(attrs))
    with pytest.warns(UnverifiedStoreWarning, match="its values are read unverified. kpflow-verify seal=true"):
        EpisodeStore(store)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        EpisodeStore(store)  # once per store and process
    copy = tmp_path / "copy.zarr"
    shutil.copytree(store, copy)
    with pytest.warns(UnverifiedStoreWarning, match="copy.zarr has no checksums"):  # training on it says so
        ChunkDataModule(copy, horizon=4, batch_size=4, val_fraction=0.0).setup()


# 10, 12, 13, 14: LeRobot datasets that do not hold what they say
def test_lerobot_state_with_names_kpflow_does_not_read_says_what_it_expected(dataset):
    info_path = dataset / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    width = info["features"]["observation.state"]["shape"][0]
    info["features"]["observation.state"]["names"] = [f"joint_{i}" for i in range(width)]
    info_path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"gave no field 'keypoints' \(it gave \['action', 'state'\]\). kpflow reads keypoints from "
                       r"feature observation.state named k0.x, k0.y\[, k0.z\].*named \['joint_0'.*data.obs_key=state"):  # fmt: skip
        ChunkDataModule(dataset, horizon=4, batch_size=4, val_fraction=0.0).setup()


def test_a_lerobot_data_file_with_a_duplicated_column_is_named(dataset, tmp_path):
    data = sorted(dataset.glob("data/*/*.parquet"))[0]
    table = pq.read_table(data)
    dup = pa.Table.from_arrays([*table.columns, table.column("action")], names=[*table.column_names, "action"])
    pq.write_table(dup, data)
    with pytest.raises(ValueError, match=rf"{data.name} does not read as parquet with columns"):
        import_lerobot(dataset, tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def test_a_lerobot_data_file_that_is_not_parquet_is_named(dataset, tmp_path):
    data = sorted(dataset.glob("data/*/*.parquet"))[0]
    data.write_bytes(b"not parquet at all" * 10)
    with pytest.raises(ValueError, match=rf"{data.name} is not a readable parquet file"):
        import_lerobot(dataset, tmp_path / "x.zarr")


def test_a_lerobot_dataset_with_no_frames_is_refused_by_name(dataset, tmp_path):
    info_path = dataset / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["total_frames"] = 0
    info_path.write_text(json.dumps(info))
    for data in dataset.glob("data/*/*.parquet"):
        pq.write_table(pq.read_table(data).slice(0, 0), data)
    with pytest.raises(ValueError, match="info.json declares 0 frames: a dataset to import needs at least one"):
        import_lerobot(dataset, tmp_path / "x.zarr")


# 15: a broken YAML under --config-dir
def test_a_broken_yaml_under_the_config_dir_is_one_line(tmp_path):
    (tmp_path / "task").mkdir()
    (tmp_path / "task" / "broken.yaml").write_text("a: [1, 2\nb: {\n")
    done = subprocess.run([sys.executable, "evaluate.py", "--config-dir", str(tmp_path), "task=broken"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 2, done.stderr
    assert lines[0] == f"error: {tmp_path / 'task' / 'broken.yaml'}, line 2 column 2: not valid YAML (expected ',' or ']', but got ':')"


# 16: an unknown camera is refused before any attempt
def test_an_unknown_camera_is_refused_before_any_episode():
    from kpflow.tasks.suite.task import SuiteTask
    from kpflow.vision.keypoint_source import KeypointSource

    task = SuiteTask("lift", KeypointSource("camera", cameras=("nosuchcam",)))
    with pytest.raises(ValueError, match=r"lift has no camera \['nosuchcam'\]; its cameras are \[.*'frontview'"):
        task.make_env()
