"""Generation past one machine (kpflow/generation/generate.py, kpflow/data/store_merge.py, kpflow/cli/merge.py): a run
split into shards (``shards=S shard=K``: the attempts ``i % S == K``) and merged is the unsharded run, to the bit;
the merge refuses anything but the finished shards of one run, each once, and leaves nothing behind when it fails;
and the real multirun command line through a Hydra launcher, then ``kpflow-merge``, gives the same folder."""

import json
import os
import shutil
import subprocess
import sys
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.store_merge import merge_stores
from kpflow.generation.journal import check_output, run_manifest, shard_indices
from tests.helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
#: what a merged run may differ in from one run: the timing of the attempts, and where they came from
THROUGHPUT = ("attempts_run", "attempts_per_minute", "real_time", "wall_s")
N, FAMILIES = 4, ("mimicgen", "rigid")


def files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (but the write lock, which holds its writer's pid) by relative path."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".kpflow-write.lock"
    }


def assert_same_store(a: Path, b: Path) -> None:
    """Same episodes, attrs and arrays (dtype, shape, values), and the same bytes on disk."""
    with EpisodeStore(a) as x, EpisodeStore(b) as y:
        assert x.n_episodes == y.n_episodes and x.fields == y.fields
        for i in range(x.n_episodes):
            assert x.episode_attrs(i) == y.episode_attrs(i)
            ex, ey = x.episode(i), y.episode(i)
            for name in ex:
                assert ex[name].dtype == ey[name].dtype and ex[name].shape == ey[name].shape
                assert ex[name].tobytes() == ey[name].tobytes(), f"{name} of episode {i} differs"
    assert files(a) == files(b)


def assert_same_hdf5(a: Path, b: Path) -> None:
    def walk(f: h5py.File) -> dict:
        out = {"/": dict(f.attrs)}
        f.visititems(
            lambda name, node: out.__setitem__(
                name, (dict(node.attrs), node[()] if isinstance(node, h5py.Dataset) else None)
            )
        )
        return out

    with h5py.File(a, "r") as x, h5py.File(b, "r") as y:
        wx, wy = walk(x), walk(y)
    assert sorted(wx) == sorted(wy)
    for key in wx:
        if key == "/":
            assert wx[key] == wy[key]
            continue
        (ax, vx), (ay, vy) = wx[key], wy[key]
        assert {k: str(v) for k, v in ax.items()} == {k: str(v) for k, v in ay.items()}, key
        assert (vx is None and vy is None) or (vx.dtype == vy.dtype and np.array_equal(vx, vy)), key


def without_throughput(results: dict) -> dict:
    results = json.loads(json.dumps(results))
    results.pop("merged_from", None)
    for row in results["summary"]:
        for key in THROUGHPUT:
            row.pop(key)
    return results


# ------------------------------------------------------------------------------------------ merging stores


def write_store(path: Path, indices: list[int]) -> Path:
    with EpisodeStore(path, mode="a") as store:
        store.attrs["task"] = "probe"
        for i in indices:
            rng = np.random.default_rng(i)
            store.add_episode({"action": rng.normal(size=(3 + i, 7)).astype(np.float32), "state": rng.normal(size=(3 + i, 5))},
                              attrs={"index": i, "source": i % 2})  # fmt: skip
    return path


def test_stores_merge_by_an_attribute_into_the_bytes_one_writer_writes(tmp_path):
    a, b = write_store(tmp_path / "a.zarr", [0, 2, 4]), write_store(tmp_path / "b.zarr", [1, 3])
    empty = write_store(tmp_path / "empty.zarr", [])
    reference = write_store(tmp_path / "reference.zarr", [0, 1, 2, 3, 4])
    merge_stores(tmp_path / "merged.zarr", [a, empty, b], key="index")
    assert_same_store(tmp_path / "merged.zarr", reference)
    merge_stores(tmp_path / "concatenated.zarr", [a, b])  # no key: store by store
    with EpisodeStore(tmp_path / "concatenated.zarr") as store:
        assert [store.episode_attrs(i)["index"] for i in range(len(store))] == [0, 2, 4, 1, 3]


