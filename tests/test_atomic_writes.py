"""Writes killed half-way leave the old file or folder intact, and the next write removes their temporaries."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from kpflow.data.episode_store import EpisodeStore
from kpflow.utils.io import atomic_dir, remove_stale_temporaries, write_text

ROOT = Path(__file__).resolve().parents[1]


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_next_write_removes_temporaries_of_dead_processes_only(tmp_path):
    target = tmp_path / "results.md"
    stale_file = tmp_path / f".results.md.{dead_pid()}.abc.tmp.md"
    stale_dir = tmp_path / f".results.md.{dead_pid()}.def.tmp.md"
    live = tmp_path / f".results.md.{os.getppid()}.ghi.tmp.md"  # a live process's write in progress
    other = tmp_path / f".other.md.{dead_pid()}.jkl.tmp.md"  # another target's: not ours to judge now
    stale_file.write_text("half")
    stale_dir.mkdir()
    (stale_dir / "x").write_text("half")
    live.write_text("in progress")
    other.write_text("half")
    write_text(target, "done\n")
    assert target.read_text() == "done\n"
    assert not stale_file.exists() and not stale_dir.exists()
    assert live.exists() and other.exists()
    assert remove_stale_temporaries(tmp_path / "other.md") == [other]


def test_atomic_dir_replaces_a_folder_whole_or_not_at_all(tmp_path):
    dest = tmp_path / "store"
    with atomic_dir(dest) as tmp:
        (tmp / "a").write_text("old")
    with pytest.raises(FileExistsError, match="exists already"):
        with atomic_dir(dest):
            pass
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_dir(dest, overwrite=True) as tmp:
            (tmp / "b").write_text("new")
            raise RuntimeError("boom")
    assert sorted(p.name for p in dest.iterdir()) == ["a"]  # the old folder, untouched
    with atomic_dir(dest, overwrite=True) as tmp:
        (tmp / "b").write_text("new")
    assert sorted(p.name for p in dest.iterdir()) == ["b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store"]  # no temporaries left


def kill_when(proc: subprocess.Popen, appears, timeout: float = 60.0, after: float = 0.3) -> None:
    """SIGKILL ``proc`` ``after`` seconds once ``appears()`` is true (it must still be running then)."""
    t0 = time.monotonic()
    while not appears():
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else "exited early"
        assert time.monotonic() - t0 < timeout
        time.sleep(0.02)
    time.sleep(after)
    assert proc.poll() is None, "finished before it could be killed: make the job longer"
    proc.send_signal(signal.SIGKILL)
    proc.wait()


VIDEO = """
import sys, numpy as np
from kpflow.utils.video import write_video
frames = [np.full((256, 256, 3), i % 255, np.uint8) for i in range(3000)]
write_video(frames, sys.argv[1], fps=30)
"""


def test_killed_video_write_leaves_no_file_and_its_temporary_is_removed_next_time(tmp_path):
    from kpflow.utils.video import write_video

    path = tmp_path / "episode.mp4"
    proc = subprocess.Popen([sys.executable, "-c", VIDEO, str(path)], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    kill_when(proc, lambda: any(tmp_path.glob(".episode.mp4.*.tmp.mp4")))
    assert not path.exists() and len(list(tmp_path.glob(".episode.mp4.*.tmp.mp4"))) == 1
    write_video([np.zeros((16, 16, 3), np.uint8)] * 3, path)
    assert path.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode.mp4"]


def write_replay_buffer(path: Path, n_episodes: int, length: int = 20) -> None:
    """A buffer in the standard layout (random in-arena states; the import does not check physics)."""
    rng = np.random.default_rng(0)
    n = n_episodes * length
    root = zarr.open_group(str(path), mode="w")
    state = np.c_[rng.uniform(100, 400, (n, 4)), rng.uniform(-np.pi, np.pi, n)].astype(np.float32)
    root.create_dataset("data/state", data=state, chunks=(1000, 5))
    root.create_dataset("data/action", data=rng.uniform(100, 400, (n, 2)).astype(np.float32), chunks=(1000, 2))
    root.create_dataset("meta/episode_ends", data=np.arange(1, n_episodes + 1, dtype=np.int64) * length)


def test_killed_overwriting_import_keeps_the_old_store_and_the_next_import_cleans_up(tmp_path):
    from kpflow.tasks.pusht.replay_import import import_pusht_replay

    source, dest = tmp_path / "buffer.zarr", tmp_path / "demos.zarr"
    write_replay_buffer(source, 1500)
    old = import_pusht_replay(source, dest, max_episodes=3, progress=False)
    old_ends = old.episode_ends
    cmd = [
        sys.executable,
        "-m",
        "kpflow.tasks.pusht.replay_import",
        str(source),
        str(dest),
        "--overwrite",
        "--no-progress",
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    kill_when(
        proc,
        lambda: any((t / "meta" / "episode_ends").exists() for t in tmp_path.glob(".demos.zarr.*.tmp.zarr")),
        after=0.3,
    )
    leftovers = list(tmp_path.glob(".demos.zarr.*.tmp.zarr"))
    assert len(leftovers) == 1
    np.testing.assert_array_equal(EpisodeStore(dest).episode_ends, old_ends)  # the old store, intact
    new = import_pusht_replay(source, dest, max_episodes=5, progress=False, overwrite=True)
    assert len(new) == 5 and not any(tmp_path.glob(".demos.zarr.*"))


# A full disk, planted without root: the file-size limit (RLIMIT_FSIZE, inherited by ffmpeg, a child process) with
# SIGXFSZ ignored makes every write past FULL_AT bytes fail with EFBIG, as writes to a full disk fail with ENOSPC.
FULL_AT = 16_384
FULL_DISK = f"""
import resource, signal, sys
import numpy as np

