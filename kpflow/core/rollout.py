"""The one closed-loop episode: a policy acts in a Gymnasium env, one action per ``env.step``, until success, the
env's end or a step limit.

:func:`rollout` resets the env (``reset(seed=..., options=...)``: a Gymnasium task's seeded scene, Push-T's
configuration), runs the policy through :class:`~kpflow.core.policy.ClosedLoop` (its observation history and
action queue) and records what a demonstration store holds: the observation's ``record`` fields before each step and
the action taken (Diffusion Policy's convention). The episode ends on ``info["is_success"]`` (Gymnasium's convention,
a success), on ``terminated`` or ``truncated``, or after ``max_steps``.

An :class:`Override` may take control from the policy for a while (an expert correcting it): each step it is asked
first, and an action it returns replaces the policy's, whose pending chunk is dropped (it starts afresh when it gets
control back). A policy ends the episode early by raising :class:`StopEpisode` (a person pressing Enter).
``track`` names the info values kept at every step (Push-T's coverage, for its thresholds).

Two optional hooks let an env with costly observations (a camera capture) take part: before each step the loop
tells it whether a decision will read the observation that step returns (``env.unwrapped.will_read(bool)``, where
the env has it: the policy's history is refilled before its queue runs dry), and an env that cannot start the
episode (a camera that placed nothing) says so in reset's ``info["failure"]``, which ends the episode before any step.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from kpflow.core.policy import ClosedLoop, Policy


class StopEpisode(Exception):
    """Raised by a policy's ``act`` to end the episode before its next step (a person pressing Enter)."""


class Override(Protocol):
    """Something that may take control from the policy for a while (an expert correcting it): each step it is asked
    first, and an action it returns replaces the policy's (whose pending chunk is then dropped)."""

    def start(self, env, obs: dict, info: dict, seed: int | None) -> None:
        """A new episode began in ``env`` with ``obs`` and ``info``."""

    def act(self, step: int, obs: dict) -> np.ndarray | None:
        """The action for ``step``, or None to leave it to the policy."""

    def update(self, step: int, info: dict) -> None:
        """``step`` was taken; ``info`` is the env's after it."""


@dataclass
class Episode:
    """How an episode went: ``success`` (the env said ``is_success``), the ``steps`` taken, the policy's
    ``decisions`` (chunks asked for), the wall ``seconds``, the ``records`` (each recorded observation field and
    ``action``, ``[T, ...]`` float32), the ``tracked`` info values after each step (``[T]``), the first and last
    ``info``, the ``frames`` (``env.render()``, when asked) and, with an override, the steps it took (``overridden
    [T]``)."""

    success: bool
    steps: int
    decisions: int
    seconds: float
    records: dict[str, np.ndarray]
    tracked: dict[str, np.ndarray]
    first_info: dict
    info: dict
    frames: list | None = None
    overridden: np.ndarray | None = None


def _next_action(loop: ClosedLoop, override: Override | None, step: int, obs: dict) -> tuple[np.ndarray, bool]:
    action = None if override is None else override.act(step, obs)
    if action is None:
        return loop.action(obs), False
    loop.drop()
    return np.asarray(action, dtype=np.float64), True


def rollout(
    env,
    policy: Policy,
    max_steps: int,
    seed: int | None = None,
    reset: dict | None = None,
    record: tuple[str, ...] = (),
    render: bool = False,
    override: Override | None = None,
    track: tuple[str, ...] = (),
    action_dim: int | None = None,
) -> Episode:
    """Run ``policy`` in ``env`` (module docstring) for at most ``max_steps`` steps.

    ``reset``: the arguments of ``env.reset`` (``{"seed": s}``, ``{"options": {"config": c}}``); ``seed`` reseeds
    the policy (its sampling noise). ``record``: the observation fields kept before each step (with the actions);
    ``render``: collect ``env.render()`` before the first step and after each; ``track``: the ``info`` values kept
    after each step; ``action_dim``: check the policy's
    chunks are ``[H, action_dim]`` and finite (:class:`~kpflow.core.policy.ClosedLoop`)."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    obs, info = env.reset(**(reset or {}))
    first_info = info
    loop = ClosedLoop(policy, action_dim)
    loop.reset(seed)
    will_read = getattr(env.unwrapped, "will_read", None)
    if override is not None:
        override.start(env, obs, info, seed)
    log, tracked = {k: [] for k in (*record, "action")}, {k: [] for k in track}
    frames = [env.render()] if render else None
    overridden, success, steps, start = [], False, 0, time.perf_counter()
    for step in range(0 if info.get("failure") else int(max_steps)):
        loop.observe(obs)
        try:
            action, took_over = _next_action(loop, override, step, obs)
        except StopEpisode:
            break
        overridden.append(took_over)
        for k in record:
            log[k].append(obs[k])
        log["action"].append(action)
        if will_read is not None:
            will_read(loop.reads_next())
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
        if override is not None:
            override.update(step, info)
        if frames is not None:
            frames.append(env.render())
        for k in track:
            tracked[k].append(info[k])
        if info.get("is_success", False):
            success = True
            break
        if terminated or truncated:
            break
    records = {k: np.asarray(v, dtype=np.float32) for k, v in log.items()}
    tracked = {k: np.asarray(v) for k, v in tracked.items()}
    return Episode(success, steps, loop.decisions, time.perf_counter() - start, records, tracked, first_info, info, frames,
                   np.array(overridden, bool) if override is not None else None)  # fmt: skip
