"""Collect demonstrations: ``kpflow-collect task=pusht n_episodes=35``.

Rolls the task's scripted expert out on seeded configurations and commits each successful episode to an
:class:`~kpflow.data.episode_store.EpisodeStore` (zarr, Diffusion Policy layout) in the run's output folder, beside
the resolved config and a few episode videos.
"""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.scene import GOAL_MODES, SPLITS
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command
from kpflow.utils.io import write_json
from kpflow.utils.run import remove_unused_run_folder, start_run

TASKS = ("pusht",)
KEYS = {
    "n_episodes": Key(int, lo=1),
    "seed": SEED,
    "max_steps": Key(int, lo=1),
    "workers": Key(int, lo=1),
    "videos": Key(int, lo=0),
    "keep_failures": Key(bool),
    "split": Key(str, choices=SPLITS),
    "goal": Key(str, choices=GOAL_MODES),
}


@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="collect")
@command
def main(cfg: DictConfig) -> dict:
    task = HydraConfig.get().runtime.choices.get("task")
    if task not in TASKS:  # only Push-T has a scripted collector
        remove_unused_run_folder(Path(cfg.output_dir))
        raise ValueError(f"config key task must be one of {', '.join(TASKS)}; got {task!r}")
    out = start_run(cfg, KEYS)
    summary = collect_pusht(
        out / "episodes.zarr",
        n_episodes=cfg.n_episodes,
        split=cfg.split,
        goal=cfg.goal,
        seed=cfg.seed,
        max_steps=cfg.max_steps,
        workers=cfg.workers,
        keep_failures=cfg.keep_failures,
        videos=cfg.videos,
        video_dir=out,
    )
    write_json(out / "summary.json", summary)
    print(
        f"collected {summary['episodes']} episodes ({summary['successes']}/{summary['attempts']} attempts succeeded,"
        f" {summary['steps']} steps) into {summary['store']}"
    )
    return summary


if __name__ == "__main__":
    main()
