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

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import LOCK_NAME, EpisodeStore, UnverifiedStoreWarning
from kpflow.data.lerobot_dataset import export_lerobot, import_lerobot
from kpflow.utils.file_lock import UnsafeLockFile
from kpflow.utils.run import RUN_LOCK, claim_run_folder
from tests.helpers import run_command, walk_to_block_store

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
    done = run_command("kpflow.cli.verify", f"store={store}", "seal=true")
    assert (
        done.returncode == 1 and "is a symbolic link" in done.stderr and len(done.stderr.strip().splitlines()) == 2
    ), done.stderr
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


# issue 63.2: lock files that are hard links (as a tar extracted with filter='data' may carry) are refused by name,
# and neither the file they share a name with nor anything else is written
def test_a_store_lock_hard_linked_to_its_own_metadata_is_refused_and_the_store_intact(store):
    zattrs = store / "meta" / ".zattrs"
    before = zattrs.read_bytes()
    (store / LOCK_NAME).unlink(missing_ok=True)
    os.link(zattrs, store / LOCK_NAME)
    with pytest.raises(
        UnsafeLockFile,
        match=rf"{LOCK_NAME} is a hard link \(2 names for one file\): a lock file is never written through",
    ):
        EpisodeStore(store, mode="a")  # what kpflow-verify seal=true opens
    assert zattrs.read_bytes() == before
    (store / LOCK_NAME).unlink()
    assert len(EpisodeStore(store)) > 0


