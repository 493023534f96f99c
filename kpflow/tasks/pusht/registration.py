"""Push-T's Gymnasium ids, one per split: ``gymnasium.make("kpflow/PushT-v0")`` after ``import kpflow``.

``max_episode_steps`` wraps each in Gymnasium's ``TimeLimit`` (truncation), so the env itself runs unbounded.
``kpflow/PushT-v0`` is Diffusion Policy's protocol (``reset(seed=s)`` gives its start state for seed ``s``).
"""

from __future__ import annotations

import gymnasium as gym

ENTRY_POINT = "kpflow.tasks.pusht.env:PushTEnv"

#: id -> (PushTEnv keyword arguments, max_episode_steps)
ENV_IDS: dict[str, tuple[dict, int]] = {
    "kpflow/PushT-v0": ({"split": "standard", "goal": "fixed"}, 300),
    "kpflow/PushT-InDistribution-v0": ({"split": "in_distribution", "goal": "random"}, 1200),
    "kpflow/PushT-RobotOOD-v0": ({"split": "robot_ood", "goal": "random"}, 1200),
    "kpflow/PushT-ObjectOOD-v0": ({"split": "object_ood", "goal": "random"}, 1200),
}


def registered_steps(split: str) -> int:
    """The ``max_episode_steps`` registered for Push-T's ``split`` (its id's of :data:`ENV_IDS`): the one place an
    episode's step limit is written (300 on ``standard``, Diffusion Policy's; 1200 on Table 1's splits)."""
    for kwargs, max_episode_steps in ENV_IDS.values():
        if kwargs["split"] == split:
            return max_episode_steps
    raise ValueError(
        f"no Push-T id registers split {split!r}; the splits are {[k['split'] for k, _ in ENV_IDS.values()]}"
    )


def register_envs() -> None:
    """Register every id of :data:`ENV_IDS` that is not registered yet."""
    for env_id, (kwargs, max_episode_steps) in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=ENTRY_POINT, kwargs=kwargs, max_episode_steps=max_episode_steps)
