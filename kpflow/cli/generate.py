"""Generate demonstrations for a robosuite benchmark task: ``kpflow-generate task=square n=200``.

Transports ``n_sources`` scripted demonstrations into ``n`` new scenes per variant and family, segment by segment
(:mod:`kpflow.generation.generate`), and keeps the successes: ``<variant>/<family>/episodes.zarr`` and robomimic's
``demos.hdf5``, with ``results.json``, ``results.md`` (generation rates with 95% intervals, failure reasons,
throughput), a video and the resolved config in the run folder.

Every attempt is committed as it finishes (:mod:`kpflow.generation.journal`), so a run that was stopped (a
kill, a crash, a lost machine) continues in its folder with the same command plus ``resume=true`` and its folder:
``run_name=NAME`` (the folder ``outputs/generate/<task>/NAME``) or ``hydra.run.dir=FOLDER``. It skips the attempts
already committed and ends with the stores and results an uninterrupted run writes (the throughput counts the
attempts the resumed run made). Without ``resume=true`` a folder that holds a generation run is refused; with it,
one whose settings (``generation.json``) differ from the command's is refused, naming them (``workers``, ``videos``
and ``export`` may change).

Past one machine: ``shards=S shard=K`` runs only the attempts ``i`` with ``i % S == K`` (every variant and family;
``K`` in ``0..S-1``, ``S`` at most ``n``), and a Hydra multirun over a launcher runs all the shards as separate jobs,
each in its own folder ``multirun/generate/<task>/<run_name>/<job>_shard<K>``::

    kpflow-generate -m task=lift n=200 shards=4 'shard=range(4)' run_name=NAME hydra/launcher=pool
    kpflow-merge 'shards=multirun/generate/lift/NAME/*' out=outputs/generate/lift/NAME

(``hydra/launcher=local``: submitit jobs on this machine; ``slurm``: SLURM jobs.) ``kpflow-merge``
(:mod:`kpflow.cli.merge`) joins them into the folder one run writes, the same to the bit. A shard resumes like a
run (``resume=true`` with its folder, ``hydra.run.dir=...``); its ``generation.json`` records the shard, so a resume
with another ``shards`` or ``shard`` is refused.
"""

from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.generation.generate import generate
from kpflow.generation.journal import check_output, run_manifest, shard_indices
from kpflow.tasks.suite.task import SuiteTask
from kpflow.utils.config_checks import SEED, Key, check_config
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.run import remove_unused_run_folder, start_run, write_config

KEYS = {
    "n": Key(int, lo=1),
    "n_sources": Key(int, lo=1),
    "candidates": Key(int, lo=1, nullable=True),
    "stop_early": Key(bool),
    "seed": SEED,
    "workers": Key(int, lo=1),
    "videos": Key(int, lo=0),
    "export": Key(bool),
    "resume": Key(bool),
    "run_name": Key(str),
    "shards": Key(int, lo=1),
    "shard": Key(int, lo=0),
}


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="generate")
@command
def main(cfg: DictConfig) -> dict:
    task = instantiate(cfg.task)
    unknown = [f for f in cfg.families if f not in cfg.transports]
    try:
        if unknown:
            raise ValueError(f"families {unknown} are not among the transports {sorted(cfg.transports)}")
        if not isinstance(task, SuiteTask):
            raise ValueError(
                f"generation needs a robosuite benchmark task (lift, stack, can, square), not {type(task).__name__}"
            )
        check_config(cfg, KEYS)
        shard_indices(cfg.n, cfg.shards, cfg.shard)  # shard in 0..shards-1, shards <= n
    except ValueError:
        remove_unused_run_folder(Path(cfg.output_dir))
        raise
    out = start_run(cfg, KEYS, write=False)  # claims the folder: no other run passes the check below with us
    families = {name: instantiate(cfg.transports[name]) for name in cfg.families}
    settings = dict(n=cfg.n, n_sources=cfg.n_sources, seed=cfg.seed, candidates=cfg.candidates, stop_early=cfg.stop_early,
                    shards=cfg.shards, shard=cfg.shard)  # fmt: skip
    check_output(out, run_manifest(task, families, list(cfg.variants), **settings), cfg.resume)  # before config.yaml
    write_config(cfg)
    results = generate(out, task, families, list(cfg.variants), **settings, workers=cfg.workers, videos=cfg.videos,
                       export=cfg.export, resume=cfg.resume)  # fmt: skip
    part = f" (shard {cfg.shard} of {cfg.shards})" if cfg.shards > 1 else ""
    for row in results["summary"]:
        print(f"{task.name} {row['variant']} {row['family']}{part}: {row['successes']}/{row['trials']} generated")
    return results


if __name__ == "__main__":
    main()
