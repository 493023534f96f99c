"""Keyboard teleoperation of Push-T: record your own demonstrations into an :class:`~kpflow.data.episode_store.EpisodeStore`.

Needs pygame, an optional extra: ``pip install 'kpflow[teleop]'``. Run::

    kpflow-teleop store=demos.zarr split=in_distribution goal=random episodes=5

Keys: arrows or WASD move the agent's absolute target (10 px per control step while held, 3 px with shift held);
space pauses/resumes; Enter saves the episode and starts the next one; Backspace discards it and restarts the same
configuration; Escape (or closing the window) quits, dropping the unsaved episode. An episode is also saved when the
block reaches the goal or after ``max_steps`` steps.

The simulation advances only while recording: a new episode waits for the first movement key (so no idle steps
open a demonstration), and a paused one is frozen. Each recorded step stores the observation *before* the action
and the action taken (the Diffusion Policy dataset's convention): ``keypoints`` [T, 25, 2], ``action`` [T, 2],
``agent_pos`` [T, 2], ``block_pose`` [T, 3] and ``goal_pose`` [T, 3], all float32.
"""

from __future__ import annotations

import os
from typing import Any, Callable, Iterable

import numpy as np

from kpflow.core.rollout import StopEpisode
from kpflow.data.episode_store import EpisodeStore

from .env import PushTEnv
from .geometry import coverage
from .rollout import run_episode

UNBOUNDED = 10**9  # steps: an env without max_steps records until Enter or success
_STATUS_PX = 28  # height of the status line under the scene


