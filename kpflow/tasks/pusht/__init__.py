"""Push-T: push a T-shaped block onto a goal pose (Diffusion Policy's standard physics), seen through 25 keypoints.

* :mod:`.geometry` -- the T's boxes, its 12 keypoints (fixed order) and the coverage score.
* :mod:`.workspace` -- the standard 512-px arena and the large 1024-px one with a 512-px training region.
* :mod:`.physics` -- the pymunk space, built as the standard env builds it (quirks documented there).
* :mod:`.scene` -- seeded reset configurations: in-distribution, robot out of it, object out of it, and
  Diffusion Policy's standard start-state draw.
* :mod:`.env` -- :class:`PushTEnv`, the Gymnasium environment; :mod:`.registration` -- its ids
  (``gymnasium.make("kpflow/PushT-v0")``), registered on import.
* :mod:`.render` -- RGB frames (videos: :mod:`kpflow.utils.video`).
* :mod:`.routing` -- agent paths around the block, retimed into speed-bounded targets.
* :mod:`.demonstrator` -- :class:`~.demonstrator.PushTExpert`, the scripted demonstrator.
* :mod:`.rollout` -- one episode with any policy, recorded in the Diffusion Policy convention.
"""

from .env import PushTEnv
from .geometry import KEYPOINT_NAMES, N_KEYPOINTS, coverage, observation_keypoints, t_keypoints
from .physics import PushTPhysics
from .registration import ENV_IDS, register_envs
from .scene import (
    FIXED_GOAL,
    SPLITS,
    STANDARD_FIRST_SEED,
    Config,
    make_split,
    sample_config,
    split_config,
    standard_config,
)
from .workspace import WORKSPACES, Workspace, get_workspace

__all__ = [
    "PushTEnv",
    "ENV_IDS",
    "PushTPhysics",
    "KEYPOINT_NAMES",
    "N_KEYPOINTS",
    "coverage",
    "observation_keypoints",
    "t_keypoints",
    "FIXED_GOAL",
    "SPLITS",
    "Config",
    "make_split",
    "sample_config",
    "split_config",
    "standard_config",
    "STANDARD_FIRST_SEED",
    "WORKSPACES",
    "Workspace",
    "get_workspace",
]

register_envs()
