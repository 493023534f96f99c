"""Evaluate: ``python evaluate.py policy=transport split=all`` (Push-T) or ``python evaluate.py experiment=frames``.
Builds the experiment (and what it needs: policy, data, map) from ``conf/``, runs it, and writes the resolved
config, results, plots and videos under the run's output folder."""

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from kpflow.utils.run import log_metrics, make_loggers, start_run


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
def main(cfg: DictConfig) -> dict:
    out = start_run(cfg)
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