def disk_full():
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, ({FULL_AT}, {FULL_AT}))

what, path = sys.argv[1:]
frames = [np.random.default_rng(i).integers(0, 255, (64, 64, 3), dtype=np.uint8) for i in range(30)]
if what == "old_video":  # what write_video did before it checked: imageio straight into the temporary, renamed after
    import imageio.v2 as imageio
    disk_full()
    imageio.mimsave(path, frames, format="FFMPEG", fps=10, codec="libx264", macro_block_size=1)
elif what == "video":
    from kpflow.utils.video import write_video
    disk_full()
    write_video(frames, path)
elif what in ("text", "json"):
    from kpflow.utils.io import write_json, write_text
    disk_full()
    write_text(path, "| row |\\n" * {FULL_AT}) if what == "text" else write_json(path, {{"trials": list(range({FULL_AT}))}})
elif what == "figure":
    import matplotlib.pyplot as plt
    from kpflow.utils.io import save_figure
    fig = plt.figure(figsize=(4, 4))
    plt.imshow(np.random.default_rng(0).random((200, 200)))
    disk_full()
    save_figure(fig, path, dpi=200)
elif what == "checkpoint":  # how train.py's checkpoints are saved (Lightning's save through SafeCheckpointIO)
    import torch
    from kpflow.utils.checkpoint import SafeCheckpointIO
    disk_full()
    SafeCheckpointIO().save_checkpoint({{"state_dict": {{"w": torch.randn(20_000)}}}}, path)
