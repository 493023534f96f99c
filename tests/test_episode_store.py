"""EpisodeStore: round trip, the standard replay-buffer layout, appending, validation and crash recovery."""

from pathlib import Path

import numpy as np
import pytest
import zarr

from kpflow.data.episode_store import EpisodeStore

PUSHT = Path(__file__).resolve().parents[2] / "shared/data/pusht_cchi_v7_replay.zarr"
LENGTHS = [3, 7, 1, 12]


def make_episode(t: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "keypoints": rng.normal(size=(t, 25, 2)).astype(np.float32),
        "action": rng.normal(size=(t, 2)).astype(np.float32),
        "state": rng.normal(size=(t, 5)),
    }


def concat(episodes: list[dict[str, np.ndarray]], name: str) -> np.ndarray:
    return np.concatenate([e[name] for e in episodes])


@pytest.fixture
def filled(tmp_path) -> tuple[Path, list[dict[str, np.ndarray]]]:
    """A store with LENGTHS episodes written and closed."""
    path = tmp_path / "demos.zarr"
    store = EpisodeStore(path, mode="a")
    episodes = [make_episode(t, seed) for seed, t in enumerate(LENGTHS)]
    for seed, e in enumerate(episodes):
        assert store.add_episode(e, attrs={"seed": seed, "success": seed % 2 == 0}) == seed
    return path, episodes


def assert_same(store: EpisodeStore, episodes: list[dict[str, np.ndarray]]) -> None:
    ends = np.cumsum([len(next(iter(e.values()))) for e in episodes])
    assert store.n_episodes == len(store) == len(episodes)
    assert store.n_steps == (ends[-1] if len(ends) else 0)
    np.testing.assert_array_equal(store.episode_ends, ends)
    for got, want in zip(store, episodes, strict=True):
        assert set(got) == set(want)
        for name in want:
            np.testing.assert_array_equal(got[name], want[name])


def test_round_trip(filled):
    path, episodes = filled
    store = EpisodeStore(path)
    assert_same(store, episodes)
    assert store.fields == ("action", "keypoints", "state")
    np.testing.assert_array_equal(store.episode(-1)["keypoints"], episodes[-1]["keypoints"])
    assert store.episode_slice(1) == slice(3, 10) and store.episode_slice(-4) == slice(0, 3)
    np.testing.assert_array_equal(store.field("state"), concat(episodes, "state"))
    assert store.field("keypoints").dtype == np.float32 and store.field("state").dtype == np.float64
    assert store.episode_attrs(2) == {"seed": 2, "success": True}
    assert (
        f"{path}" in repr(store)
        and "episodes=4" in repr(store)
        and "steps=23" in repr(store)
        and "keypoints" in repr(store)
    )
    with pytest.raises(IndexError, match=r"episode 4 out of range.*4 episodes"):
        store.episode(4)
    with pytest.raises(IndexError, match="-4..3"):
        store.episode_slice(-5)
    with pytest.raises(KeyError, match="nope"):
        store.field("nope")


def test_layout_is_the_standard_replay_buffer(filled):
    path, episodes = filled
    root = zarr.open(str(path), mode="r")
    assert set(root.group_keys()) == {"data", "meta"}
    for name in ("keypoints", "action", "state"):
        np.testing.assert_array_equal(root[f"data/{name}"][:], concat(episodes, name))
        assert root[f"data/{name}"].compressor.cname == "zstd"
    ends = root["meta/episode_ends"]
    assert ends.dtype == np.int64
    np.testing.assert_array_equal(ends[:], np.cumsum(LENGTHS))


def test_reopen_and_append(filled):
    path, episodes = filled
    store = EpisodeStore(path, mode="a")
    store.attrs["task"] = "pusht"
    more = make_episode(5, seed=10)
    assert store.add_episode(more) == 4
    again = EpisodeStore(path)
    assert_same(again, [*episodes, more])
    assert again.attrs["task"] == "pusht"
    assert again.episode_attrs(0) == {"seed": 0, "success": True} and again.episode_attrs(4) == {}
    assert len(zarr.open(str(path), mode="r")["meta"].attrs["episode_attrs"]) == 5


