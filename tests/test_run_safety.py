"""Entry points refuse bad config values naming the key before writing anything, a run folder belongs to one run,
a failed resume leaves the run's config as it was, and an interrupted collection continues where it stopped."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.demos import ensure_pusht_demos
from kpflow.utils.config_checks import TRAINER_KEYS, Key, check_config
from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]


def entry_keys():
    from hydra.utils import instantiate

    from kpflow.cli import collect, correct, evaluate, train

    return {
        "evaluate": lambda cfg: evaluate.keys_of(evaluate.with_task_built(cfg)[1]),
        "train": train.KEYS,
        "collect": lambda cfg: collect.keys_of(instantiate(cfg.task)),
        "correct": correct.KEYS,
    }


BAD = [
    ("evaluate", "n_configs=abc", r"config key n_configs must be an integer >= 1; got 'abc' \(str\)"),
    ("evaluate", "workers=0", "config key workers must be an integer >= 1; got 0"),
    (
        "evaluate",
        "condition=bogus",
        "config key condition must be one of in_distribution, .*standard, all; got 'bogus'",
    ),
    ("collect", "n_episodes=abc", "config key n_episodes must be an integer >= 1; got 'abc'"),
    (
        "collect",
        "condition=bogus",
        "config key condition must be one of in_distribution, robot_ood, object_ood, standard or null; got 'bogus'",
    ),
    ("collect", "keep_failures=maybe", "config key keep_failures must be true or false; got 'maybe'"),
    ("correct", "rounds=abc", "config key rounds must be an integer >= 1; got 'abc'"),
    ("correct", "rounds=0", "config key rounds must be an integer >= 1; got 0"),
    ("correct", "eval_configs=1.5", "config key eval_configs must be an integer >= 0; got 1.5"),
    ("train", "trainer.max_epochs=abc", "config key trainer.max_epochs must be an integer >= -1 or null; got 'abc'"),
    (
        "train",
        "+trainer.gradient_clip_val=-1",
        "config key trainer.gradient_clip_val must be a finite number >= 0 or null; got -1",
    ),
    ("train", "resume=yes", "config key resume must be true or false; got 'yes'"),
    # issue 40: a seed numpy cannot take, and a number that is not finite, name their key
    ("evaluate", "seed=4294967296", r"config key seed must be an integer in 0..2147483647; got 4294967296"),
    ("collect", "seed=-1", r"config key seed must be an integer in 0..2147483647; got -1"),
    (
        "train",
        "+trainer.gradient_clip_val=inf",
        "config key trainer.gradient_clip_val must be a finite number >= 0 or null; got inf",
    ),
]


@pytest.mark.parametrize("entry, override, message", BAD, ids=[f"{e}:{o}" for e, o, _ in BAD])
def test_bad_values_name_the_key(entry, override, message):
    with initialize_config_dir(str(ROOT / "kpflow" / "conf"), version_base="1.3"):
        cfg = compose(entry, overrides=[override], return_hydra_config=True)
    keys = entry_keys()[entry]
    with pytest.raises(ValueError, match=message):
        check_config(cfg, keys(cfg) if callable(keys) else keys)


def test_good_configs_pass_their_checks():
    for entry, keys in entry_keys().items():
        with initialize_config_dir(str(ROOT / "kpflow" / "conf"), version_base="1.3"):
            cfg = compose(entry, return_hydra_config=True)
        check_config(cfg, keys(cfg) if callable(keys) else keys)
    for trainer in ("cpu", "gpu", "ddp"):
        with initialize_config_dir(str(ROOT / "kpflow" / "conf"), version_base="1.3"):
            check_config(compose("train", overrides=[f"trainer={trainer}"]), TRAINER_KEYS)


def test_key_spec_by_hand():
    assert Key(int, lo=1).accepts(3) and not Key(int).accepts(True) and not Key(int).accepts(2.0)
    assert Key(float, lo=0).accepts(2) and not Key(float, lo=0).accepts(-0.5)
    assert Key(int, nullable=True).accepts(None) and not Key(int).accepts(None)
    assert Key(str, choices=("a", "b")).accepts("a") and not Key(str, choices=("a",)).accepts("b")


def run(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("cmd", [
    ("kpflow.cli.evaluate", "n_configs=abc"),
    ("kpflow.cli.collect", "split=bogus"),
    ("kpflow.cli.correct", "rounds=0"),
    ("kpflow.cli.train", "trainer.max_epochs=abc"),
], ids=["evaluate", "collect", "correct", "train"])  # fmt: skip
def test_a_refused_config_leaves_no_run_folder(tmp_path, cmd):
    out = tmp_path / "run"
    done = run_command(*cmd, f"hydra.run.dir={out}")  # in this process: the error path needs no fresh interpreter
    assert done.returncode != 0 and "config key" in done.stderr, done.stderr[-2000:]
    assert not out.exists()


@pytest.mark.parametrize("cmd, message", [
    (("kpflow.cli.train", "experiment=kcfm", "data.path=/nonexistent", "logger=none"), "no episode store at /nonexistent"),
    (("kpflow.cli.evaluate", "policy=kcfm", "checkpoint=/nonexistent.ckpt", "logger=none"), "no checkpoint at /nonexistent.ckpt"),
], ids=["train", "evaluate"])  # fmt: skip
def test_a_run_that_fails_before_its_first_result_leaves_no_folder(tmp_path, cmd, message):
    """Issue 66: a run that passed its checks but failed building its data or policy left its folder (evaluate: with
    a config.yaml of a run that never ran), and Hydra's ``outputs/<task>/`` above it, behind."""
    out = tmp_path / "run"
    done = run_command(*cmd, f"hydra.run.dir={out}")
    assert done.returncode != 0 and message in done.stderr, done.stderr[-2000:]
    assert not out.exists()


