"""Keyboard teleoperation of Push-T, headless: key events are posted to the real pygame event queue."""

import itertools
import os
import sys

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402

from kpflow.cli.teleop import main  # noqa: E402
from kpflow.data.episode_store import EpisodeStore  # noqa: E402
from kpflow.tasks.pusht.env import PushTEnv  # noqa: E402
from kpflow.tasks.pusht.teleop import KeyboardTeleop  # noqa: E402

FIELDS = {"keypoints": (25, 2), "action": (2,), "agent_pos": (2,), "block_pose": (3,), "goal_pose": (3,)}


def down(key: int) -> pygame.event.Event:
    return pygame.event.Event(pygame.KEYDOWN, key=key)


def up(key: int) -> pygame.event.Event:
    return pygame.event.Event(pygame.KEYUP, key=key)


def scripted(script: dict[int, list], teleop: KeyboardTeleop | None = None, targets: list | None = None):
    """An event source that posts ``script[i]`` to pygame's queue on its i-th call, then drains the queue.

    With ``targets``, it also logs ``teleop.target()`` at each call (the target before that control step).
    """
    calls = itertools.count()

    def source():
        if targets is not None:
            targets.append(teleop.target())
        for event in script.get(next(calls), ()):
            pygame.event.post(event)
        return pygame.event.get()

    return source


def make_teleop(path, **env_kwargs) -> KeyboardTeleop:
    env = PushTEnv(render_size=96, render_mode="rgb_array", **env_kwargs)
    teleop = KeyboardTeleop(env, EpisodeStore(path, mode="a"), step_px=10, fine_px=3, fps=0, window_size=128)
    pygame.event.clear()
    return teleop


@pytest.fixture
def teleop(tmp_path):
    t = make_teleop(tmp_path / "demos.zarr")
    yield t
    t.close()