def test_casts_within_kind(tmp_path):
    store = EpisodeStore(tmp_path / "s.zarr", mode="a")
    store.add_episode(make_episode(2, 0))
    e = make_episode(3, 1)
    e["keypoints"] = e["keypoints"].astype(np.float64)
    store.add_episode(e)
    assert store.episode(1)["keypoints"].dtype == np.float32


def bad_episodes() -> list[tuple[str, dict, str]]:
    good = make_episode(4, 99)
    missing = {k: v for k, v in good.items() if k != "state"}
    extra = {**good, "reward": np.zeros(4)}
    shape = {**good, "keypoints": np.zeros((4, 24, 2), np.float32)}
    length = {**good, "action": np.zeros((3, 2), np.float32)}
    nan = {**good, "state": np.where(np.arange(5) == 2, np.nan, good["state"])}
    inf = {**good, "action": np.full((4, 2), np.inf, np.float32)}
    empty = {k: v[:0] for k, v in good.items()}
    kind = {**good, "state": np.zeros((4, 5), np.complex64)}
    scalar = {**good, "action": np.float32(1.0)}
    return [
        ("missing", missing, r"missing field\(s\) \['state'\]"),
        ("extra", extra, r"extra field\(s\) \['reward'\]"),
        ("shape", shape, r"field 'keypoints' has trailing shape \(24, 2\).*\(25, 2\)"),
        ("length", length, r"length mismatch.*'action': 3"),
        ("nan", nan, "field 'state' contains NaN or inf"),
        ("inf", inf, "field 'action' contains NaN or inf"),
        ("empty", empty, "empty episode: length T = 0"),
        ("no fields", {}, "empty episode"),
        ("dtype", kind, "field 'state' has dtype complex64"),
        ("scalar", scalar, "field 'action' is a scalar"),
    ]


@pytest.mark.parametrize("what, episode, message", bad_episodes(), ids=[b[0] for b in bad_episodes()])
def test_validation_errors_name_the_problem(filled, what, episode, message):
    path, episodes = filled
    store = EpisodeStore(path, mode="a")
    with pytest.raises(ValueError, match=message):
        store.add_episode(episode)
    assert_same(EpisodeStore(path), episodes)  # nothing written
    assert zarr.open(str(path), mode="r")["data/action"].shape[0] == sum(LENGTHS)


def test_first_episode_is_validated_too(tmp_path):
    store = EpisodeStore(tmp_path / "s.zarr", mode="a")
    with pytest.raises(ValueError, match="field 'x' contains NaN"):
        store.add_episode({"x": np.array([1.0, np.nan])})
    with pytest.raises(ValueError, match="must be JSON-serialisable"):
        store.add_episode({"x": np.ones(2)}, attrs={"seed": object()})
    assert store.n_episodes == 0 and store.fields == ()


def test_opening_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no episode store at .*missing.zarr"):
        EpisodeStore(tmp_path / "missing.zarr")
    with pytest.raises(ValueError, match="mode must be"):
        EpisodeStore(tmp_path / "x.zarr", mode="w")
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "notes.txt").write_text("hi")
    for mode in ("r", "a"):
        with pytest.raises(ValueError, match=f"{plain} is not an episode store: not a zarr group"):
            EpisodeStore(plain, mode=mode)
    (tmp_path / "file").write_text("hi")
    with pytest.raises(ValueError, match="it is a file"):
        EpisodeStore(tmp_path / "file", mode="a")
    other = tmp_path / "other.zarr"
    zarr.open_group(str(other), mode="w").create_dataset("data/x", data=np.ones(3))
    for mode in ("r", "a"):
        with pytest.raises(ValueError, match=f"{other} is not an episode store: missing meta/episode_ends"):
            EpisodeStore(other, mode=mode)