def test_the_folders_made_for_a_removed_run_go_with_it(tmp_path, monkeypatch):
    from kpflow.utils.run import remove_unused_run_folder

    monkeypatch.chdir(tmp_path)
    (tmp_path / "outputs" / "kept").mkdir(parents=True)
    run = tmp_path / "outputs" / "kcfm" / "2026-12-07_10-00-00"
    run.mkdir(parents=True)
    (run / "train.log").write_text("")  # Hydra's job log: bookkeeping
    remove_unused_run_folder(run)
    assert not (tmp_path / "outputs" / "kcfm").exists() and (tmp_path / "outputs" / "kept").is_dir()


@pytest.mark.slow
def test_run_folder_belongs_to_one_run_and_a_failed_resume_keeps_its_config(tmp_path):
    out = tmp_path / "run"
    base = (
        "train.py",
        "experiment=frames_field",
        "logger=csv",
        f"hydra.run.dir={out}",
        "data.n_points=60",
        "trainer.enable_progress_bar=false",
    )
    assert run(*base, "trainer.max_epochs=1").returncode == 0
    config = (out / "config.yaml").read_text()
    checkpoints = sorted(p.name for p in (out / "checkpoints").iterdir())

    done = run_command("kpflow.cli.train", *base[1:], "trainer.max_epochs=1")  # the same run_name again, without resume
    assert done.returncode != 0 and "already holds a run" in done.stderr and "resume=true" in done.stderr
    done = run_command(
        "kpflow.cli.train", *base[1:], "trainer.max_epochs=2", "resume=true", "model.hidden=64"
    )  # a resume that cannot work
    assert done.returncode != 0 and "does not fit the configured model" in done.stderr and "net.0.weight" in done.stderr
    assert (out / "config.yaml").read_text() == config  # the run's config, as it was
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == checkpoints  # no last-v1.ckpt beside them
    assert len(list((out / "csv").iterdir())) == 1  # and no logger folder for the failed attempts

    assert run(*base, "trainer.max_epochs=2", "resume=true").returncode == 0
    assert "max_epochs: 2" in (out / "config.yaml").read_text()


def same_store(a: Path, b: Path) -> None:
    x, y = EpisodeStore(a), EpisodeStore(b)
    assert len(x) == len(y) and x.fields == y.fields
    np.testing.assert_array_equal(x.episode_ends, y.episode_ends)
    for name in x.fields:
        np.testing.assert_array_equal(x.field(name), y.field(name))
    assert [x.episode_attrs(i) for i in range(len(x))] == [y.episode_attrs(i) for i in range(len(y))]


@pytest.mark.slow
def test_an_interrupted_collection_continues_where_it_stopped(tmp_path, monkeypatch):
    partial, whole = tmp_path / "partial.zarr", tmp_path / "whole.zarr"
    add = EpisodeStore.add_episode

    def interrupted(self, episode, attrs=None):
        if len(self) == 1:
            raise KeyboardInterrupt  # Ctrl-C after the first episode
        return add(self, episode, attrs)

    with monkeypatch.context() as m:
        m.setattr(EpisodeStore, "add_episode", interrupted)
        with pytest.raises(KeyboardInterrupt):
            collect_pusht(partial, 3, workers=1, progress=False)
    assert len(EpisodeStore(partial)) == 1
    summary = collect_pusht(partial, 3, workers=2, progress=False)
    assert summary["resumed_from"] == 1 and summary["episodes"] == 3
    collect_pusht(whole, 3, workers=1, progress=False)
    same_store(partial, whole)
    assert collect_pusht(partial, 3, progress=False)["attempts"] == 0  # complete: nothing to do
    ensure_pusht_demos(partial, 3, workers=1)  # and the demos it is used as are accepted


