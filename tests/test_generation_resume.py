"""Generation's numbers depend on the settings and seed only, and a stopped run resumes (kpflow/generation/generate.py,
kpflow/generation/journal.py): an attempt is the same to the bit whichever attempts its worker ran before, a
cell's journal and store recover from a kill at any point and refuse anything else, and a real
``kpflow-generate`` killed with SIGKILL and resumed ends as an uninterrupted run with other workers does."""

import json
import re
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.generation.journal import CellJournal, check_output
from tests.helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
#: what an uninterrupted and a resumed run may differ in: the timing of the attempts each process ran
THROUGHPUT = ("attempts_run", "attempts_per_minute", "real_time", "wall_s")


def assert_same_episode(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert np.array_equal(a[name], b[name]), f"{name} differs by {np.max(np.abs(a[name] - b[name]))}"


def test_an_attempt_is_the_same_in_a_fresh_generator_and_after_other_attempts():
    """Before, robosuite drew Lift's cube side from an unseeded generator whenever a worker built its simulator: the
    same attempt differed by 0.15 in the state and 2 pi in an action's rotation vector between two generators."""
    from kpflow.generation.generate import Generator
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.tasks.suite.task import SuiteTask

    task, families = SuiteTask("lift"), {"mimicgen": SegmentTransport(None, in_hand=False)}
    used = Generator(task, families)
    used.setup()
    for job in [("d0", 0, "mimicgen"), ("wide", 1, "mimicgen")]:
        used.attempt(*job)
    after = used.attempt("wide", 2, "mimicgen")
    fresh = Generator(task, families)
    fresh.setup()
    first = fresh.attempt("wide", 2, "mimicgen")
    assert first[0] == after[0] and first[0]["success"]
    assert_same_episode(first[1], after[1])


def _slow_square(job: int) -> int:
    time.sleep(0.02 * (job % 3))
    return job * job


def test_attempts_stream_in_order_as_they_finish_and_stopping_early_leaves_no_worker():
    import multiprocessing

    from kpflow.eval.parallel import iter_jobs

    results = iter_jobs(_slow_square, list(range(40)), 2, progress=False)
    assert [next(results) for _ in range(5)] == [0, 1, 4, 9, 16]
    results.close()  # as when committing an attempt fails: the workers are stopped, not left running the rest
    assert multiprocessing.active_children() == []


# ------------------------------------------------------------------------------------------ the journal


def record(i: int, success: bool) -> dict:
    return {"variant": "d0", "index": i, "family": "f", "source": 0, "success": success,
            "failure": None if success else "not grasped", "steps": 3, "scene": {"objects": {}}}  # fmt: skip


def episode(i: int) -> dict:
    rng = np.random.default_rng(i)
    return {"action": rng.normal(size=(3 + i, 7)), "state": rng.normal(size=(3 + i, 5))}


def committed_cell(folder: Path, outcomes: list[bool]) -> CellJournal:
    journal = CellJournal(folder, "d0", "f")
    assert journal.committed() == []
    with journal:
        for i, ok in enumerate(outcomes):
            journal.commit(record(i, ok), episode(i) if ok else None)
    return journal


def test_a_cell_drops_a_torn_line_and_an_uncommitted_success_and_continues_after_them(tmp_path):
    journal = committed_cell(tmp_path, [True, False, True])
    with open(journal.journal, "ab") as f:  # killed after attempt 3's line, before its episode was stored
        f.write((json.dumps(record(3, True)) + "\n").encode())
    assert CellJournal(tmp_path, "d0", "f").committed() == [record(i, ok) for i, ok in enumerate([True, False, True])]
    assert len(journal.journal.read_text().splitlines()) == 3
    with open(journal.journal, "ab") as f:  # killed in the middle of a line
        f.write(json.dumps(record(3, False)).encode()[:25])
    again = CellJournal(tmp_path, "d0", "f")
    assert len(again.committed()) == 3 and journal.journal.read_bytes().endswith(b"}\n")
    with again:
        again.commit(record(3, True), episode(3))
        with pytest.raises(ValueError, match="expected attempt 4"):
            again.commit(record(5, False), None)
    assert [r["index"] for r in CellJournal(tmp_path, "d0", "f").committed()] == [0, 1, 2, 3]
    with EpisodeStore(journal.store_path) as store:
        assert [store.episode_attrs(i)["index"] for i in range(store.n_episodes)] == [0, 2, 3]
        for j, i in enumerate([0, 2, 3]):
            assert_same_episode(store.episode(j), episode(i))


def test_a_damaged_cell_is_refused_naming_the_file_and_left_as_it_was(tmp_path):
    journal = committed_cell(tmp_path / "a", [True, False, True])
    lines = journal.journal.read_text().splitlines()
    for damaged, match in [
        ([lines[0], "not json", lines[2]], "attempts.jsonl, line 2 is not a JSON record"),
        ([lines[0], lines[2]], "line 2 records attempt"),  # an attempt missing
        ([lines[0], json.dumps({"index": 1}), lines[2]], "line 2 is not an attempt record"),
        ([lines[0], lines[1]], "episodes.zarr holds the episodes of attempts \\[0, 2\\]"),  # a committed success lost
    ]:
        text = "".join(line + "\n" for line in damaged)
        journal.journal.write_text(text)
        with pytest.raises(ValueError, match=match):
            CellJournal(tmp_path / "a", "d0", "f").committed()
        assert journal.journal.read_text() == text
    journal.journal.write_text("".join(line + "\n" for line in lines))
    with pytest.raises(ValueError, match="records attempt"):  # another cell's journal
        CellJournal(tmp_path / "a", "wide", "f").committed()
    other = committed_cell(tmp_path / "b", [True])
    with EpisodeStore(other.store_path, mode="a") as store:  # an episode the journal never recorded
        store.add_episode(episode(5), attrs={"variant": "d0", "index": 5, "family": "f", "source": 0})
    with pytest.raises(ValueError, match=r"holds the episodes of attempts \[0, 5\] but .* records the successes \[0\]"):
        CellJournal(tmp_path / "b", "d0", "f").committed()


def test_a_run_folder_is_resumed_only_when_asked_and_only_with_its_own_settings(tmp_path):
    settings = {"task": "lift", "variants": ["d0"], "n": 4, "seed": 0}
    check_output(tmp_path / "new", settings, resume=False)  # nothing there
    with pytest.raises(FileNotFoundError, match="resume=true but .*generation.json does not exist"):
        check_output(tmp_path / "new", settings, resume=True)
    (tmp_path / "generation.json").write_text(json.dumps(settings))
    with pytest.raises(FileExistsError, match="already holds a generation run .*pass resume=true"):
        check_output(tmp_path, settings, resume=False)
    check_output(tmp_path, settings, resume=True)
    with pytest.raises(ValueError, match=r"these differ \(n: 4 there, 5 now; seed: 0 there, 1 now\)"):
        check_output(tmp_path, {**settings, "n": 5, "seed": 1}, resume=True)
    committed_cell(tmp_path / "old" / "d0" / "f", [True])  # a cell without the run's generation.json
    with pytest.raises(FileExistsError, match="attempts.jsonl exists"):
        check_output(tmp_path / "old", settings, resume=False)


# ------------------------------------------------------------------------------------------ the command, killed


def journal_lines(run: Path) -> int:
    return sum(len(p.read_bytes().split(b"\n")) - 1 for p in run.glob("*/*/attempts.jsonl"))


@pytest.mark.slow
def test_a_killed_generate_command_resumes_to_the_uninterrupted_runs_stores_and_results(tmp_path):
    from kpflow.generation.generate import generate
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap
    from kpflow.tasks.suite.task import SuiteTask

    n, variants, names = 4, ["wide"], ["mimicgen", "rigid"]
    run = tmp_path / "run"
    command = [sys.executable, "-m", "kpflow.cli.generate", "task=lift", f"n={n}", f"variants=[{','.join(variants)}]",
               f"families=[{','.join(names)}]", "workers=1", "videos=0", "export=false", f"hydra.run.dir={run}"]  # fmt: skip
    env = child_env(OMP_NUM_THREADS="1")
    killed = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while journal_lines(run) < 2 and killed.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    killed.send_signal(signal.SIGKILL)
    stderr = killed.communicate()[1].decode()
    assert killed.returncode == -signal.SIGKILL, stderr[-2000:]
    committed = journal_lines(run)
    assert 2 <= committed < n * len(names) and not (run / "results.json").exists()

    again = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 1 and "pass resume=true" in again.stderr  # not without being asked
    resumed = subprocess.run(command + ["resume=true"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]

    reference = tmp_path / "reference"  # uninterrupted, two workers sharing the attempts out as they come
    families = {
        "mimicgen": SegmentTransport(None, in_hand=False),
        "rigid": SegmentTransport(partial(AffineMap, kind="rigid")),
    }
    generate(reference, SuiteTask("lift"), families, variants, n=n, workers=2, videos=0, export=False, progress=False)

    assert json.loads((run / "generation.json").read_text()) == json.loads((reference / "generation.json").read_text())
    ours, theirs = (json.loads((d / "results.json").read_text()) for d in (run, reference))
    assert len(ours["attempts"]) == n * len(names) and ours["attempts"] == theirs["attempts"]
    assert [r["attempts_run"] for r in ours["summary"]] != [n] * len(names)  # the resumed run timed only its own
    for rows in (ours["summary"], theirs["summary"]):
        for row in rows:
            for key in THROUGHPUT:
                row.pop(key)
    assert ours == theirs and sum(r["successes"] for r in ours["summary"]) >= n
    for v in variants:
        for f in names:
            assert (run / v / f / "attempts.jsonl").read_text() == (reference / v / f / "attempts.jsonl").read_text()
            with (
                EpisodeStore(run / v / f / "episodes.zarr") as a,
                EpisodeStore(reference / v / f / "episodes.zarr") as b,
            ):
                assert a.n_episodes == b.n_episodes
                for i in range(a.n_episodes):
                    assert a.episode_attrs(i) == b.episode_attrs(i)
                    assert_same_episode(a.episode(i), b.episode(i))
    table = [line.rsplit("|", 3)[0] for line in (run / "results.md").read_text().splitlines()[4:]]
    assert table == [line.rsplit("|", 3)[0] for line in (reference / "results.md").read_text().splitlines()[4:]]
    # the last line the kill left may have been a success whose episode was not stored yet: then it was run again
    resumed_from = int(
        re.search(rf"Resumed: (\d+) of the {n * len(names)} attempts", (run / "results.md").read_text())[1]
    )
    assert resumed_from in (committed - 1, committed)
