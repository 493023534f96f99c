"""Generate demonstrations for a robosuite benchmark task: ``python -m kpflow.generate task=square n=200``.

Transports ``n_sources`` scripted demonstrations into ``n`` new scenes per variant and family, segment by segment
(:mod:`kpflow.eval.generation`), and keeps the successes: ``<variant>/<family>/episodes.zarr`` and robomimic's
``demos.hdf5``, with ``results.json``, ``results.md`` (generation rates with 95% intervals, failure reasons,
throughput), a video and the resolved config in the run folder.
"""

from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.eval.generation import generate
from kpflow.tasks.suite.task import SuiteTask
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command
from kpflow.utils.run import remove_unused_run_folder, start_run

KEYS = {
    "n": Key(int, lo=1),
    "n_sources": Key(int, lo=1),
    "candidates": Key(int, lo=1, nullable=True),
    "stop_early": Key(bool),
    "seed": SEED,
    "workers": Key(int, lo=1),
    "videos": Key(int, lo=0),
    "export": Key(bool),
}


@hydra.main(version_base="1.3", config_path="../conf", config_name="generate")
@command
def main(cfg: DictConfig) -> dict:
    task = instantiate(cfg.task)
    unknown = [f for f in cfg.families if f not in cfg.transports]
    if not isinstance(task, SuiteTask) or unknown:
        remove_unused_run_folder(Path(cfg.output_dir))
        if unknown:
            raise ValueError(f"families {unknown} are not among the transports {sorted(cfg.transports)}")
        raise ValueError(f"generation needs a robosuite benchmark task (lift, stack, can, square), not {type(task).__name__}")
    out = start_run(cfg, KEYS)
    families = {name: instantiate(cfg.transports[name]) for name in cfg.families}
    results = generate(out, task, families, list(cfg.variants), n=cfg.n, n_sources=cfg.n_sources, seed=cfg.seed,
                       candidates=cfg.candidates, stop_early=cfg.stop_early, workers=cfg.workers, videos=cfg.videos,
                       export=cfg.export)  # fmt: skip
    for row in results["summary"]:
        print(f"{task.name} {row['variant']} {row['family']}: {row['successes']}/{row['trials']} generated")
    return results


if __name__ == "__main__":
    main()