def test_run_folder_and_data_folder_locks_hard_linked_elsewhere_are_refused(tmp_path):
    from kpflow.utils.io import atomic_dir

    target = _precious(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    os.link(target, run / RUN_LOCK)
    with pytest.raises(UnsafeLockFile, match=rf"{RUN_LOCK} is a hard link"):
        claim_run_folder(run)
    os.link(target, tmp_path / ".demos.zarr.lock")  # the lock an import takes beside its store
    with pytest.raises(UnsafeLockFile, match=r".demos.zarr.lock is a hard link"):
        with atomic_dir(tmp_path / "demos.zarr"):
            pass
    assert target.read_text() == "do not touch" and not (tmp_path / "demos.zarr").exists()


# 11: a store's field record damaged; a sealed store that lost its checksums; an unsealed one read
def _zattrs(store: Path) -> tuple[Path, dict]:
    path = store / "meta" / ".zattrs"
    return path, json.loads(path.read_text())


def test_a_damaged_field_record_is_named(store):
    path, attrs = _zattrs(store)
    attrs["fields"] = {name: "float32" for name in attrs["fields"]}  # each spec damaged to a string
    path.write_text(json.dumps(attrs))
    with pytest.raises(
        ValueError,
        match=r"demos.zarr: meta/.zattrs' field record is damaged: it must map each field to \{dtype, shape\}",
    ):
        EpisodeStore(store)
    attrs["fields"] = "keypoints"
    path.write_text(json.dumps(attrs))
    with pytest.raises(ValueError, match="field record is damaged"):
        EpisodeStore(store)


@pytest.mark.parametrize("attrs, refused", [
    ([1, 2, 3], r"meta/.zattrs is damaged: it holds a JSON list, not an object of attributes"),
    ("fields", r"meta/.zattrs is damaged: it holds a JSON str, not an object"),
    ({"episode_attrs": 7}, r"meta/.zattrs is damaged: its episode_attrs must be a list"),
])  # fmt: skip
def test_store_metadata_that_is_json_but_not_an_object_is_named(store, attrs, refused):
    """Issue 63.8: valid JSON of the wrong kind gave an AttributeError."""
    (store / "meta" / ".zattrs").write_text(json.dumps(attrs))
    with pytest.raises(ValueError, match=rf"demos.zarr: {refused}"):
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
    done = run_command("kpflow.cli.evaluate", "--config-dir", str(tmp_path), "task=broken")
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 2, done.stderr
    assert (
        lines[0]
        == f"error: {tmp_path / 'task' / 'broken.yaml'}, line 2 column 2: not valid YAML (expected ',' or ']', but got ':')"
    )


# 16: an unknown camera is refused before any attempt
def test_an_unknown_camera_is_refused_before_any_episode():
    from kpflow.tasks.suite.task import SuiteTask
    from kpflow.vision.keypoint_source import KeypointSource

    task = SuiteTask("lift", KeypointSource("camera", cameras=("nosuchcam",)))
    with pytest.raises(ValueError, match=r"lift has no camera \['nosuchcam'\]; its cameras are \[.*'frontview'"):
        task.make_env("d0")


# 1-7: resources a small file can claim, refused before anything is allocated or decompressed
def _checkpoint(hparams: dict, path: Path) -> Path:
    import torch

    torch.save({"state_dict": {}, "hyper_parameters": hparams}, path)
    return path


@pytest.mark.parametrize("key, value, hparams", [
    ("objective.train_steps", 10**7, {"n_keypoints": 25, "objective": {"name": "ddpm", "train_steps": 10**7}}),
    ("horizon", 1 << 22, {"n_keypoints": 25, "horizon": 1 << 22}),
    ("network.down_dims", 1 << 20, {"n_keypoints": 25, "network": {"name": "unet", "down_dims": [64, 1 << 20]}}),
    # a file of the older flat layout is checked in the config's groups, where its values move (kpflow.policies.kcfm.config)
    ("objective.train_steps", 10**7, {"n_keypoints": 25, "objective": "ddpm", "objective_options": {"train_steps": 10**7}}),
    ("network.down_dims", 1 << 20, {"n_keypoints": 25, "down_dims": [64, 1 << 20]}),
])  # fmt: skip
def test_a_checkpoint_asking_beyond_the_limits_is_refused_before_building(tmp_path, key, value, hparams):
    from kpflow import load_policy

    path = _checkpoint(hparams, tmp_path / "big.ckpt")
    with pytest.raises(
        ValueError,
        match=rf"big.ckpt: hyper-parameter {key} = {value} is beyond kpflow's limit \d+ \(kpflow/utils/limits.py\)",
    ):
        load_policy(path)


def test_a_learned_map_checkpoint_of_a_million_layers_is_refused_at_once(tmp_path):
    from kpflow.maps.map_module import MapModule
    from kpflow.utils.checkpoint import load_checkpoint

    path = _checkpoint({"n_keypoints": 25, "dim": 2, "n_layers": 10**6}, tmp_path / "map.ckpt")
    with pytest.raises(ValueError, match=r"map.ckpt: hyper-parameter n_layers = 1000000 is beyond kpflow's limit 256"):
        load_checkpoint(MapModule, path)


@pytest.mark.parametrize("hparams, refused", [
    ({"n_keypoints": 25, "horizon": "TENSOR"}, r"hyper-parameter horizon is a tensor, not a plain number"),
    # a flat file of the older layout: its widths are checked where they move, the config's network group
    ({"n_keypoints": 25, "down_dims": [64, "TENSOR"]}, r"hyper-parameter network.down_dims\[1\] is a tensor"),
    ({"n_keypoints": 25, "horizon": 16.0}, r"hyper-parameter horizon = 16.0 is a float, not a whole number \(int\)"),
    ({"n_keypoints": 25, "horizon": True}, r"hyper-parameter horizon = True is a bool, not a whole number"),
    ({"n_keypoints": 25, "horizon": -4}, r"hyper-parameter horizon = -4 is negative"),
])  # fmt: skip
def test_hyper_parameters_the_limits_bound_must_be_plain_whole_numbers(tmp_path, hparams, refused):
    """Issue 63.5, 63.8: a tensor (which slips past a comparison and sizes the model all the same: 4.7 GB at the first
    act for 2^22) or a float where the limits table bounds a whole number is refused, naming the file and key."""
    import torch

    from kpflow import load_policy

    hparams = {k: [torch.tensor(1 << 20) if i == "TENSOR" else i for i in v] if isinstance(v, list) else torch.tensor(1 << 22) if v == "TENSOR" else v
               for k, v in hparams.items()}  # fmt: skip
    path = _checkpoint(hparams, tmp_path / "odd.ckpt")
    with pytest.raises(ValueError, match=rf"odd.ckpt: {refused}"):
        load_policy(path)


def test_a_learned_map_of_a_tensor_number_of_layers_is_refused_at_once(tmp_path):
    """Issue 63.5: ``n_layers=torch.tensor(10**6)`` spun over 60 s at 1.7 GB (load_checkpoint, kpflow-serve map=learned)."""
    import torch

    from kpflow.maps.learned import LearnedMap

    path = _checkpoint({"n_keypoints": 25, "dim": 2, "n_layers": torch.tensor(10**6)}, tmp_path / "map.ckpt")
    with pytest.raises(ValueError, match=r"map.ckpt: hyper-parameter n_layers is a tensor"):
        LearnedMap(str(path))  # what map=learned map.checkpoint=... builds


def _zip_bomb(path: Path, member: str, declared: int, prefix: bytes = b"") -> Path:
    """A zip whose ``member`` deflates ``declared`` bytes of zeros (after ``prefix``) into a few hundred kB."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z, z.open(member, "w", force_zip64=True) as f:
        f.write(prefix)
        zeros = bytes(1 << 24)
        for _ in range(declared // len(zeros)):
            f.write(zeros)
    return path


BOMB = 1 << 30  # 1 GiB declared


def _npz_bomb(path: Path) -> Path:
    """An npz whose ``keypoints`` member declares (and holds, as deflated zeros) 1 GiB of float32."""
    import io

    header = np.lib.format.header_data_from_array_1_0(np.zeros(4, np.float32))
    header["shape"] = (BOMB // 4,)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return _zip_bomb(path, "keypoints.npy", BOMB, buf.getvalue())


def test_compressed_entries_that_would_expand_are_refused_before_decompressing(tmp_path):
    from kpflow.data.source_index import SourceIndex

    ckpt = _zip_bomb(tmp_path / "bomb.ckpt", "archive/data/0", BOMB)
    with pytest.raises(
        ValueError, match=r"bomb.ckpt: member 'archive/data/0' claims 1073741824 bytes from \d+ stored, beyond 64 times"
    ):
        from kpflow import load_policy

        load_policy(ckpt)
    npz = _npz_bomb(tmp_path / "bomb.source_index.npz")
    with pytest.raises(ValueError, match=r"array 'keypoints' claims \d+ bytes from \d+ stored, beyond 64 times"):
        SourceIndex.load(npz)


def test_a_sparse_zarr_chunk_of_gigabytes_is_refused_unread(store):
    from kpflow.data.zarr_checks import UnsafeStoreError

    chunk = next(p for p in (store / "data" / "keypoints").iterdir() if not p.name.startswith("."))
    os.truncate(chunk, 8 << 30)  # 8 GiB on disk, sparse: nothing written
    with pytest.raises(
        UnsafeStoreError, match=rf"keypoints/{chunk.name} is 8589934592 bytes on disk, more than it can hold"
    ):
        EpisodeStore(store).field("keypoints")


def test_a_small_parquet_declaring_millions_of_frames_is_refused(dataset, tmp_path):
    info_path = dataset / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    files = sorted(dataset.glob("data/*/*.parquet"))
    template = pq.read_table(files[0])
    n = 2_000_000
    columns = {}
    for name in template.column_names:  # every frame the same: dictionary and run-length encodings shrink it to kB
        columns[name] = template.column(name).combine_chunks().take(pa.array(np.zeros(n, np.int64)))
    for f in files:
        f.unlink()
    pq.write_table(pa.table(columns), files[0], compression="zstd", compression_level=19)
    assert files[0].stat().st_size < 1_000_000  # against hundreds of MB decoded
    info["total_frames"], info["total_episodes"] = n, 1
    info_path.write_text(json.dumps(info))
    with pytest.raises(
        ValueError, match=rf"{files[0].name} declares 2000000 frames of \d+ values \(\d+ bytes\) in a \d+-byte file"
    ):
        import_lerobot(dataset, tmp_path / "x.zarr")


def test_a_parquet_list_column_holding_more_values_per_row_than_declared_is_refused_before_decoding(dataset, tmp_path):
    """Issue 63.6: rows of the declared count whose state column holds 20,000 values each instead of the 50 the
    features give (a 7.6 kB file held 2,000,000 per row, 2.7 GB decoded): the footer's value count is refused."""
    files = sorted(dataset.glob("data/*/*.parquet"))
    table = pa.concat_tables([pq.read_table(f) for f in files])
    per_row, n = 20_000, table.num_rows
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * per_row)
    columns = {name: table.column(name).combine_chunks() for name in table.column_names}
    columns["observation.state"] = pa.ListArray.from_arrays(offsets, pa.array(np.zeros(n * per_row, np.float32)))
    for f in files:
        f.unlink()
    pq.write_table(pa.table(columns), files[0], compression="zstd")
    assert files[0].stat().st_size < 100_000
    with pytest.raises(
        ValueError,
        match=rf"{files[0].name} declares {n * per_row} values in column observation.state over {n} rows, more than the 50 per row",
    ):
        import_lerobot(dataset, tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def test_refusals_keep_memory_bounded(tmp_path, store):
    """In a fresh process, the 1 GiB checkpoint and npz bombs, the 8 GiB sparse chunk and the checkpoints asking for
    10^8 diffusion steps (issue 57: 1.5 GB at 10^7), a 2^27-action chunk (34 GB) and a 2^22-action chunk given as a
    tensor (issue 63: 4.7 GB) are refused while its peak
    resident memory grows by less than 200 MB: what they declare is never allocated."""
    _zip_bomb(tmp_path / "bomb.ckpt", "archive/data/0", BOMB)
    _npz_bomb(tmp_path / "bomb.npz")
    chunk = next(p for p in (store / "data" / "keypoints").iterdir() if not p.name.startswith("."))
    os.truncate(chunk, 8 << 30)
    _checkpoint(
        {"n_keypoints": 25, "objective": "ddpm", "objective_options": {"train_steps": 10**8}}, tmp_path / "steps.ckpt"
    )
    _checkpoint({"n_keypoints": 25, "horizon": 1 << 27}, tmp_path / "horizon.ckpt")
    import torch

    _checkpoint({"n_keypoints": 25, "horizon": torch.tensor(1 << 22)}, tmp_path / "tensor.ckpt")  # issue 63.5: 4.7 GB
    script = (
        "import resource, sys\n"
        "import kpflow\n"
        "from kpflow.data.episode_store import EpisodeStore\n"
        "from kpflow.utils.formats import read_npz\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "for load in (lambda: kpflow.load_policy(sys.argv[1]), lambda: read_npz(sys.argv[2], ['keypoints']),\n"
        "             lambda: EpisodeStore(sys.argv[3]).field('keypoints'), lambda: kpflow.load_policy(sys.argv[4]),\n"
        "             lambda: kpflow.load_policy(sys.argv[5]), lambda: kpflow.load_policy(sys.argv[6])):\n"
        "    try:\n        load()\n    except ValueError as e:\n        print('refused', str(e)[:60])\n"
        "print('grew_kb', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)\n"
    )
    files = [
        tmp_path / "bomb.ckpt",
        tmp_path / "bomb.npz",
        store,
        tmp_path / "steps.ckpt",
        tmp_path / "horizon.ckpt",
        tmp_path / "tensor.ckpt",
    ]
    done = subprocess.run(
        [sys.executable, "-c", script, *map(str, files)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and done.stdout.count("refused") == 6, done.stdout + done.stderr[-2000:]
    grew = int(done.stdout.rsplit("grew_kb", 1)[1])
    assert grew < 200_000, done.stdout


@pytest.mark.parametrize("spelling", ["list", "nested", "motors", "string"])
def test_3d_keypoint_names_in_lerobots_spellings_import_as_keypoints(tmp_path, spelling):
    """``k0.x, k0.y, k0.z, ...`` reads as 3-D keypoints whichever way LeRobot spells a feature's names."""
    with EpisodeStore(tmp_path / "s.zarr", mode="a") as s:
        for _ in range(2):
            s.add_episode(
                {
                    "keypoints": np.random.default_rng(0).random((5, 4, 3), np.float32),
                    "action": np.zeros((5, 10), np.float32),
                }
            )
    with EpisodeStore(tmp_path / "s.zarr") as s:
        root = export_lerobot(s, tmp_path / "lr", fps=10.0, task="t", robot_type="r")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    names = info["features"]["observation.state"]["names"]
    info["features"]["observation.state"]["names"] = {
        "list": names, "nested": [names[i : i + 3] for i in range(0, 12, 3)], "motors": {"motors": names}, "string": ", ".join(names),
    }[spelling]  # fmt: skip
    info_path.write_text(json.dumps(info))
    store = import_lerobot(root, tmp_path / "back.zarr")
    assert store.field("keypoints").shape == (10, 4, 3)
