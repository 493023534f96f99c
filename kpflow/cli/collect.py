"""Collect demonstrations: ``kpflow-collect task=pusht n_episodes=35``, or for a Gymnasium task of your own
(:class:`~kpflow.core.task.GymTask` with an expert) ``kpflow-collect --config-dir conf task=<task> n_episodes=50``.
A policy's own successful episodes (self-generated demonstrations), where the task's collector lets a policy act
(Push-T): ``kpflow-collect policy=transport data=pusht_human data.max_episodes=90 condition=standard first_index=10000``.

One path for every task (:func:`~kpflow.tasks.collection.collect_episodes`): the task's scripted expert (or the
policy) is rolled out on seeded scenes and each successful episode committed to an
:class:`~kpflow.data.episode_store.EpisodeStore` (zarr, Diffusion Policy layout) in the run's output folder
(``episodes.zarr``), beside the resolved config and (Push-T) a few episode videos. ``split=`` is the old spelling
of ``condition=``, ``goal=`` of ``options.goal=``.
"""

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.cli.spellings import old_spellings_read, read_split
from kpflow.tasks.collection import CollectRequest, check_collectable, collect_episodes
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.io import write_json
from kpflow.utils.run import remove_unused_run_folder, start_run

log = logging.getLogger(__name__)  # the console and the run's collect.log (Hydra's job logging)
KEYS = {
    "n_episodes": Key(int, lo=1),
    "seed": SEED,
    "max_steps": Key(int, lo=1, nullable=True),
    "workers": Key(int, lo=1, nullable=True),
    "videos": Key(int, lo=0, nullable=True),
    "keep_failures": Key(bool),
    "first_index": Key(int, lo=0),
    "condition": Key(str, nullable=True),
}


def keys_of(task) -> dict:
    """:data:`KEYS`, with ``condition`` one of the conditions ``task`` declares (or null: its first)."""
    conditions = getattr(task, "conditions", None)
    return {**KEYS, "condition": Key(str, nullable=True, choices=tuple(conditions))} if conditions else KEYS


@old_spellings_read(renamed={"goal": "options.goal"})  # goal= was a top-level key
@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="collect")
@command
def main(cfg: DictConfig) -> dict:
    read_split(cfg)
    task = instantiate(cfg.task)
    try:
        check_collectable(task)
    except ValueError:
        remove_unused_run_folder(Path(cfg.output_dir))
        raise
    policy, source = None, "expert"
    if cfg.get("policy") is not None:
        source = f"policy:{HydraConfig.get().runtime.choices.get('policy')}"
        policy = instantiate(cfg.policy)  # before the run folder: a bad policy leaves nothing behind
    out = start_run(cfg, keys_of(task))
    request = CollectRequest(
        n_episodes=cfg.n_episodes,
        condition=cfg.condition,
        seed=cfg.seed,
        keep_failures=cfg.keep_failures,
        first_index=cfg.first_index,
        max_steps=cfg.max_steps,
        workers=cfg.workers,
        videos=cfg.videos,
        video_dir=out,
        policy=policy,
        source=source,
        options=dict(cfg.get("options") or {}),
    )
    log.info("collecting %d %s episodes (%s, condition %s) into %s", cfg.n_episodes, task.name, source,
             cfg.condition or task.conditions[0], out)  # fmt: skip
    return finished(out, collect_episodes(task, out / "episodes.zarr", request))


def finished(out: Path, summary: dict) -> dict:
    """Write the run's ``summary.json`` and say what was collected, on the console and in the run's collect.log."""
    write_json(out / "summary.json", summary)
    log.info("collected %d episodes (%d/%d attempts succeeded, %d steps) into %s", summary["episodes"],
             summary["successes"], summary["attempts"], summary["steps"], summary["store"])  # fmt: skip
    log.info("summary: %s  config: %s", out / "summary.json", out / "config.yaml")
    return summary


if __name__ == "__main__":
    main()