"""


def write_on_a_full_disk(what: str, path: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", FULL_DISK, what, str(path)], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


def test_a_video_cut_short_by_a_full_disk_is_refused_and_nothing_reaches_its_name(tmp_path):
    import imageio_ffmpeg

    # the planted case is live: ffmpeg's failed writes go unnoticed, and the file it leaves does not play
    old = tmp_path / "old.mp4"
    done = write_on_a_full_disk("old_video", old)
    assert done.returncode == 0, done.stderr[-2000:]
    assert old.stat().st_size == FULL_AT
    with pytest.raises(RuntimeError, match="moov atom not found"):
        imageio_ffmpeg.count_frames_and_secs(str(old))
    # write_video reads the temporary back before renaming it: it raises, naming the file, and leaves nothing
    for name in ("episode.mp4", "episode.gif"):
        path = tmp_path / "run" / name
        done = write_on_a_full_disk("video", path)
        assert done.returncode == 1, done.stderr[-2000:]
        assert f"\nOSError: {path} was not written: " in done.stderr, done.stderr[-2000:]
        assert sorted(p.name for p in path.parent.iterdir()) == []  # neither the video nor its temporary


@pytest.mark.parametrize(
    "what, name",
    [("text", "results.md"), ("json", "results.json"), ("figure", "success.png"), ("checkpoint", "last.ckpt")],
)
def test_results_figures_and_checkpoints_cut_short_by_a_full_disk_leave_nothing(tmp_path, what, name):
    path = tmp_path / name
    done = write_on_a_full_disk(what, path)
    assert done.returncode == 1, done.stderr[-2000:]
    last = done.stderr.strip().splitlines()[-1]  # issue 63.8: one line naming the file and the fix, not a bare [Errno]
    assert (
        f"{path} was not written: no room left (File too large); nothing reached its name" in last
        and "Free space" in last
    ), last
    assert list(tmp_path.iterdir()) == []


GATED_IMPORT = """
import sys, time
from pathlib import Path
import kpflow.tasks.pusht.replay_import as replay_import

gate, fields = Path(sys.argv[1]), replay_import.episode_fields
def gated(*args):  # the first episode waits while the gate file is there: the import is under way, held
    while gate.exists():
        time.sleep(0.02)
    return fields(*args)
replay_import.episode_fields = gated
sys.exit(replay_import.main(sys.argv[2:]))
"""


def test_a_second_import_into_one_folder_at_once_is_refused_by_name(tmp_path):
    """Issue 63.3: two imports into one data folder without --overwrite: the second is refused, naming the folder
    and the first's pid, while the first runs (a real import in another process, held at its first episode); after
    it, the folder holds episodes and is refused as such."""
    from kpflow.tasks.pusht.replay_import import import_pusht_replay
    from kpflow.utils.file_lock import LockHeld

    source, dest, gate = tmp_path / "replay.zarr", tmp_path / "demos.zarr", tmp_path / "gate"
    write_replay_buffer(source, 30)
    gate.touch()
    cmd = [sys.executable, "-c", GATED_IMPORT, str(gate), str(source), str(dest), "--no-progress"]
    first = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not any(tmp_path.glob(".demos.zarr.*.tmp.zarr")):
        assert first.poll() is None and time.monotonic() - t0 < 120, first.stderr.read()
        time.sleep(0.02)
    with pytest.raises(
        LockHeld, match=rf"demos.zarr is being written by process {first.pid} \(.demos.zarr.lock is held\)"
    ):
        import_pusht_replay(source, dest, progress=False)
    gate.unlink()
    out, err = first.communicate(timeout=120)
    assert first.returncode == 0 and out.startswith("imported 30 episodes"), err
    with pytest.raises(FileExistsError, match="demos.zarr already holds 30 episodes; pass overwrite=True"):
        import_pusht_replay(source, dest, progress=False)
    assert len(EpisodeStore(dest)) == 30 and sorted(p.name for p in tmp_path.iterdir()) == ["demos.zarr", "replay.zarr"]


def test_a_folder_made_meanwhile_is_never_replaced_without_overwrite(tmp_path):
    dest = tmp_path / "store"
    with pytest.raises(FileExistsError, match="store was written by another process while this one wrote it"):
        with atomic_dir(dest) as tmp:
            (tmp / "mine").write_text("new")
            dest.mkdir()  # another writer's folder, published while this one was writing
            (dest / "theirs").write_text("kept")
    assert sorted(p.name for p in dest.iterdir()) == ["theirs"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store"]