def _import_pygame():
    """Import pygame, or explain how to install it."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError as e:
        raise ImportError("keyboard teleoperation needs pygame: install it with pip install 'kpflow[teleop]'") from e
    return pygame


class KeyboardTeleop:
    """Drive a :class:`PushTEnv` from the keyboard in a pygame window and save episodes into ``store``.

    Args:
        env: the environment; its split and goal mode are written to the store's attrs (once: a store recorded
            with another split or goal mode is refused).
        store: an episode store open for appending.
        step_px: target displacement per control step while a direction key is held.
        fine_px: the same with shift held.
        fps: control rate (the env's 10 Hz); 0 runs unthrottled.
        window_size: side of the square scene in the window, in pixels.

    Raises:
        ImportError: pygame is not installed.
        ValueError: the store holds demonstrations of another task, split or goal mode.
    """

    def __init__(
        self,
        env: PushTEnv,
        store: EpisodeStore,
        step_px: float = 10.0,
        fine_px: float = 3.0,
        fps: float = 10,
        window_size: int = 512,
    ) -> None:
        pg = self._pg = _import_pygame()
        if env.render_mode != "rgb_array":
            raise ValueError(
                f"teleoperation shows env.render(): the env needs render_mode='rgb_array', not {env.render_mode!r}"
            )
        self.env, self.store = env, store
        self.step_px, self.fine_px, self.fps = float(step_px), float(fine_px), fps
        self._set_store_attrs()
        self._directions = {
            pg.K_RIGHT: (1, 0),
            pg.K_d: (1, 0),
            pg.K_LEFT: (-1, 0),
            pg.K_a: (-1, 0),
            pg.K_DOWN: (0, 1),
            pg.K_s: (0, 1),  # image rows grow with world y
            pg.K_UP: (0, -1),
            pg.K_w: (0, -1),
        }
        self._shift = {pg.K_LSHIFT, pg.K_RSHIFT}
        self._held: set[int] = set()
        self._target: np.ndarray | None = None
        self.paused = self.save_requested = self.discard_requested = self.quit_requested = False
        pg.display.init()
        pg.font.init()
        self._screen = pg.display.set_mode((window_size, window_size + _STATUS_PX))
        pg.display.set_caption(
            "Push-T teleop: arrows/WASD move (shift: fine), space pause, Enter save, Backspace discard, Esc quit"
        )
        self._font = pg.font.Font(None, 24)
        self._clock = pg.time.Clock()

    def _set_store_attrs(self) -> None:
        """Write task, split and goal mode to the store's attrs; refuse a store recorded with other ones."""
        expected = {"task": "pusht", "split": self.env.split, "goal": self.env.goal_mode}
        clash = {
            k: self.store.attrs[k] for k in expected if k in self.store.attrs and self.store.attrs[k] != expected[k]
        }
        if clash:
            raise ValueError(f"{self.store.path} holds demonstrations with {clash}; this session records {expected}")
        self.store.attrs.update(expected)

    # ------------------------------------------------------------------------------------------------ input
    def handle_event(self, event: Any) -> None:
        """Update the held keys and the pending commands (pause, save, discard, quit) from one pygame event."""
        pg = self._pg
        if event.type == pg.QUIT:
            self.quit_requested = True
        elif event.type == pg.WINDOWFOCUSLOST:
            self._held.clear()  # key releases are not delivered to an unfocused window
        elif event.type == pg.KEYUP:
            self._held.discard(event.key)
        elif event.type == pg.KEYDOWN:
            if event.key in self._directions or event.key in self._shift:
                self._held.add(event.key)
            elif event.key == pg.K_SPACE:
                self.paused = not self.paused
            elif event.key in (pg.K_RETURN, pg.K_KP_ENTER):
                self.save_requested = True
            elif event.key == pg.K_BACKSPACE:
                self.discard_requested = True
            elif event.key == pg.K_ESCAPE:
                self.quit_requested = True

    def velocity(self) -> np.ndarray:
        """Target displacement per control step from the held keys (opposite keys cancel)."""
        d = np.sum([self._directions[k] for k in self._held if k in self._directions] or [(0, 0)], axis=0)
        return np.sign(d) * (self.fine_px if self._held & self._shift else self.step_px)

    def target(self) -> np.ndarray:
        """The agent's current absolute target (the next action), a copy."""
        if self._target is None:
            raise RuntimeError("no episode started: call run_episode() first")
        return self._target.copy()

    # ------------------------------------------------------------------------------------------------ episodes
    # ------------------------------------------------------------------------------------------------ policy
    def reset(self, seed: int | None = None) -> None:
        """Start an episode: no target yet (the first observation gives it), nothing pending or held."""
        self._target, self._steps = None, 0
        self.paused = self.save_requested = self.discard_requested = self.quit_requested = False
        self._held.clear()

    def act(self, obs: dict) -> np.ndarray:
        """The next target ``[1, 2]`` from the keyboard (the person is the policy of
        :func:`~kpflow.tasks.pusht.rollout.run_episode`).

        Each control tick reads the events once (``event_source``), then either returns a target (while recording:
        not paused, and moving or already started) or redraws the window and waits for the next tick. Enter (after
        at least one step), Backspace and quitting end the episode by raising
        :class:`~kpflow.core.rollout.StopEpisode`.
        """
        if self._target is None:
            self._target = np.asarray(obs["agent_pos"], float).copy()
        elif self._steps:
            self._tick(obs)  # the step just taken: show it
        while True:
            for event in self._event_source():
                self.handle_event(event)
            if self.quit_requested or self.discard_requested:
                raise StopEpisode
            if self.save_requested:
                if self._steps:
                    raise StopEpisode
                self.save_requested = False  # nothing recorded yet: nothing to save
            if not self.paused and (self._steps or self.velocity().any()):
                self._target = np.clip(self._target + self.velocity(), 0.0, self.env.workspace.size)
                self._steps += 1
                return self._target[None].copy()
            self._tick(obs)

    def _tick(self, obs: dict) -> None:
        self._draw(coverage(obs["block_pose"], obs["goal_pose"]), self._steps)
        self._clock.tick(self.fps)

    # ------------------------------------------------------------------------------------------------ episodes
    def run_episode(
        self,
        seed: int,
        event_source: Callable[[], Iterable[Any]] | None = None,
        max_steps: int | None = None,
    ) -> dict[str, np.ndarray] | None:
        """Reset the env with ``seed``, record one episode and save it to the store.

        The episode is :func:`~kpflow.tasks.pusht.rollout.run_episode`'s with this teleop as the policy.
        ``event_source`` (default ``pygame.event.get``) is called once per control tick, before that tick's
        action. The episode ends on Enter, success, or ``max_steps`` recorded steps (default: the env's
        ``max_steps``), and is then saved; it returns the recorded arrays. It returns ``None`` without saving on
        Backspace (see :attr:`discard_requested`) or quit (:attr:`quit_requested`).
        """
        self._event_source = event_source or self._pg.event.get
        max_steps = self.env.max_steps if max_steps is None else max_steps
        self.env.reset(seed=seed)  # the seed's configuration of the env's split
        result = run_episode(
            self.env, self, self.env.config, UNBOUNDED if max_steps is None else max_steps, record=True
        )
        if self.quit_requested or self.discard_requested:
            return None
        attrs = {"seed": int(seed), "success": result.success, "coverage": result.coverage, "source": "teleop"}
        self.store.add_episode(result.episode, attrs)
        return result.episode

    def run(self, n_episodes: int, seed: int = 0, event_source: Callable[[], Iterable[Any]] | None = None) -> int:
        """Record up to ``n_episodes`` episodes with seeds ``seed, seed + 1, ...``; returns how many were saved.

        A discarded episode restarts with the same seed; quitting stops early. ``event_source``: as in
        :meth:`run_episode`.
        """
        saved = 0
        while saved < n_episodes:
            if self.run_episode(seed + saved, event_source) is not None:
                saved += 1
            elif self.quit_requested:
                break
        return saved

    def close(self) -> None:
        """Close the window."""
        self._pg.display.quit()

    # ------------------------------------------------------------------------------------------------ display
    def _draw(self, coverage: float, n_steps: int) -> None:
        pg, screen = self._pg, self._screen
        frame = self.env.render()
        side = screen.get_width()
        scene = pg.image.frombuffer(np.ascontiguousarray(frame).tobytes(), frame.shape[1::-1], "RGB")
        if scene.get_size() != (side, side):
            scene = pg.transform.smoothscale(scene, (side, side))
        screen.fill((255, 255, 255))
        screen.blit(scene, (0, 0))
        state = "  PAUSED" if self.paused else ("" if n_steps else "  (move to start)")
        text = f"coverage {coverage:.0%}   step {n_steps}   episodes {self.store.n_episodes}{state}"
        screen.blit(self._font.render(text, True, (0, 0, 0)), (8, side + 6))
        pg.display.flip()
