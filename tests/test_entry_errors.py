"""Entry points check what they can while the run is being built, before any trial, and say what is wrong in one
short message: a policy checkpoint of another task (its keypoints and actions against the task's), and a learned
map that is missing, not a learned map's checkpoint, or trained on other keypoints than it would be fitted on."""

import re
from pathlib import Path

import numpy as np
import pytest

from kpflow.core.policy import PolicyLayout
from kpflow.policies.factory import check_checkpoint_fits
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import run_command, train_learned_map

ROOT = Path(__file__).resolve().parents[1]
PUSHT_CKPT = "release/pusht_table1_kcfm_35_corrected.ckpt"
PUSHT_STORE = "release/pusht_table1_35_corrected.zarr"  # a finished store: no collection before the check
# Push-T evaluations of the transport policy on the released store (n_configs=1: one trial, had it got that far)
TRANSPORT = [
    "policy=transport",
    "split=in_distribution",
    "n_configs=1",
    "workers=1",
    "logger=none",
    "data.n_episodes=null",
    f"data.path={PUSHT_STORE}",
]


def evaluate(tmp_path, *args: str) -> list[str]:
    """Run evaluate.py, which must fail; its stderr lines but robosuite's notices on import (five on every import,
    whatever happens after)."""
    done = run_command(
        "kpflow.cli.evaluate", *args, f"hydra.run.dir={tmp_path / 'run'}"
    )  # the error path, in this process
    assert done.returncode == 1, done.stderr[-3000:]
    lines = [line for line in done.stderr.strip().splitlines() if not line.startswith("[robosuite WARNING]")]
    assert len(lines) <= 3 and lines[0].startswith("error: "), done.stderr[-3000:]
    assert (
        not list((tmp_path / "run").glob("*.mp4")) and not (tmp_path / "run" / "results.json").exists()
    )  # no trial ran
    return lines


def test_a_pusht_checkpoint_on_a_robosuite_task_is_refused_naming_both_layouts(tmp_path):
    (error, *_) = evaluate(
        tmp_path, "experiment=suite_policy", "task=lift", f"policy.checkpoint={PUSHT_CKPT}", "workers=1", "logger=none"
    )
    assert (
        f"{PUSHT_CKPT} is a policy for 25 keypoints in 2-D and 2-D actions, but lift shows 11 keypoints in 3-D" in error
    )
    assert "takes 10-D actions: pass a checkpoint trained on lift" in error


def test_the_task_layouts_policies_are_checked_against():
    from kpflow.tasks.suite.task import SuiteTask

    # the robosuite tasks' policy keypoints, as suite_kcfm.yaml trains on them
    assert {t: SuiteTask(t).policy_layout for t in ("lift", "stack", "can", "square")} == {
        "lift": PolicyLayout(11, 3, 10), "stack": PolicyLayout(19, 3, 10), "can": PolicyLayout(13, 3, 10), "square": PolicyLayout(16, 3, 10),
    }  # fmt: skip
    check_checkpoint_fits("suite.ckpt", {"n_keypoints": 16, "keypoint_dim": 3, "action_dim": 10}, SuiteTask("square"))
    with pytest.raises(
        ValueError,
        match="suite.ckpt is a policy for 16 keypoints in 3-D and 10-D actions, but pusht shows 25 keypoints in 2-D",
    ):
        check_checkpoint_fits("suite.ckpt", {"n_keypoints": 16, "keypoint_dim": 3, "action_dim": 10}, PushTTask())


@pytest.mark.parametrize("checkpoint, message", [
    ("missing.ckpt", "no learned-map checkpoint at missing.ckpt"),
    (PUSHT_CKPT, f"{ROOT / PUSHT_CKPT} is not a readable MapModule checkpoint .*a learned map needs a MapModule checkpoint"),
], ids=["missing", "not_a_learned_map"])  # fmt: skip
def test_a_wrong_learned_map_is_refused_before_any_trial(tmp_path, checkpoint, message):
    (error, *_) = evaluate(tmp_path, *TRANSPORT, "map=learned", f"map.checkpoint={checkpoint}")
    assert error.startswith("error: experiment.trial.policy: ")
    assert re.search(message, error), error


def four_point_pairs(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    source = rng.uniform(0, 1, (n, 4, 2))
    return source, source + rng.normal(0, 0.05, (n, 4, 2))


@pytest.mark.parametrize("where, args, use", [
    ("pusht", TRANSPORT, "policy transportation (fit_on=['objects', 'robot']) fits it on 13 keypoints in 2-D"),
    ("frames", ["experiment=frames", "logger=none", "experiment.n_configs=2"], "the frames task fits it on 10 keypoints in 2-D"),
])  # fmt: skip
def test_a_learned_map_of_other_keypoints_is_refused_naming_both_layouts(tmp_path, where, args, use):
    checkpoint = train_learned_map(tmp_path, four_point_pairs, n_keypoints=4, steps=1)
    (error, *_) = evaluate(tmp_path, *args, "map=learned", f"map.checkpoint={checkpoint}")
    assert f"the learned map {checkpoint} was trained on 4 keypoints in 2-D, but {use}" in error
    assert not list((tmp_path / "run").glob("*.png"))


def test_a_required_key_left_out_is_named_with_how_to_give_it(tmp_path):
    """``kpflow-train experiment=kcfm`` without ``data.path`` (a ``???`` in the config): one line naming the key."""
    done = run_command("kpflow.cli.train", "experiment=kcfm", "logger=none", f"hydra.run.dir={tmp_path / 'run'}")
    lines = done.stderr.strip().splitlines()
    assert (
        done.returncode == 1
        and lines[0] == "error: config key data.path is required and not given: add data.path=<value> to the command"
    ), done.stderr


def test_a_policy_checkpoint_is_spelled_checkpoint_and_named_when_left_out(tmp_path):
    """``checkpoint=`` is the one spelling of a policy's checkpoint across commands (evaluate, collect, correct,
    serve; ``policy.checkpoint=`` still works); left out, one line names it."""
    from tests.helpers import compose_config

    for entry in ("evaluate", "collect", "correct"):
        given = compose_config(entry, ["policy=kcfm", "checkpoint=release:pusht_standard_fast"], tmp_path)
        assert given.policy.checkpoint == "release:pusht_standard_fast", entry
    done = run_command("kpflow.cli.evaluate", "policy=kcfm", "logger=none", f"hydra.run.dir={tmp_path / 'run'}")
    lines = done.stderr.strip().splitlines()
    assert (
        done.returncode == 1
        and lines[0] == "error: config key checkpoint is required and not given: add checkpoint=<value> to the command"
    ), done.stderr
    assert not (tmp_path / "run").exists()
