"""The scripted Push-T expert solves the task like a hand on a mouse; routing, rollouts and collection."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
import yaml

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht import PushTEnv, split_config
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.demonstrator import CONTACTS, NORMALS, PushTExpert
from kpflow.tasks.pusht.geometry import AGENT_RADIUS, N_KEYPOINTS, OUTLINE, to_world
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.routing import padded_obstacle, path_length, retime, shortest_path, smooth
from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    "split,index,limit",
    [("in_distribution", 0, 600), ("in_distribution", 1, 600), ("robot_ood", 0, 1200), ("object_ood", 0, 1200)],
)
def test_expert_reaches_95_percent_coverage(split, index, limit):
    config = split_config(split, index)
    result = run_episode(PushTEnv(split=split), PushTExpert(config.workspace), config, limit, seed=index, record=True)
    assert result.success and result.coverage >= 0.95
    assert result.first_step[0.85] is not None and result.first_step[0.85] <= result.steps
    ep = result.episode
    assert ep["keypoints"].shape == (result.steps, N_KEYPOINTS, 2) and ep["action"].shape == (result.steps, 2)
    # Hand-like motion: the target never jumps more than 15 px per step, and the first one is near the agent.
    steps = np.linalg.norm(np.diff(ep["action"], axis=0), axis=1)
    assert steps.max() <= 15.0 + 1e-3
    assert np.linalg.norm(ep["action"][0] - ep["agent_pos"][0]) <= 15.0 + 1e-3
    # Not stop-and-go: the target keeps moving on most steps.
    assert (steps > 0.5).mean() > 0.7


def test_expert_with_the_fixed_standard_goal():
    config = split_config("in_distribution", 2, goal="fixed")
    result = run_episode(PushTEnv(goal="fixed"), PushTExpert(), config, 600, seed=2)
    assert result.success


def test_expert_is_reproducible_and_seeds_vary_the_motion():
    config = split_config("in_distribution", 3)
    env = PushTEnv()
    a = run_episode(env, PushTExpert(), config, 80, seed=5, record=True).episode["action"]
    b = run_episode(env, PushTExpert(), config, 80, seed=5, record=True).episode["action"]
    c = run_episode(env, PushTExpert(), config, 80, seed=6, record=True).episode["action"]
    np.testing.assert_array_equal(a, b)
    n = min(len(a), len(c))
    assert not np.allclose(a[:n], c[:n])


def test_expert_rejects_bad_speeds():
    with pytest.raises(ValueError, match="push_speed"):
        PushTExpert(push_speed=20.0, max_speed=15.0)


def test_contacts_lie_on_the_outline_with_outward_normals():
    outline = shapely.Polygon(OUTLINE)
    assert len(CONTACTS) >= 30
    for p, n in zip(CONTACTS, NORMALS):
        assert outline.exterior.distance(shapely.Point(p)) < 1e-9
        assert np.isclose(np.linalg.norm(n), 1.0)
        assert not outline.contains(shapely.Point(p + 0.5 * n)) and outline.contains(shapely.Point(p - 0.5 * n))


def test_shortest_path_goes_around_the_padded_block():
    outline = to_world((256.0, 256.0, 0.3), OUTLINE)
    obstacle = padded_obstacle(outline, AGENT_RADIUS + 2)
    start, goal = np.array([256.0, 150.0]), np.array([256.0, 420.0])  # opposite sides of the T
    path = shortest_path(start, goal, obstacle, (0.0, 512.0))
    assert path is not None and np.allclose(path[0], start) and np.allclose(path[-1], goal)
    assert not shapely.intersects(shapely.LineString(path), obstacle)
    assert path_length(path) > np.linalg.norm(goal - start)
    # A straight line is returned as is when it is free, and a start inside the obstacle has no path.
    assert len(shortest_path(start, np.array([400.0, 100.0]), obstacle, (0.0, 512.0))) == 2
    assert shortest_path(np.array([256.0, 300.0]), goal, obstacle, (0.0, 512.0)) is None
    smoothed = smooth(path, obstacle)
    assert len(smoothed) >= len(path) and not shapely.intersects(shapely.LineString(smoothed), obstacle)


def test_retime_bounds_speed_and_acceleration_and_ends_on_the_path_end():
    path = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 80.0]])
    targets = retime(path, v_max=12.0, accel=2.0, v_start=0.0, v_end=3.0)
    speeds = np.linalg.norm(np.diff(np.concatenate([path[:1], targets]), axis=0), axis=1)
    assert np.allclose(targets[-1], path[-1]) and speeds.max() <= 12.0 + 1e-9
    line = np.array([[0.0, 0.0], [180.0, 0.0]])  # on a straight line step lengths are the speeds along the path
    speeds = np.diff(np.concatenate([[0.0], retime(line, v_max=12.0, accel=2.0, v_end=3.0)[:, 0]]))
    assert np.abs(np.diff(speeds[:-1])).max() <= 2.0 + 1e-6
    assert speeds[-2] <= 3.0 + 2.0 + 1e-6  # slowed down to the entry speed at the end


class ChunkPolicy:
    """Holds the agent still with chunks of 4 identical targets (checks open-loop chunk execution)."""

    def __init__(self):
        self.calls = 0

    def reset(self, seed=None):
        self.calls = 0

    def act(self, obs):
        self.calls += 1
        return np.repeat(obs["agent_pos"][None], 4, axis=0)


def test_run_episode_executes_chunks_open_loop_and_records_obs_before_actions():
    config = split_config("in_distribution", 0)
    policy = ChunkPolicy()
    result = run_episode(PushTEnv(max_steps=None), policy, config, 10, record=True)
    assert result.steps == 10 and policy.calls == 3 and not result.success
    np.testing.assert_allclose(result.episode["agent_pos"][0], config.agent_pos, atol=1e-3)
    assert result.frames is None
    with pytest.raises(ValueError, match="max_steps"):
        run_episode(PushTEnv(), policy, config, 0)


def test_collect_commits_successful_episodes_deterministically(tmp_path):
    one = collect_pusht(tmp_path / "a.zarr", 2, workers=1, progress=False, videos=1, video_dir=tmp_path)
    two = collect_pusht(tmp_path / "b.zarr", 2, workers=2, progress=False)
    assert one["episodes"] == two["episodes"] == 2 and one["videos"] and Path(one["videos"][0]).stat().st_size > 0
    a, b = EpisodeStore(tmp_path / "a.zarr"), EpisodeStore(tmp_path / "b.zarr")
    assert a.attrs["task"] == "pusht" and a.episode_attrs(0)["success"]
    for i in range(2):
        for key in ("keypoints", "action", "agent_pos", "block_pose", "goal_pose"):
            np.testing.assert_array_equal(a.episode(i)[key], b.episode(i)[key])
    with pytest.raises(ValueError, match="holds 2 episodes of another collection"):
        collect_pusht(tmp_path / "a.zarr", 1, progress=False)
    with pytest.raises(ValueError, match="n_episodes"):
        collect_pusht(tmp_path / "c.zarr", 0, progress=False)


@pytest.mark.slow
def test_collect_cli_writes_store_config_summary_and_video(tmp_path):
    cmd = [sys.executable, "-m", "kpflow.cli.collect", "task=pusht", "n_episodes=2", "workers=1", "videos=1",
           "seed=1", f"hydra.run.dir={tmp_path}"]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["n_episodes"] == 2
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["episodes"] == 2 and len(EpisodeStore(tmp_path / "episodes.zarr")) == 2
    assert (tmp_path / "episode_000.mp4").stat().st_size > 0
    log = (tmp_path / "collect.log").read_text()  # the run's log says what it did (it was empty: issue 66)
    assert (
        "collecting 2 pusht episodes (expert, condition in_distribution)" in log
        and f"collected 2 episodes (2/{summary['attempts']} attempts" in log
    )


@pytest.mark.slow
def test_collect_cli_names_an_unknown_task(tmp_path):
    done = run_command("kpflow.cli.collect", "task=packing", f"hydra.run.dir={tmp_path}")
    assert (
        done.returncode != 0
        and "collects a Gymnasium task with an expert (kpflow.core.task.GymTask, e.g. Push-T), not PackingTask"
        in done.stderr
    )  # no scripted collector for it
    assert not (tmp_path / "config.yaml").exists()
    done = run_command("kpflow.cli.collect", "task=nope", f"hydra.run.dir={tmp_path}")
    assert done.returncode != 0 and "task/nope" in done.stderr and "pusht" in done.stderr  # Hydra lists the tasks