def test_read_only_refuses_writes(filled):
    path, episodes = filled
    store = EpisodeStore(path)
    with pytest.raises(PermissionError, match="read-only"):
        store.add_episode(make_episode(2, 5))
    with pytest.raises(PermissionError):
        store.attrs["task"] = "x"
    assert_same(EpisodeStore(path), episodes)


def crash_before_commit(monkeypatch) -> None:
    def crash(self, end):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(EpisodeStore, "_commit", crash)


def test_crash_before_commit_loses_only_that_episode(filled, monkeypatch):
    path, episodes = filled
    with monkeypatch.context() as m:
        crash_before_commit(m)
        with pytest.raises(RuntimeError, match="simulated crash"), EpisodeStore(path, mode="a") as store:
            store.add_episode(make_episode(6, 20), attrs={"seed": 20})
    raw = zarr.open(str(path), mode="r")
    assert raw["data/action"].shape[0] == sum(LENGTHS) + 6  # the rows are on disk, uncommitted
    assert len(raw["meta"].attrs["episode_attrs"]) == 5

    assert_same(EpisodeStore(path), episodes)  # readers ignore them

    store = EpisodeStore(path, mode="a")  # appending truncates them first
    assert raw["data/keypoints"].shape[0] == sum(LENGTHS)
    more = make_episode(2, 21)
    store.add_episode(more, attrs={"seed": 21})
    reopened = EpisodeStore(path)
    assert_same(reopened, [*episodes, more])
    assert reopened.episode_attrs(-1) == {"seed": 21}
    raw = zarr.open(str(path), mode="r")
    assert all(a.shape[0] == sum(LENGTHS) + 2 for _, a in raw["data"].arrays())
    assert len(raw["meta"].attrs["episode_attrs"]) == 5


def test_torn_commit_is_an_uncommitted_episode(filled, monkeypatch):
    """A crash between zarr's two writes of an append to episode_ends (.zarray grown, value not written)."""
    path, episodes = filled

    def torn(self, end):
        self._ends_array.resize(len(self._ends) + 1)  # what Array.append writes first
        raise RuntimeError("simulated crash")

    with monkeypatch.context() as m:
        m.setattr(EpisodeStore, "_commit", torn)
        with pytest.raises(RuntimeError, match="simulated crash"), EpisodeStore(path, mode="a") as store:
            store.add_episode(make_episode(6, 20))
    raw = zarr.open(str(path), mode="r")
    assert raw["meta/episode_ends"][-1] == 0 and raw["meta/episode_ends"].shape == (len(LENGTHS) + 1,)
    assert_same(EpisodeStore(path), episodes)  # readers ignore it

    with EpisodeStore(path, mode="a") as store:  # appending removes it first
        assert raw["meta/episode_ends"].shape == (len(LENGTHS),) and raw["data/state"].shape[0] == sum(LENGTHS)
        more = make_episode(3, 30)
        store.add_episode(more)
    assert_same(EpisodeStore(path), [*episodes, more])
    assert "pending_episode" not in zarr.open(str(path), mode="r")["meta"].attrs


def damage(path: Path, how: str) -> None:
    """Damage a filled store with raw zarr the way a bug or a hand edit would (no append was in progress)."""
    raw = zarr.open(str(path), mode="a")
    ends = raw["meta/episode_ends"]
    if how == "last end not above the one before":
        ends[-1] = ends[-2]
    elif how == "index shorter than the data":
        ends.resize(len(LENGTHS) - 2)
    elif how == "empty index with full data":
        ends.resize(0)
    elif how == "index longer than the data":
        for name in ("action", "keypoints", "state"):
            raw[f"data/{name}"].resize(sum(LENGTHS) - 5, *raw[f"data/{name}"].shape[1:])
    elif how == "more episode attrs than episodes":
        raw["meta"].attrs["episode_attrs"] = [{}] * (len(LENGTHS) + 2)
    elif how == "one array longer than the index":
        raw["data/state"].resize(sum(LENGTHS) + 4, 5)