def test_a_merge_of_stores_that_do_not_fit_together_is_refused_and_leaves_nothing(tmp_path):
    a, b = write_store(tmp_path / "a.zarr", [0, 2]), write_store(tmp_path / "b.zarr", [1, 2])
    out = tmp_path / "out.zarr"
    with pytest.raises(ValueError, match=r"index 2 is held twice: by episode 1 of .*a.zarr and episode 1 of .*b.zarr"):
        merge_stores(out, [a, b], key="index")
    with EpisodeStore(tmp_path / "c.zarr", mode="a") as c:
        c.attrs["task"] = "probe"
        c.add_episode({"action": np.zeros((2, 7)), "state": np.zeros((2, 5))}, attrs={"index": 9})  # float64 actions
    with pytest.raises(
        ValueError, match=r"fields differ \(action: \('<f4', \(7,\)\) in .*a.zarr, \('<f8', \(7,\)\) in .*c.zarr"
    ):
        merge_stores(out, [a, tmp_path / "c.zarr"], key="index")
    other = write_store(tmp_path / "other.zarr", [5])
    with EpisodeStore(other, mode="a") as s:
        s.attrs["task"] = "another"
    with pytest.raises(ValueError, match="hold different store attrs \\(task\\)"):
        merge_stores(out, [a, other])
    # a chunk damaged after it was written: found while copying, after the first episodes were written
    damaged = write_store(tmp_path / "damaged.zarr", [7, 8])
    chunk = damaged / "data" / "state" / "0.0"
    chunk.write_bytes(chunk.read_bytes()[:-1] + bytes([chunk.read_bytes()[-1] ^ 1]))
    with pytest.raises(ValueError):
        merge_stores(out, [a, damaged], key="index")
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".out.zarr")]
    merge_stores(out, [a])
    with pytest.raises(FileExistsError, match="exists already"):
        merge_stores(out, [a])


# ------------------------------------------------------------------------------------------ shards


def test_shards_split_the_attempts_by_index_and_a_resume_keeps_its_shard(tmp_path):
    assert list(shard_indices(5)) == [0, 1, 2, 3, 4]
    assert [list(shard_indices(5, 2, k)) for k in (0, 1)] == [[0, 2, 4], [1, 3]]
    for shards, shard, match in [(2, 2, r"shard must be in 0..shards-1 = 0..1; got 2"), (6, 0, "shards must be in 1..n = 1..5"),
                                 (2, -1, "shard must be in 0..shards-1")]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            shard_indices(5, shards, shard)
    task = SimpleNamespace(name="lift")
    whole = run_manifest(task, {}, ["d0"], 4, 1, 0, None, True)
    assert "shards" not in whole and "shard" not in whole  # an unsharded run's manifest is what it always was
    one = run_manifest(task, {}, ["d0"], 4, 1, 0, None, True, shards=2, shard=0)
    assert one == {**whole, "shards": 2, "shard": 0}
    (tmp_path / "generation.json").write_text(json.dumps(one))
    check_output(tmp_path, one, resume=True)
    with pytest.raises(ValueError, match=r"these differ \(shard: 0 there, 1 now\)"):
        check_output(tmp_path, {**one, "shard": 1}, resume=True)
    with pytest.raises(ValueError, match=r"these differ \(shards: 2 there, 1 now\)"):
        check_output(tmp_path, whole, resume=True)


@pytest.mark.parametrize("launcher", ["pool", "local", "slurm"])
def test_the_shards_of_a_sweep_compose_with_every_launcher_into_folders_named_by_shard(launcher, tmp_path):
    from omegaconf import read_write

    from tests.helpers import compose_config

    cfg = compose_config(
        "generate", [f"hydra/launcher={launcher}", "task=square", "shards=4", "shard=3", "run_name=NAME"], tmp_path
    )
    with read_write(cfg.hydra.job):
        cfg.hydra.job.num = 7
    assert (cfg.hydra.sweep.dir, cfg.hydra.sweep.subdir) == ("multirun/generate/square/NAME", "7_shard3")
    assert (
        cfg.hydra.launcher._target_.rsplit(".", 1)[-1]
        == {"pool": "JoblibLauncher", "local": "LocalLauncher", "slurm": "SlurmLauncher"}[launcher]
    )
    if launcher != "pool":
        assert cfg.hydra.launcher.submitit_folder == "multirun/generate/square/NAME/.submitit/%j"


