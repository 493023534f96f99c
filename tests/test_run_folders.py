"""A run folder belongs to one live run (kpflow/utils/run.claim_run_folder): a second run into it is refused at once,
naming the first's pid and the folder, while the first completes and prints what it computed; the lock goes with
its process, so a finished or killed run's folder takes the next run (a re-run, resume=true).

The first run is held at a known point without timing: the test holds the write lock of the demonstration store it
is about to collect into, so the run (which claimed its folder before building anything) waits there, saying so on
stderr, until the test lets it go."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from kpflow.data.episode_store import LOCK_NAME
from kpflow.utils.file_lock import FileLock
from kpflow.utils.run import RUN_LOCK, RunFolderInUse, claim_run_folder
from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]
HANG_GUARD_S = 300  # a run that never gets there fails the test instead of hanging it (not a timing assertion)


def start(log: Path, *args: str) -> subprocess.Popen:
    """``python *args`` in the repository, its stdout and stderr into ``log``.out / ``log``.err."""
    out, err = open(f"{log}.out", "w"), open(f"{log}.err", "w")
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, stdout=out, stderr=err, text=True)


def wait_for(proc: subprocess.Popen, log: Path, text: str) -> None:
    """Wait until ``text`` appears in ``log``.err (the process still running)."""
    t0 = time.monotonic()
    while text not in Path(f"{log}.err").read_text():
        assert proc.poll() is None, f"exited before saying {text!r}: " + Path(f"{log}.err").read_text()[-3000:]
        assert time.monotonic() - t0 < HANG_GUARD_S, f"never said {text!r}"
        time.sleep(0.05)


def finish(proc: subprocess.Popen, log: Path) -> tuple[int, str, str]:
    rc = proc.wait(HANG_GUARD_S)
    return rc, Path(f"{log}.out").read_text(), Path(f"{log}.err").read_text()


def run(script: str, *args: str) -> subprocess.CompletedProcess:
    """``python script *args`` (``evaluate.py``, ``train.py``) run in this process (tests.helpers.run_command): the
    runs a test starts beside a live one; the live one is a real process of its own."""
    return run_command({"evaluate.py": "kpflow.cli.evaluate", "train.py": "kpflow.cli.train"}[script], *args)


def gate(store: Path) -> FileLock:
    """Hold the write lock of the (not yet collected) store ``store``: a run collecting into it waits."""
    store.mkdir()
    return FileLock(store / LOCK_NAME)


def assert_refused(done: subprocess.CompletedProcess, folder: Path, holder: int) -> None:
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) <= 3, done.stderr[-3000:]
    assert f"error: {folder} is in use by another run (process {holder})" in lines[0], done.stderr


def evaluate_args(store: Path, folder: Path, n_configs: int) -> list[str]:
    return [
        "evaluate.py", "policy=nearest", "split=in_distribution", f"n_configs={n_configs}", "workers=1", "logger=none",
        "data.n_episodes=2", "data.workers=1", f"data.path={store}", "experiment.trial.max_steps=30", "experiment.videos=0",
        f"hydra.run.dir={folder}",
    ]  # fmt: skip


@pytest.mark.slow
def test_two_evaluations_into_one_folder_the_second_is_refused_and_the_first_prints_its_own_table(tmp_path):
    store, folder = tmp_path / "demos.zarr", tmp_path / "run"
    held = gate(store)
    first = start(tmp_path / "first", *evaluate_args(store, folder, n_configs=2))
    wait_for(first, tmp_path / "first", f"to finish writing {store}")  # past start_run: the folder is claimed

    second = run(*evaluate_args(store, folder, n_configs=1))
    assert_refused(second, folder, first.pid)

    held.release()
    rc, out, err = finish(first, tmp_path / "first")
    assert rc == 0, err[-3000:]
    table = (folder / "results.md").read_text()
    assert "| nearest | in_distribution | 2 |" in table and table in out  # its own table, printed from what it computed
    assert yaml.safe_load((folder / "config.yaml").read_text())["n_configs"] == 2
    assert len(json.loads((folder / "results.json").read_text())["trials"]) == 2
    assert not (folder / ".hydra").exists()  # Hydra's own copy is off: nothing a second run could overwrite
    assert not (folder / RUN_LOCK).exists()  # the first run removed its lock when it ended


def train_args(store: Path, folder: Path, seed: int, *extra: str) -> list[str]:
    return [
        "train.py", "experiment=pusht_kcfm", "data.n_episodes=2", "data.workers=1", f"data.path={store}",
        "data.batch_size=64", "trainer.max_epochs=1", "trainer.enable_progress_bar=false", "logger=none", f"seed={seed}",
        f"hydra.run.dir={folder}", *extra,
    ]  # fmt: skip


@pytest.mark.slow
def test_two_trainings_into_one_folder_the_second_is_refused_and_resume_continues_the_first(tmp_path):
    store, folder = tmp_path / "demos.zarr", tmp_path / "run"
    held = gate(store)
    first = start(tmp_path / "first", *train_args(store, folder, seed=1))
    wait_for(first, tmp_path / "first", f"to finish writing {store}")

    second = run(*train_args(store, folder, seed=2))  # would pass "already holds a run": nothing is written yet
    assert_refused(second, folder, first.pid)

    held.release()
    rc, out, err = finish(first, tmp_path / "first")
    assert rc == 0, err[-3000:]
    assert yaml.safe_load((folder / "config.yaml").read_text())["seed"] == 1  # the first's config and checkpoints
    saved = (folder / "checkpoints" / "last.ckpt").read_bytes()

    resumed = run(*train_args(store, folder, 1, "resume=true", "trainer.max_epochs=2"))  # the lock left with the first
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert (folder / "checkpoints" / "last.ckpt").read_bytes() != saved
    assert yaml.safe_load((folder / "config.yaml").read_text())["trainer"]["max_epochs"] == 2


@pytest.mark.slow
def test_a_killed_run_frees_its_folder_for_the_next(tmp_path):
    store, folder = tmp_path / "demos.zarr", tmp_path / "run"
    held = gate(store)
    first = start(tmp_path / "first", *evaluate_args(store, folder, n_configs=1))
    wait_for(first, tmp_path / "first", f"to finish writing {store}")
    assert_refused(run(*evaluate_args(store, folder, n_configs=1)), folder, first.pid)
    first.send_signal(signal.SIGKILL)
    first.wait()
    held.release()

    again = run(*evaluate_args(store, folder, n_configs=1))  # the same run again, into the dead run's folder
    assert again.returncode == 0, again.stderr[-3000:]
    assert "| nearest | in_distribution | 1 |" in again.stdout


HOLD = """
import os, sys, time
from pathlib import Path
from kpflow.utils.run import RUN_LOCK, claim_run_folder
claim_run_folder(Path(sys.argv[1]))
print("claimed", (Path(sys.argv[1]) / RUN_LOCK).read_text() == str(os.getpid()), flush=True)
time.sleep(600)
"""


def test_claiming_a_folder_another_process_holds_names_it_and_its_pid(tmp_path):
    folder = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "claimed True"
        with pytest.raises(RunFolderInUse, match=rf"{folder} is in use by another run \(process {holder.pid}\)"):
            claim_run_folder(folder)
    finally:
        holder.kill()
        holder.wait()
    FileLock(folder / RUN_LOCK).release()  # the killed holder's lock died with it


HOLD_WITH_WORKERS = """
import multiprocessing as mp, os, sys, time
from pathlib import Path
from kpflow.utils.run import claim_run_folder
claim_run_folder(Path(sys.argv[1]))
pool = mp.get_context("fork").Pool(2)
pool.apply_async(time.sleep, (600,))
pids = [p.pid for p in pool._pool]
print(" ".join(map(str, pids)), flush=True)
time.sleep(600)
"""


def test_a_killed_runs_forked_workers_do_not_keep_its_folder(tmp_path):
    """A worker forked from a run closes its copy of the run's lock, so the folder is free as soon as the run dies, not
    only once its last worker has finished (what a resumed generation ran into)."""
    folder = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_WITH_WORKERS, str(folder)], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    workers = [int(pid) for pid in holder.stdout.readline().split()]
    try:
        with pytest.raises(RunFolderInUse):
            claim_run_folder(folder)
        holder.kill()
        holder.wait()
        assert all(Path(f"/proc/{pid}").exists() for pid in workers)  # the workers live on, orphaned
        claim_run_folder(folder)  # and the folder is free
    finally:
        for pid in workers:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_failed_run_leaves_neither_its_lock_nor_an_empty_folder(tmp_path):
    """A training that fails after claiming its folder (here: no data at data.path) says why in one line and leaves
    nothing behind; one that wrote a result keeps its folder, without the lock."""
    folder = tmp_path / "run"
    done = run(
        "train.py",
        "experiment=kcfm",
        f"data.path={tmp_path / 'missing.zarr'}",
        "logger=none",
        f"hydra.run.dir={folder}",
    )
    assert done.returncode == 1 and "missing.zarr" in done.stderr.splitlines()[0], done.stderr[-3000:]
    assert not folder.exists()
    kept = tmp_path / "kept"
    code = (f"from pathlib import Path; from kpflow.utils.run import claim_run_folder; claim_run_folder(Path({str(kept)!r})); "
            f"(Path({str(kept)!r}) / 'results.json').write_text('{{}}'); raise SystemExit(3)")  # fmt: skip
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=HANG_GUARD_S).returncode == 3
    assert sorted(p.name for p in kept.iterdir()) == ["results.json"]