DAMAGE = {
    "last end not above the one before": "not strictly increasing from 0 at index 3",
    "index shorter than the data": r"data/\w+ has 23 rows but meta/episode_ends ends at row 10, and no append was in progress",
    "empty index with full data": r"has 23 rows but the index is empty",
    "index longer than the data": r"has 18 rows but meta/episode_ends says 23: rows were lost",
    "more episode attrs than episodes": "lists attrs for 6 episodes but the store holds 4",
    "one array longer than the index": r"data/state has 27 rows but meta/episode_ends ends at row 23",
}


@pytest.mark.parametrize("how", DAMAGE)
def test_damaged_index_is_refused_and_left_as_it_is(filled, how):
    path, _ = filled
    damage(path, how)
    before = {
        p.relative_to(path): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file() and p.name != ".kpflow-write.lock"
    }
    for mode in ("r", "a"):
        with pytest.raises(ValueError, match=DAMAGE[how]):
            EpisodeStore(path, mode=mode)
    after = {
        p.relative_to(path): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file() and p.name != ".kpflow-write.lock"
    }
    assert after == before  # nothing was "repaired"


def test_missing_chunk_is_an_error_naming_the_field(tmp_path):
    path = tmp_path / "s.zarr"
    with EpisodeStore(path, mode="a") as store:
        for seed in range(3):
            store.add_episode({"obs": np.ones((700, 2), np.float32) * seed, "action": np.ones((700, 1))})
    (path / "data" / "obs" / "1.0").unlink()  # rows 1024..2047 of obs
    for mode in ("r", "a"):
        with pytest.raises(
            ValueError, match=r"field 'obs' is missing chunk\(s\) of its first 2100 rows \(data/obs/1.0\)"
        ):
            EpisodeStore(path, mode=mode)


def test_damaged_chunk_and_metadata_name_the_field(filled):
    path, _ = filled
    (path / "data" / "action" / "0.0").write_bytes(b"\x00garbage" * 50)
    store = EpisodeStore(path)
    with pytest.raises(ValueError, match=f"{path}: field 'action' could not be read: a chunk is damaged"):
        store.episode(0)
    with pytest.raises(ValueError, match="field 'action' could not be read"):
        store.field("action")
    good = (path / "data" / "state" / ".zarray").read_text()
    (path / "data" / "state" / ".zarray").write_text("{not json")
    for mode in ("r", "a"):
        with pytest.raises(
            ValueError, match=f"{path}: field 'state' has damaged metadata \\(data/state/.zarray: JSONDecodeError"
        ):
            EpisodeStore(path, mode=mode)
    (path / "data" / "state" / ".zarray").write_text(good)
    (path / "meta" / ".zattrs").write_text("[[[")
    with pytest.raises(ValueError, match=r"meta/.zattrs is damaged"):
        EpisodeStore(path)


HOLDER = """
import sys, time
from kpflow.data.episode_store import EpisodeStore
store = EpisodeStore(sys.argv[1], mode="a")
print("holding", flush=True)
time.sleep(float(sys.argv[2]))
"""