def families() -> dict:
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap

    return {
        "mimicgen": SegmentTransport(None, in_hand=False),
        "rigid": SegmentTransport(partial(AffineMap, kind="rigid")),
    }


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Lift's d0 scenes, two families, four attempts each, with the robomimic export: one run and the same run as two
    shards."""
    from kpflow.generation.generate import generate
    from kpflow.tasks.suite.task import SuiteTask

    root = tmp_path_factory.mktemp("shards")
    settings = dict(n=N, workers=1, videos=0, export=True, progress=False)
    generate(root / "single", SuiteTask("lift"), families(), ["d0"], **settings)
    for k in range(2):
        generate(root / f"shard{k}", SuiteTask("lift"), families(), ["d0"], **settings, shards=2, shard=k)
    return root


@pytest.mark.slow
def test_two_shards_merged_are_the_unsharded_run_to_the_bit(runs, tmp_path):
    from kpflow.generation.generate import merge_shards

    single, out = runs / "single", tmp_path / "merged"
    for k in range(2):
        shard = json.loads((runs / f"shard{k}" / "results.json").read_text())
        assert [r["index"] for r in shard["attempts"]] == [k, k + 2] * len(FAMILIES) and shard["shards"] == 2
    merged = merge_shards([runs / "shard1", runs / "shard0"], out)  # in any order
    ours, theirs = (json.loads((d / "results.json").read_text()) for d in (out, single))
    assert json.loads(json.dumps(merged)) == ours and ours["merged_from"] == [
        str(runs / "shard0"),
        str(runs / "shard1"),
    ]
    assert without_throughput(ours) == without_throughput(theirs)
    assert [r["trials"] for r in ours["summary"]] == [N] * len(FAMILIES) and sum(
        r["successes"] for r in ours["summary"]
    ) >= N
    assert [r["attempts_run"] for r in ours["summary"]] == [N] * len(FAMILIES)  # the shards' attempts, pooled
    assert (out / "generation.json").read_bytes() == (single / "generation.json").read_bytes()
    for family in FAMILIES:
        cell, reference = out / "d0" / family, single / "d0" / family
        assert (cell / "attempts.jsonl").read_bytes() == (reference / "attempts.jsonl").read_bytes()
        assert_same_store(cell / "episodes.zarr", reference / "episodes.zarr")
        assert (cell / "demos.hdf5").exists() == (reference / "demos.hdf5").exists()
        if (reference / "demos.hdf5").exists():
            assert_same_hdf5(cell / "demos.hdf5", reference / "demos.hdf5")
    table = [line.rsplit("|", 3)[0] for line in (out / "results.md").read_text().splitlines()[4:]]
    assert table == [line.rsplit("|", 3)[0] for line in (single / "results.md").read_text().splitlines()[4:]]
    assert "Merged from 2 shards" in (out / "results.md").read_text()


def copy_shard(runs: Path, k: int, to: Path) -> Path:
    shutil.copytree(runs / f"shard{k}", to)
    return to


@pytest.mark.slow
def test_the_merge_refuses_anything_but_the_finished_shards_of_one_run_and_writes_nothing(runs, tmp_path):
    from kpflow.generation.generate import generate, merge_shards
    from kpflow.tasks.suite.task import SuiteTask

    s0, s1, out = runs / "shard0", runs / "shard1", tmp_path / "out"
    other = copy_shard(runs, 1, tmp_path / "other_seed")
    manifest = json.loads((other / "generation.json").read_text())
    (other / "generation.json").write_text(json.dumps({**manifest, "seed": 1}))
    unfinished = copy_shard(runs, 1, tmp_path / "unfinished")
    (unfinished / "results.json").unlink()
    torn = copy_shard(runs, 1, tmp_path / "torn")
    journal = torn / "d0" / "rigid" / "attempts.jsonl"
    journal.write_text(journal.read_text().splitlines(keepends=True)[0])  # as if stopped after its first attempt
    damaged = copy_shard(runs, 1, tmp_path / "damaged")
    with EpisodeStore(damaged / "d0" / "rigid" / "episodes.zarr") as store:
        assert store.n_episodes  # a chunk of the last cell flipped: found while copying, after the first cell merged
    chunk = next((damaged / "d0" / "rigid" / "episodes.zarr" / "data" / "action").glob("0.*"))
    chunk.write_bytes(chunk.read_bytes()[:-1] + bytes([chunk.read_bytes()[-1] ^ 1]))
    (tmp_path / "empty").mkdir()
    for folders, error, match in [
        ([s0], ValueError, r"the run has 2 shards but shard\(s\) \[1\] are missing: given 0 \(.*shard0\)"),
        (
            [s0, s1, copy_shard(runs, 0, tmp_path / "again")],
            ValueError,
            r"shard 0 of 2 is given twice: .*shard0 and .*again",
        ),
        ([s0, s1, s0], ValueError, r"shard0 is given twice"),
        (
            [s0, other],
            ValueError,
            r"shard0 and .*other_seed are not shards of one run: their settings \(generation.json\) differ "
            r"\(seed: 0 in .*shard0, 1 in .*other_seed\)",
        ),
        ([s0, runs / "single"], ValueError, r"differ \(shards: 2 in .*shard0, 1 in .*single\)"),
        ([s0, unfinished], ValueError, r"unfinished \(shard 1 of 2\) has not finished: it has no results.json"),
        (
            [s0, torn],
            ValueError,
            r"torn/d0/rigid/attempts.jsonl records 1 of the cell's 2 attempts: the cell is unfinished",
        ),
        (
            [s0, damaged],
            ValueError,
            r"damaged/d0/rigid/episodes.zarr: field 'action' could not be read: a chunk is damaged",
        ),
        ([s0, tmp_path / "empty"], FileNotFoundError, r"empty is not a generation run folder"),
    ]:
        with pytest.raises(error, match=match):
            merge_shards(folders, out)
        assert not out.exists() and not [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")]
    out.mkdir()
    with pytest.raises(FileExistsError, match="exists already"):
        merge_shards([s0, s1], out)
    with pytest.raises(ValueError, match=r"these differ \(shard: 0 there, 1 now\)"):  # a resume keeps its shard
        generate(
            s0,
            SuiteTask("lift"),
            families(),
            ["d0"],
            n=N,
            workers=1,
            videos=0,
            progress=False,
            resume=True,
            shards=2,
            shard=1,
        )


# ------------------------------------------------------------------------------------------ the commands


def run(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """A kpflow console script (this interpreter's) run in ``cwd``."""
    env = child_env(OMP_NUM_THREADS="1", PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_a_multirun_over_the_joblib_launcher_then_kpflow_merge_gives_the_unsharded_run(runs, tmp_path):
    sweep = ["kpflow-generate", "-m", "task=lift", f"n={N}", "variants=[d0]", "families=[mimicgen]", "workers=1", "videos=0",
             "export=false", "shards=2", "shard=range(2)", "run_name=NAME", "hydra/launcher=pool"]  # fmt: skip
    done = run(sweep, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    sweep_dir = tmp_path / "multirun" / "generate" / "lift" / "NAME"
    assert sorted(p.name for p in sweep_dir.iterdir() if p.is_dir()) == ["0_shard0", "1_shard1"]
    merge = ["kpflow-merge", "shards=multirun/generate/lift/NAME/*", "out=outputs/generate/lift/NAME"]
    done = run(merge, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "lift d0 mimicgen: " in done.stdout and "merged 2 shards into outputs/generate/lift/NAME" in done.stdout
    out, single = tmp_path / "outputs" / "generate" / "lift" / "NAME", runs / "single"
    # the module's unsharded run has two families and the export: the mimicgen cell is the same
    assert (out / "d0" / "mimicgen" / "attempts.jsonl").read_bytes() == (
        single / "d0" / "mimicgen" / "attempts.jsonl"
    ).read_bytes()
    assert_same_store(out / "d0" / "mimicgen" / "episodes.zarr", single / "d0" / "mimicgen" / "episodes.zarr")
    assert not (out / "d0" / "mimicgen" / "demos.hdf5").exists()  # the shards exported nothing
    ours, theirs = (json.loads((d / "results.json").read_text()) for d in (out, single))
    assert without_throughput(ours)["summary"] == without_throughput(theirs)["summary"][:1]
    config = (out / "config.yaml").read_text()
    assert "shards: 1\nshard: 0\n" in config and "output_dir: outputs/generate/lift/NAME\n" in config

    again = run(merge, tmp_path)  # the merged folder is there: refused, with one line
    assert again.returncode == 1 and "error: outputs/generate/lift/NAME exists already" in again.stderr
    bad = run(["kpflow-generate", "task=lift", "n=4", "shards=2", "shard=2", "hydra.run.dir=bad"], tmp_path)
    assert (
        bad.returncode == 1
        and "shard must be in 0..shards-1 = 0..1; got 2" in bad.stderr
        and not (tmp_path / "bad").exists()
    )