def test_collection_refuses_another_collections_store_without_touching_it(tmp_path):
    path = tmp_path / "demos.zarr"
    collect_pusht(path, 1, workers=1, progress=False)
    before = {p: p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file() and "lock" not in p.name}
    with pytest.raises(ValueError, match=r"another collection \(seed: 0 there, 1 asked\)"):
        collect_pusht(path, 1, seed=1, progress=False)
    with pytest.raises(ValueError, match=r"another collection \(n_episodes: 1 there, 2 asked\)"):
        collect_pusht(path, 2, progress=False)
    with pytest.raises(ValueError, match="another collection.*split: 'in_distribution' there, 'robot_ood' asked"):
        ensure_pusht_demos(path, 1, split="robot_ood", workers=1)
    with pytest.raises(ValueError, match="unknown Push-T split 'bogus'"):
        collect_pusht(tmp_path / "new.zarr", 2, split="bogus", progress=False)
    assert not (tmp_path / "new.zarr").exists()
    assert {p: p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file() and "lock" not in p.name} == before


COLLECT = """
import sys
from kpflow.tasks.pusht.demos import ensure_pusht_demos
ensure_pusht_demos(sys.argv[1], 4, workers=1)
"""


@pytest.mark.slow
def test_a_killed_first_use_collection_is_resumed_by_the_next_run(tmp_path):
    path, whole = tmp_path / "demos.zarr", tmp_path / "whole.zarr"
    proc = subprocess.Popen([sys.executable, "-c", COLLECT, str(path)], cwd=ROOT, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    # Wait for the array's metadata, not its folder: zarr makes the folder first, and a store read in between has
    # data but no episode_ends yet (which EpisodeStore refuses, as it should).
    while not ((path / "meta" / "episode_ends" / ".zarray").exists() and len(EpisodeStore(path)) >= 1):
        assert proc.poll() is None and time.monotonic() - t0 < 120
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 1 <= len(EpisodeStore(path)) < 4
    ensure_pusht_demos(path, 4, workers=1)
    collect_pusht(whole, 4, workers=1, progress=False)
    same_store(path, whole)


def _ensure(path: str) -> None:
    ensure_pusht_demos(path, 2, workers=1)


def test_two_jobs_collecting_into_one_store_on_first_use_give_one_collection(tmp_path):
    """What a joblib sweep does on first use: the second job waits for the first's lock and finds the store done."""
    import multiprocessing as mp

    path, whole = tmp_path / "demos.zarr", tmp_path / "whole.zarr"
    jobs = [mp.get_context("fork").Process(target=_ensure, args=(str(path),)) for _ in range(2)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(300)
        assert job.exitcode == 0
    collect_pusht(whole, 2, workers=1, progress=False)
    same_store(path, whole)


def test_wandb_mode_disabled_leaves_the_wandb_logger_out(tmp_path, monkeypatch):
    from kpflow.utils.run import make_loggers
    from tests.helpers import compose_config

    cfg = compose_config("evaluate", ["logger=default"], tmp_path)
    monkeypatch.setenv("WANDB_MODE", "offline")  # the default logger group: CSV and an offline wandb run
    assert [type(lg).__name__ for lg in make_loggers(cfg)] == ["CSVLogger", "WandbLogger"]
    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert [type(lg).__name__ for lg in make_loggers(cfg)] == ["CSVLogger"]


def test_a_run_with_wandb_disabled_writes_no_wandb_folder(tmp_path):
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "evaluate.py",
        "experiment=frames",
        "map=affine",
        "logger=default",
        "experiment.n_configs=2",
        "task.n_points=40",
        f"hydra.run.dir={out}",
    ]
    done = subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, "WANDB_MODE": "disabled"}
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert list((out / "csv").rglob("metrics.csv"))  # the run logged, through the CSV logger only
    assert not (out / "wandb").exists() and "wandb:" not in done.stdout + done.stderr  # nor wandb's console lines
