"""Collect demonstrations: ``kpflow-collect task=pusht n_episodes=35``, or for a Gymnasium task of your own
(:class:`~kpflow.core.task.GymTask` with an expert) ``kpflow-collect --config-dir conf task=<task> n_episodes=50``.
Push-T also collects a policy's own successful episodes (self-generated demonstrations):
``kpflow-collect policy=transport data=pusht_human data.max_episodes=90 split=standard first_index=10000``.

Rolls the task's scripted expert out on seeded configurations and commits each successful episode to an
:class:`~kpflow.data.episode_store.EpisodeStore` (zarr, Diffusion Policy layout) in the run's output folder
(``episodes.zarr``), beside the resolved config and (Push-T) a few episode videos.
"""

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.cli.spellings import old_spellings_read
from kpflow.core.task import GymTask
from kpflow.tasks.collection import collect_gym_episodes
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.scene import GOAL_MODES, SPLITS
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.io import write_json
from kpflow.utils.run import remove_unused_run_folder, start_run

log = logging.getLogger(__name__)  # the console and the run's collect.log (Hydra's job logging)
KEYS = {
    "n_episodes": Key(int, lo=1),
    "seed": SEED,
    "max_steps": Key(int, lo=1),
    "workers": Key(int, lo=1),
    "videos": Key(int, lo=0),
    "keep_failures": Key(bool),
    "split": Key(str, choices=(*SPLITS, "standard")),
    "first_index": Key(int, lo=0),
    "goal": Key(str, choices=GOAL_MODES),
    "condition": Key(str, nullable=True),
}


@old_spellings_read
@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="collect")
@command
def main(cfg: DictConfig) -> dict:
    if HydraConfig.get().runtime.choices.get("task") != "pusht":
        return collect_task(cfg)
    policy = source = None
    if cfg.get("policy") is not None:
        source = f"policy:{HydraConfig.get().runtime.choices.get('policy')}"
        policy = instantiate(cfg.policy)  # before the run folder: a bad policy leaves nothing behind
    out = start_run(cfg, KEYS)
    log.info("collecting %d Push-T episodes (%s, split %s) into %s", cfg.n_episodes, source or "expert", cfg.split, out)
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
        policy=policy,
        source=source or "expert",
        first_index=cfg.first_index,
    )
    return finished(out, summary)


def collect_task(cfg: DictConfig) -> dict:
    """A Gymnasium task's expert episodes (:func:`~kpflow.tasks.collection.collect_gym_episodes`)."""
    task = instantiate(cfg.task)
    if not isinstance(task, GymTask):
        remove_unused_run_folder(Path(cfg.output_dir))
        raise ValueError(
            f"kpflow-collect collects Push-T or a Gymnasium task with an expert (kpflow.core.task.GymTask), not {type(task).__name__}"
        )
    out = start_run(cfg, KEYS)
    log.info("collecting %d episodes of %s's expert into %s", cfg.n_episodes, type(task).__name__, out)
    summary = collect_gym_episodes(
        task, out / "episodes.zarr", cfg.n_episodes, cfg.condition, cfg.seed, cfg.keep_failures
    )
    return finished(out, summary)


def finished(out: Path, summary: dict) -> dict:
    """Write the run's ``summary.json`` and say what was collected, on the console and in the run's collect.log."""
    write_json(out / "summary.json", summary)
    log.info("collected %d episodes (%d/%d attempts succeeded, %d steps) into %s", summary["episodes"],
             summary["successes"], summary["attempts"], summary["steps"], summary["store"])  # fmt: skip
    log.info("summary: %s  config: %s", out / "summary.json", out / "config.yaml")
    return summary


if __name__ == "__main__":
    main()
