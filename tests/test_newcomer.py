"""The README's "Train on your own data" commands, run exactly as written (but the install, which is the
environment this test runs in) on a small synthetic LeRobot dataset named ``my_dataset`` (a point walking to a
square target: 5 keypoints in 2-D, 2-D actions): train a K-CFM, check it on held-out episodes, serve it and ask it
for an action chunk."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.lerobot_dataset import export_lerobot
from kpflow.examples.train_on_store import walking_store
from tests.helpers import child_env

ROOT = Path(__file__).resolve().parents[1]


def walking_dataset(root: Path) -> None:
    """kpflow/examples/train_on_store.py's walking episodes, as a LeRobot dataset at ``root``."""
    with EpisodeStore(walking_store(root.with_suffix(".zarr"), episodes=12)) as store:
        export_lerobot(store, root, fps=10, task="walk to the target")


def newcomer_commands() -> list[str]:
    """The command lines of the README's newcomer block, comments dropped."""
    block = re.search(
        r"<!-- newcomer:start -->\n```bash\n(.*?)```\n<!-- newcomer:end -->", (ROOT / "README.md").read_text(), re.S
    )
    assert block, "README.md lost its newcomer block"
    return [line.split("  #")[0].strip() for line in block[1].splitlines() if line.strip()]


def test_the_readme_promises_at_most_five_commands():
    commands = newcomer_commands()
    assert len(commands) <= 5 and commands[0].startswith("make venv")
    assert any(c.startswith("kpflow-train") for c in commands) and any(c.startswith("kpflow-serve") for c in commands)


@pytest.mark.slow
def test_newcomer_trains_evaluates_and_serves_a_lerobot_dataset(tmp_path):
    walking_dataset(tmp_path / "my_dataset")
    install, *commands = newcomer_commands()  # the install is this test's environment
    script = "\n".join(["set -euo pipefail", "trap 'kill $(jobs -p) 2>/dev/null || true' EXIT", *commands])
    env = child_env(PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", OMP_NUM_THREADS="1", WANDB_MODE="offline",
                    MPLBACKEND="Agg")  # fmt: skip
    done = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    run = tmp_path / "outputs" / "kcfm" / "mine"
    assert (run / "checkpoints" / "last.ckpt").is_file() and "n_keypoints: 5" in (
        run / "config.yaml"
    ).read_text()  # read from the data
    offline = next((tmp_path / "outputs" / "offline").iterdir())
    assert (offline / "offline.png").is_file() and "| K-CFM |" in (offline / "results.md").read_text()
    assert "server: kcfm, observes {'keypoints_history': [2, 5, 2]}, returns [8, 2] actions" in done.stdout
    assert re.search(r"action chunk \[8, 2\] in [\d.]+ ms on the server", done.stdout)
