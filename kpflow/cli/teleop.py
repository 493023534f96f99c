"""Record Push-T demonstrations from the keyboard: ``kpflow-teleop store=demos.zarr episodes=5 [split=robot_ood goal=fixed]``.

Opens a pygame window (``pip install 'kpflow[teleop]'``) and appends every saved episode to ``store``
(:class:`~kpflow.tasks.pusht.teleop.KeyboardTeleop`: the keys, what is recorded and when an episode ends).
"""

import hydra
from omegaconf import DictConfig

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.scene import GOAL_MODES, SPLITS
from kpflow.tasks.pusht.teleop import KeyboardTeleop
from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.errors import command, config_dir_checked

KEYS = {
    "store": Key(str),
    "split": Key(str, choices=SPLITS),
    "goal": Key(str, choices=GOAL_MODES),
    "episodes": Key(int, lo=0),
    "seed": Key(int, lo=0, nullable=True),
    "max_steps": Key(int, lo=1),
    "step_px": Key(float, lo=0),
    "fine_px": Key(float, lo=0),
    "fps": Key(float, lo=0),
    "window": Key(int, lo=16),
}


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="teleop")
@command
def main(cfg: DictConfig) -> int:
    check_config(cfg, KEYS)
    env = PushTEnv(split=cfg.split, goal=cfg.goal, max_steps=cfg.max_steps, render_mode="rgb_array")
    store = EpisodeStore(cfg.store, mode="a")
    teleop = KeyboardTeleop(env, store, cfg.step_px, cfg.fine_px, cfg.fps, cfg.window)
    try:
        saved = teleop.run(cfg.episodes, store.n_episodes if cfg.seed is None else cfg.seed)
    finally:
        teleop.close()
    print(f"saved {saved} episode(s); {store.path} holds {store.n_episodes}")
    return saved


if __name__ == "__main__":
    main()