def test_second_writer_fails_clearly_or_waits(filled):
    import subprocess
    import sys
    import time

    path, episodes = filled
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(path), "1.5"], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "holding"
    with pytest.raises(
        TimeoutError, match=rf"{path} cannot be opened for writing: .*held by process {holder.pid}: wait"
    ):
        EpisodeStore(path, mode="a")
    with pytest.raises(TimeoutError, match=rf"held by process {holder.pid} after 0.2 s"):
        EpisodeStore(path, mode="a", wait=0.2)
    assert_same(EpisodeStore(path), episodes)  # readers take no lock
    t0 = time.monotonic()
    with EpisodeStore(path, mode="a", wait=None) as store:  # waits for the holder to exit
        assert time.monotonic() - t0 > 0.5 and holder.wait(10) == 0
        store.add_episode(make_episode(2, 50))
        with pytest.raises(TimeoutError, match="held by this process already, through another open handle"):
            EpisodeStore(path, mode="a", wait=None)  # waiting for oneself would never end
    with pytest.raises(PermissionError, match="was closed"):
        store.add_episode(make_episode(2, 51))
    assert_same(EpisodeStore(path), [*episodes, make_episode(2, 50)])


def _append(path: str, worker: int) -> None:
    for k in range(5):
        with EpisodeStore(path, mode="a", wait=None) as store:
            store.add_episode({"x": np.full((3 + k, 2), 10 * worker + k, np.float32)}, attrs={"worker": worker, "k": k})


def test_concurrent_writers_append_whole_episodes(tmp_path):
    import multiprocessing as mp

    path = str(tmp_path / "s.zarr")
    procs = [mp.get_context("fork").Process(target=_append, args=(path, w)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    store = EpisodeStore(path)
    assert len(store) == 20
    seen = set()
    for i in range(20):
        a = store.episode_attrs(i)
        x = store.episode(i)["x"]
        assert x.shape == (3 + a["k"], 2) and (x == 10 * a["worker"] + a["k"]).all()
        seen.add((a["worker"], a["k"]))
    assert len(seen) == 20


KILLED_WRITER = """
import sys, numpy as np
from kpflow.data.episode_store import EpisodeStore
store = EpisodeStore(sys.argv[1], mode="a")
for i in range(100000):
    store.add_episode({"x": np.full((50, 200), i, np.float64)}, attrs={"i": i})
    print(i, flush=True)
"""


def test_killed_writer_leaves_only_committed_episodes(tmp_path):
    import signal
    import subprocess
    import sys

    path = tmp_path / "s.zarr"
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        for _ in range(20):
            proc.stdout.readline()
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        store = EpisodeStore(path)  # a reader sees whole episodes only
        for i in range(len(store)):
            assert (store.episode(i)["x"] == store.episode_attrs(i)["i"]).all()
        with EpisodeStore(path, mode="a") as store:  # the lock died with the writer; the torn episode is removed
            assert not list(path.rglob("*.partial"))
            n = len(store)
        assert n >= 20


def test_crash_during_first_episode(tmp_path, monkeypatch):
    path = tmp_path / "s.zarr"
    with monkeypatch.context() as m:
        crash_before_commit(m)
        with pytest.raises(RuntimeError, match="simulated crash"), EpisodeStore(path, mode="a") as store:
            store.add_episode(make_episode(4, 0))
    assert zarr.open(str(path), mode="r")["data/action"].shape[0] == 4
    store = EpisodeStore(path)
    assert (store.n_episodes, store.n_steps, store.fields) == (0, 0, ())
    assert list(store) == []

    store = EpisodeStore(path, mode="a")  # the crashed episode's fields are forgotten
    other = {"obs": np.ones((2, 3), np.float32)}
    store.add_episode(other)
    assert_same(EpisodeStore(path), [other])
    assert set(zarr.open(str(path), mode="r")["data"].array_keys()) == {"obs"}


def test_standard_pusht_dataset_opens_as_is():
    if not PUSHT.exists():
        pytest.skip(f"standard Push-T replay buffer not present at {PUSHT}")
    store = EpisodeStore(PUSHT, mode="r")
    assert (store.n_episodes, store.n_steps) == (206, 25650)
    assert {"state", "action"} <= set(store.fields)
    assert store.episode_slice(0) == slice(0, 161)
    first = store.episode(0)
    assert first["state"].shape == (161, 5) and first["action"].shape == (161, 2)
