"""Evaluate: ``python evaluate.py policy=transport split=all`` (Push-T) or ``python evaluate.py experiment=frames``.
Builds the experiment (and what it needs: policy, data, map) from ``kpflow/conf/``, runs it, writes the resolved
config, results, plots and videos under the run's output folder and prints the table it computed (an experiment
returns its results with ``metrics`` for the loggers, ``table``: the text of its results.md, and the ``figures`` and
``videos`` it wrote).

The run folder is the run's alone: a second run into a folder another live run holds is refused at once
(:func:`~kpflow.utils.run.claim_run_folder`)."""

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command
from kpflow.utils.run import log_metrics, make_loggers, start_run

SPLITS = ("in_distribution", "robot_ood", "object_ood", "standard", "all")
KEYS = {"seed": SEED, "n_configs": Key(int, lo=1), "first_config": Key(int, lo=0), "workers": Key(int, lo=1), "split": Key(str, choices=SPLITS)}


@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="evaluate")
@command
def main(cfg: DictConfig) -> dict:
    out = start_run(cfg, KEYS)
    loggers = make_loggers(cfg)
    run = instantiate(cfg.experiment)
    results = run(output_dir=out, seed=cfg.seed)
    log_metrics(loggers, results["metrics"])
    print(results["table"])  # what this run computed (results.md holds the same text)
    print(f"results: {out / 'results.md'}  plots: {[str(out / f) for f in results.get('figures', [])]}")
    if results.get("videos"):
        print(f"videos: {results['videos']}")
    return results


if __name__ == "__main__":
    main()
