"""Evaluate: ``python evaluate.py policy=transport split=all`` (Push-T) or ``python evaluate.py experiment=frames``.
Builds the experiment (and what it needs: policy, data, map) from ``conf/``, runs it, and writes the resolved
config, results, plots and videos under the run's output folder."""

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command
from kpflow.utils.run import log_metrics, make_loggers, start_run

SPLITS = ("in_distribution", "robot_ood", "object_ood", "standard", "all")
KEYS = {"seed": SEED, "n_configs": Key(int, lo=1), "first_config": Key(int, lo=0), "workers": Key(int, lo=1), "split": Key(str, choices=SPLITS)}


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
@command
def main(cfg: DictConfig) -> dict:
    out = start_run(cfg, KEYS)
    loggers = make_loggers(cfg)
    run = instantiate(cfg.experiment)
    results = run(output_dir=out, seed=cfg.seed)
    log_metrics(loggers, results["metrics"])
    print((out / "results.md").read_text())
    print(f"results: {out / 'results.md'}  plots: {sorted(str(p) for p in out.glob('*.png'))}")
    if videos := sorted(str(p) for p in out.glob("*.mp4")):
        print(f"videos: {videos}")
    return results


if __name__ == "__main__":
    main()