def test_records_saves_and_aligns_observations_with_actions(teleop, tmp_path):
    targets = []
    script = {0: [down(pygame.K_RIGHT)], 4: [up(pygame.K_RIGHT)], 7: [down(pygame.K_RETURN)]}
    episode = teleop.run_episode(seed=3, event_source=scripted(script, teleop, targets))

    store = EpisodeStore(tmp_path / "demos.zarr", mode="r")
    assert store.n_episodes == 1 and set(store.fields) == set(FIELDS)
    saved = store.episode(0)
    for name, shape in FIELDS.items():
        assert saved[name].shape == (7, *shape) and saved[name].dtype == np.float32, name
        np.testing.assert_array_equal(saved[name], episode[name])
    attrs = store.episode_attrs(0)
    assert attrs == {"seed": 3, "success": False, "coverage": attrs["coverage"], "source": "teleop"}
    assert isinstance(attrs["coverage"], float) and 0.0 <= attrs["coverage"] < 0.95
    assert dict(store.attrs) == {"task": "pusht", "split": "in_distribution", "goal": "random"}

    # Held for 4 steps: +10 px right each; released: the target stays.
    action, agent = episode["action"], episode["agent_pos"]
    start = agent[0]
    np.testing.assert_allclose(np.diff(action[:, 0], prepend=start[0]), [10, 10, 10, 10, 0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(action[:, 1], start[1], atol=1e-4)
    # action[t] is the target of step t: the target logged at the start of step t + 1.
    np.testing.assert_allclose(action, np.array(targets[1:]), atol=1e-4)
    # The observation precedes its action: the agent starts at the reset position and moves towards each target.
    assert np.all(np.diff(agent[:, 0]) > 0)
    np.testing.assert_allclose(agent[:, 1], start[1], atol=1e-3)
    assert np.all(np.abs(action[:-1] - agent[1:])[:, 0] < np.abs(action[:-1] - agent[:-1])[:, 0])
    np.testing.assert_allclose(episode["keypoints"][:, -1], agent, atol=1e-4)
    assert np.all(episode["goal_pose"] == episode["goal_pose"][0])

    # Replaying the actions from the same seed reproduces every recorded observation.
    env = PushTEnv()
    obs, _ = env.reset(seed=3)
    for t in range(7):
        for name in ("keypoints", "agent_pos", "block_pose", "goal_pose"):
            np.testing.assert_allclose(episode[name][t], obs[name], atol=1e-3, err_msg=f"{name}[{t}]")
        obs, *_ = env.step(action[t])


def test_pause_freezes_and_enter_needs_a_recorded_step(teleop):
    script = {
        0: [down(pygame.K_RETURN)],  # nothing recorded yet: ignored
        1: [down(pygame.K_d)],  # first movement starts the episode
        3: [down(pygame.K_SPACE)],  # paused: no steps on calls 3, 4, 5
        6: [down(pygame.K_SPACE)],
        8: [down(pygame.K_KP_ENTER)],
    }
    episode = teleop.run_episode(seed=0, event_source=scripted(script))
    assert len(episode["action"]) == 4
    np.testing.assert_allclose(episode["action"][:, 0] - episode["agent_pos"][0, 0], [10, 20, 30, 40], atol=1e-4)
    assert teleop.store.n_episodes == 1


def test_keys_fine_steps_diagonals_and_focus_loss(teleop):
    teleop.handle_event(down(pygame.K_RIGHT))
    teleop.handle_event(down(pygame.K_w))
    np.testing.assert_array_equal(teleop.velocity(), [10, -10])
    teleop.handle_event(down(pygame.K_LSHIFT))
    np.testing.assert_array_equal(teleop.velocity(), [3, -3])
    teleop.handle_event(up(pygame.K_LSHIFT))
    teleop.handle_event(down(pygame.K_a))  # opposite of right: cancels
    np.testing.assert_array_equal(teleop.velocity(), [0, -10])
    teleop.handle_event(pygame.event.Event(pygame.WINDOWFOCUSLOST))
    np.testing.assert_array_equal(teleop.velocity(), [0, 0])


def test_target_is_clipped_and_max_steps_ends_and_saves(teleop):
    script = {0: [down(pygame.K_LEFT), down(pygame.K_UP), down(pygame.K_RSHIFT)], 2: [up(pygame.K_RSHIFT)]}
    episode = teleop.run_episode(seed=1, event_source=scripted(script), max_steps=50)
    action = episode["action"]
    assert len(action) == 50 and teleop.store.n_episodes == 1
    np.testing.assert_allclose(action[1] - action[0], [-3, -3], atol=1e-4)
    np.testing.assert_allclose(action[2] - action[1], [-10, -10], atol=1e-4)
    np.testing.assert_array_equal(action[-1], [0, 0])  # clipped to the workspace
    assert action.min() == 0


def test_success_ends_and_saves(tmp_path):
    scratch = PushTEnv(goal="fixed")
    seed = next(s for s in range(100) if scratch.reset(seed=s)[1]["coverage"] > 0.2)
    teleop = make_teleop(tmp_path / "demos.zarr", goal="fixed", success_threshold=0.1)
    try:
        episode = teleop.run_episode(seed=seed, event_source=scripted({0: [down(pygame.K_DOWN)]}))
    finally:
        teleop.close()
    assert len(episode["action"]) == 1
    attrs = teleop.store.episode_attrs(0)
    assert attrs["success"] is True and attrs["coverage"] > 0.1 and attrs["seed"] == seed


def test_backspace_discards_and_escape_quits_without_saving(teleop):
    discard = {0: [down(pygame.K_RIGHT)], 3: [down(pygame.K_BACKSPACE)]}
    assert teleop.run_episode(seed=0, event_source=scripted(discard)) is None
    assert teleop.discard_requested and not teleop.quit_requested and teleop.store.n_episodes == 0

    for stop in (down(pygame.K_ESCAPE), pygame.event.Event(pygame.QUIT)):
        assert teleop.run_episode(seed=0, event_source=scripted({0: [down(pygame.K_RIGHT)], 3: [stop]})) is None
        assert teleop.quit_requested and teleop.store.n_episodes == 0


def test_run_restarts_discarded_episodes_with_their_seed_and_stops_on_quit(teleop):
    script = {
        0: [down(pygame.K_RIGHT)],
        2: [down(pygame.K_RETURN)],  # seed 5: saved
        3: [down(pygame.K_RIGHT)],
        4: [down(pygame.K_BACKSPACE)],  # seed 6: discarded
        5: [down(pygame.K_RIGHT)],
        7: [down(pygame.K_RETURN)],  # seed 6 again: saved
        8: [down(pygame.K_ESCAPE)],
    }
    assert teleop.run(5, seed=5, event_source=scripted(script)) == 2
    assert [teleop.store.episode_attrs(i)["seed"] for i in range(2)] == [5, 6]
    assert [len(teleop.store.episode(i)["action"]) for i in range(2)] == [2, 2]


def test_store_of_another_split_is_refused(tmp_path):
    EpisodeStore(tmp_path / "demos.zarr", mode="a").attrs.update(
        {"task": "pusht", "split": "robot_ood", "goal": "random"}
    )
    with pytest.raises(ValueError, match="robot_ood"):
        make_teleop(tmp_path / "demos.zarr")


def test_cli_sets_up_the_store(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "kpflow-teleop",
            f"store={tmp_path / 'cli.zarr'}",
            "split=object_ood",
            "goal=fixed",
            "episodes=0",
            "window=64",
        ],
    )
    main()
    store = EpisodeStore(tmp_path / "cli.zarr", mode="r")
    assert dict(store.attrs) == {"task": "pusht", "split": "object_ood", "goal": "fixed"} and store.n_episodes == 0
    assert "saved 0 episode(s)" in capsys.readouterr().out


def test_missing_pygame_gives_install_hint(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pygame", None)
    with pytest.raises(ImportError, match=r"pip install 'kpflow\[teleop\]'"):
        KeyboardTeleop(PushTEnv(), EpisodeStore(tmp_path / "demos.zarr", mode="a"))
