"""Stores on disk can neither run code nor be silently wrong (issue 40).

Code execution: a zarr array whose ``.zarray`` names numcodecs' pickle filter (object or ``<i8`` dtype) runs the
pickle's payload when zarr decodes a chunk. Every planted store is refused before any chunk is decoded, by the
read-only ``EpisodeStore``, by ``evaluate.py`` and ``train.py`` given the store, and by the Push-T importer; and the
same payload read with plain zarr does create its marker (the payload is live). Allocation: chunk shapes and
compressed headers that declare more than a chunk are refused before decoding. Silent wrong data: an edited dtype,
bytes changed inside a chunk and chunks swapped between two fields are refused naming the field and the episode;
source indexes refuse non-finite or negative weights; a LeRobot dataset whose names repeat is refused.
"""

import json
import pickle
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import zarr
from numcodecs import Blosc

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.lerobot_dataset import export_lerobot, import_lerobot
from kpflow.data.source_index import SourceIndex
from kpflow.data.zarr_checks import MAX_CHUNK_BYTES, UnsafeStoreError
from kpflow.tasks.pusht.replay_import import import_pusht_replay
from kpflow.utils.formats import read_npz, read_yaml
from tests.helpers import run_command, walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]


class Payload:
    """Unpickling this creates ``marker``: what a malicious store would do (any function could be called)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def plant_pickle(array_dir: Path, marker: Path, dtype: str) -> None:
    """Give the zarr array at ``array_dir`` the pickle filter and make its first chunk the payload."""
    meta = json.loads((array_dir / ".zarray").read_text())
    meta.update(dtype=dtype, filters=[{"id": "pickle", "protocol": 5}], compressor=None)
    (array_dir / ".zarray").write_text(json.dumps(meta))
    first = "0" if len(meta["shape"]) == 1 else ".".join("0" * len(meta["shape"]))
    (array_dir / first).write_bytes(pickle.dumps(Payload(marker)))


def assert_live(array_dir: Path, marker: Path) -> None:
    """Control: plain zarr (no kpflow check) runs the payload."""
    assert not marker.exists()
    try:
        zarr.open_array(str(array_dir), mode="r")[:1]
    except Exception:
        pass  # the payload ran before the decoded object failed to fit the array
    assert marker.exists()


@pytest.fixture
def store(tmp_path) -> Path:
    """A Push-T-shaped store of 8 episodes (keypoints, action), written by kpflow."""
    walk_to_block_store(tmp_path / "demos.zarr")
    return tmp_path / "demos.zarr"


# ------------------------------------------------------------------------------------------ code execution


@pytest.mark.parametrize(
    "array, dtype",
    [("meta/episode_ends", "|O"), ("meta/episode_ends", "<i8"), ("data/action", "|O"), ("data/action", "<f4")],
)
def test_pickle_filter_is_refused_on_open_before_any_chunk_is_decoded(store, tmp_path, array, dtype):
    marker = tmp_path / "pwned"
    plant_pickle(store / array, marker, dtype)
    for mode in ("r", "a"):
        with pytest.raises(
            UnsafeStoreError, match=rf"{store}/{array}: (filters \[.pickle.\] are refused|dtype '\|O' is refused)"
        ):
            EpisodeStore(store, mode=mode)
    assert not marker.exists()
    assert_live(store / array, marker)


def test_pickle_filter_planted_under_an_open_store_is_refused_when_a_field_is_read(store, tmp_path):
    marker = tmp_path / "pwned"
    opened = EpisodeStore(store)
    plant_pickle(store / "data/action", marker, "<f4")  # after the store was opened and checked
    with pytest.raises(UnsafeStoreError, match="filters"):  # every read re-reads the array's metadata through the check
        opened.episode(0)
    with pytest.raises(UnsafeStoreError):
        EpisodeStore(store).episode(0)
    assert not marker.exists()


def test_pusht_importer_refuses_a_planted_replay_buffer(tmp_path):
    marker = tmp_path / "pwned"
    source = tmp_path / "replay.zarr"
    root = zarr.open_group(str(source), mode="w")
    compressor = Blosc(cname="zstd", clevel=5, shuffle=Blosc.BITSHUFFLE)
    root.create_dataset("data/state", data=np.zeros((10, 5), np.float32), chunks=(10, 5), compressor=compressor)
    root.create_dataset("data/action", data=np.zeros((10, 2), np.float32), chunks=(10, 2), compressor=compressor)
    root.create_dataset("meta/episode_ends", data=np.array([10]), chunks=(10,), compressor=compressor)
    plant_pickle(source / "data/state", marker, "<f4")
    with pytest.raises(UnsafeStoreError, match="filters"):
        import_pusht_replay(source, tmp_path / "dest", progress=False)
    done = run_command("kpflow.tasks.pusht.replay_import", str(source), str(tmp_path / "dest2"), "--no-progress")
    assert (
        done.returncode == 1 and "filters ['pickle'] are refused" in done.stderr and len(done.stderr.splitlines()) == 2
    ), done.stderr
    assert not marker.exists() and not (tmp_path / "dest").exists() and not (tmp_path / "dest2").exists()
    assert_live(source / "data/state", marker)


@pytest.mark.parametrize("entry", ["evaluate", "train"])
def test_entry_points_refuse_a_planted_store(store, tmp_path, entry):
    marker = tmp_path / "pwned"
    plant_pickle(store / "data/action", marker, "<f4")
    common = ["data=pusht_store", f"data.path={store}", "logger=none", f"hydra.run.dir={tmp_path / 'run'}"]
    if entry == "evaluate":
        cmd = ["kpflow.cli.evaluate", "policy=transport", "split=in_distribution", "n_configs=1", "workers=1", *common]
    else:
        cmd = ["kpflow.cli.train", "experiment=pusht_kcfm", "data.workers=0", "trainer.max_epochs=1", *common]
    done = run_command(*cmd)  # in this process: a payload that ran would have run here, and made the marker
    assert done.returncode == 1 and "filters ['pickle'] are refused" in done.stderr, done.stderr[-2000:]
    assert len(done.stderr.strip().splitlines()) <= 3, done.stderr  # one line, not a traceback
    assert not marker.exists()


# ------------------------------------------------------------------------------------------ allocation


def test_a_chunk_shape_beyond_the_limit_is_refused(store):
    meta = json.loads((store / "data/keypoints/.zarray").read_text())
    meta["chunks"] = [1 << 30, 25, 2]
    (store / "data/keypoints/.zarray").write_text(json.dumps(meta))
    with pytest.raises(
        UnsafeStoreError,
        match=f"would take 204800 MiB to decode; kpflow reads chunks of at most {MAX_CHUNK_BYTES >> 20} MiB",
    ):
        EpisodeStore(store)


def test_a_blosc_header_claiming_more_than_a_chunk_is_refused_before_decoding(store):
    chunk = store / "data/action/0.0"
    raw = bytearray(chunk.read_bytes())
    struct.pack_into("<I", raw, 4, 2_000_000_000)  # the header's decoded size (nbytes): 2 GB from a few hundred bytes
    chunk.write_bytes(bytes(raw))
    opened = EpisodeStore(store)
    with pytest.raises(
        UnsafeStoreError, match=r"chunk data/action/0.0 decodes to 2000000000 bytes, but a chunk of this array is \d+"
    ):
        opened.episode(0)


@pytest.mark.parametrize("compressor, match", [({"id": "zstd", "level": 1}, "compressor 'zstd' is not one kpflow decodes"),
                                               ({"id": "pickle"}, "compressor 'pickle' is not one kpflow decodes")])  # fmt: skip
def test_compressors_off_the_list_are_refused(store, compressor, match):
    meta = json.loads((store / "data/action/.zarray").read_text())
    meta["compressor"] = compressor
    (store / "data/action/.zarray").write_text(json.dumps(meta))
    with pytest.raises(UnsafeStoreError, match=match):
        EpisodeStore(store)


def test_episode_ends_claiming_billions_of_rows_is_refused_without_reading_them(store):
    meta = json.loads((store / "meta/episode_ends/.zarray").read_text())
    meta["shape"] = [10**15]
    (store / "meta/episode_ends/.zarray").write_text(json.dumps(meta))
    with pytest.raises(
        ValueError, match=r"field 'meta/episode_ends' is missing chunk\(s\) of its first 1000000000000000 rows"
    ):
        EpisodeStore(store)


# ------------------------------------------------------------------------------------------ silent wrong data


def test_an_edited_dtype_is_refused_naming_the_field(store):
    meta = json.loads((store / "data/action/.zarray").read_text())
    meta["dtype"] = "<i4"
    (store / "data/action/.zarray").write_text(json.dumps(meta))
    control = zarr.open_group(str(store), mode="r")["data/action"][:3]  # plain zarr reads plausible integers
    assert control.dtype == np.int32
    for mode in ("r", "a"):
        with pytest.raises(
            ValueError,
            match=r"field 'action' is int32 \[2\] on disk but was written as <f4 \[2\]: its metadata was changed",
        ):
            EpisodeStore(store, mode=mode)


def rewrite_chunk(array_dir: Path, key: str, change) -> None:
    """Decode chunk ``key``, apply ``change`` to its values and encode it back with the array's own codec: bytes
    that decode to plausible numbers, as a flipped bit in the data (not the framing) would."""
    array = zarr.open_array(str(array_dir), mode="r")
    raw = (array_dir / key).read_bytes()
    values = np.frombuffer(array.compressor.decode(raw), dtype=array.dtype).copy()
    change(values)
    (array_dir / key).write_bytes(array.compressor.encode(values))


def test_changed_bytes_inside_a_chunk_are_refused_naming_field_and_episode(store):
    before = EpisodeStore(store).episode(2)["keypoints"]
    row = int(EpisodeStore(store).episode_slice(2).start)

    def flip(values):
        values.view(np.uint32)[row * 50 + 7] ^= 1 << 20  # one bit of one mantissa: a plausible number

    rewrite_chunk(store / "data/keypoints", "0.0.0", flip)
    plain = zarr.open_group(str(store), mode="r")["data/keypoints"][row : row + 20]
    assert np.isfinite(plain).all() and 0 < np.abs(plain - before).max() < 50  # plain zarr: plausible, wrong
    opened = EpisodeStore(store)
    with pytest.raises(ValueError, match=f"{store}: field 'keypoints' of episode 2 does not match the checksum"):
        opened.episode(2)
    with pytest.raises(ValueError, match="field 'keypoints' of episode 2 does not match"):
        opened.field("keypoints")
    np.testing.assert_array_equal(
        opened.episode(1)["keypoints"], EpisodeStore(store).episode(1)["keypoints"]
    )  # others read
    with pytest.raises(ValueError, match="field 'keypoints' of episode 2"):
        opened.verify()


def test_chunks_swapped_between_two_fields_are_refused(tmp_path):
    path = tmp_path / "s.zarr"
    rng = np.random.default_rng(0)
    with EpisodeStore(path, mode="a") as s:
        for t in (5, 7):
            s.add_episode(
                {
                    "agent_pos": rng.normal(size=(t, 2)).astype(np.float32),
                    "action": rng.normal(size=(t, 2)).astype(np.float32),
                }
            )
    a, b = path / "data/action/0.0", path / "data/agent_pos/0.0"
    tmp = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(tmp)
    swapped = zarr.open_group(str(path), mode="r")
    assert swapped["data/action"][:].shape == (12, 2)  # plain zarr reads them without a word
    with pytest.raises(ValueError, match="field 'action' of episode 0 does not match the checksum"):
        EpisodeStore(path).episode(0)


def test_legacy_stores_read_unverified_refuse_appends_until_sealed(store, tmp_path):
    legacy = tmp_path / "legacy.zarr"
    shutil.copytree(store, legacy)
    attrs = json.loads((legacy / "meta/.zattrs").read_text())
    attrs.pop("fields"), attrs.pop("checksums")  # what an earlier kpflow wrote
    (legacy / "meta/.zattrs").write_text(json.dumps(attrs))
    opened = EpisodeStore(legacy)
    assert not opened.sealed and opened.verify()["sealed"] is False
    episode = opened.episode(0)
    with (
        EpisodeStore(legacy, mode="a") as s,
        pytest.raises(ValueError, match="written without checksums .*kpflow-verify seal=true"),
    ):
        s.add_episode(episode)
    done = run_command("kpflow.cli.verify", "seal=true", "progress=false", f"store={legacy}")
    assert done.returncode == 0 and "sealed now" in done.stdout, done.stderr
    with EpisodeStore(legacy, mode="a") as s:
        assert s.sealed and s.add_episode(episode) == 8
    sealed, original = (json.loads((p / "meta/.zattrs").read_text())["checksums"] for p in (legacy, store))
    assert sealed == {name: sums + sums[:16] for name, sums in original.items()}  # the same checksums as when written


def test_verify_command_names_the_damaged_field_and_episode(store):
    done = run_command("kpflow.cli.verify", "progress=false", f"store={store}")
    assert done.returncode == 0 and f"{store}: 8 episodes, 160 steps, fields action, keypoints: verified" in done.stdout

    def nudge(values):
        values[159 * 2 + 1] += 1.0  # the last row's y: episode 7 (the chunk's rows past 160 hold no data)

    rewrite_chunk(store / "data/action", "0.0", nudge)
    done = run_command("kpflow.cli.verify", "progress=false", f"store={store}")
    assert done.returncode == 1 and "field 'action' of episode 7 does not match the checksum" in done.stderr, (
        done.stderr
    )


def test_released_store_is_sealed_and_verifies():
    store = EpisodeStore(ROOT / "release/pusht_table1_35_corrected.zarr")
    assert store.sealed and store.verify()["episodes"] == store.n_episodes


# ------------------------------------------------------------------------------------------ other formats


def test_source_index_refuses_non_finite_or_negative_weights(tmp_path):
    keypoints, chunks = np.zeros((3, 4, 2), np.float32), np.zeros((3, 5, 2), np.float32)
    for weights in ([np.nan, 1, 1, 1], [1, -1, 1, 1], [0, 0, 0, 0]):
        with pytest.raises(ValueError, match="keypoint weights must be finite, >= 0 and not all 0"):
            SourceIndex(keypoints, chunks, np.asarray(weights, np.float32))
    path = SourceIndex(keypoints, chunks).save(tmp_path / "index.npz")
    np.savez(
        tmp_path / "bad.npz",
        keypoints=keypoints,
        chunks=chunks,
        weights=np.array([np.nan, 1, 1, 1], np.float32),
        reference=np.zeros(0, np.int64),
    )
    with pytest.raises(ValueError, match="bad.npz is not a usable source index: keypoint weights must be finite"):
        SourceIndex.load(tmp_path / "bad.npz")
    assert len(SourceIndex.load(path)) == 3


def test_npz_declaring_more_than_it_holds_is_refused(tmp_path):
    import io
    import zipfile

    bomb = tmp_path / "bomb.npz"
    np.savez_compressed(bomb, x=np.zeros(1 << 24, np.uint8))  # 16 MB of zeros in a few kB
    with zipfile.ZipFile(bomb) as z:
        info = z.getinfo("x.npy")
    assert info.file_size > 1000 * info.compress_size  # deflate's best, beyond the 64x (and 1 MiB) kpflow allows
    with pytest.raises(
        ValueError,
        match=r"bomb.npz: array 'x' claims 16777344 bytes from \d+ stored, beyond 64 times plus 1048576 bytes",
    ):
        read_npz(bomb, ["x"])
    small = tmp_path / "small.npz"
    np.savez_compressed(small, x=np.zeros(1 << 19, np.uint8))  # 512 kB of zeros: within the slack every member has
    assert read_npz(small, ["x"])["x"].shape == (1 << 19,)
    lying = tmp_path / "lying.npz"
    with zipfile.ZipFile(lying, "w") as z:  # a header that declares 10^10 values over 32 bytes of data
        header = np.lib.format.header_data_from_array_1_0(np.zeros(4))
        header["shape"] = (10**10,)
        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, header)
        z.writestr("x.npy", buf.getvalue() + np.zeros(4).tobytes())
    with pytest.raises(
        ValueError, match=r"array 'x' declares \(10000000000,\) x float64 \(80000000000 bytes\) but holds 32"
    ):
        read_npz(lying, ["x"])
    objects = tmp_path / "objects.npz"
    np.savez(objects, x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="array 'x' has dtype object"):
        read_npz(objects, ["x"])


def test_yaml_aliases_are_refused(tmp_path):
    bomb = tmp_path / "config.yaml"
    bomb.write_text(
        "a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n"
    )
    with pytest.raises(ValueError, match="uses YAML anchors or aliases"):
        read_yaml(bomb)
    ok = tmp_path / "ok.yaml"
    ok.write_text("seed: 3\nexperiment: {n_trials: 2}\n")
    assert read_yaml(ok).experiment.n_trials == 2


def test_lerobot_dataset_with_repeated_feature_names_is_refused(store, tmp_path):
    root = export_lerobot(EpisodeStore(store), tmp_path / "lerobot")
    info = json.loads((root / "meta/info.json").read_text())
    names = info["features"]["observation.state"]["names"]
    info["features"]["observation.state"]["names"] = [names[0]] * len(names)  # every value named k0.x
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"feature observation.state names its values with repeats \(\['k0.x'\]\)"):
        import_lerobot(root, tmp_path / "imported.zarr")
    assert not (tmp_path / "imported.zarr").exists()
    info["features"]["observation.state"]["names"] = names[2:] + names[:2]  # every name once, out of order
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="keypoint names are not k0.x, k0.y, ... in order"):
        import_lerobot(root, tmp_path / "imported.zarr", columns={"observation.state": "keypoints", "action": "action"})
    assert import_lerobot(root, tmp_path / "as_state.zarr").episode(0)["state"].shape[1:] == (
        50,
    )  # by default: a flat state
    info["features"]["observation.state"]["names"] = names
    (root / "meta/info.json").write_text(json.dumps(info))
    assert import_lerobot(root, tmp_path / "imported.zarr").episode(0)["keypoints"].shape[1:] == (25, 2)


def test_lerobot_files_declaring_other_row_counts_are_refused_before_decompressing(store, tmp_path):
    root = export_lerobot(EpisodeStore(store), tmp_path / "lerobot")
    info = json.loads((root / "meta/info.json").read_text())
    info["total_frames"] = 10
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="info.json says 10 frames, the data files declare 160"):
        import_lerobot(root, tmp_path / "imported.zarr")


def test_damaged_checksum_records_are_refused_on_open(store):
    attrs = json.loads((store / "meta/.zattrs").read_text())
    for damage in ({**attrs["checksums"], "action": "zz" + attrs["checksums"]["action"][2:]},  # not hex
                   {**attrs["checksums"], "action": attrs["checksums"]["action"][:-16]},  # one episode short
                   {"action": attrs["checksums"]["action"]}):  # a field missing  # fmt: skip
        (store / "meta/.zattrs").write_text(json.dumps({**attrs, "checksums": damage}))
        with pytest.raises(
            ValueError, match="checksums are damaged|meta/.zattrs' field record or checksums are damaged"
        ):
            EpisodeStore(store)
