"""Evaluate: ``python evaluate.py policy=transport condition=all`` (Push-T; ``split=`` is the old spelling) or ``python evaluate.py experiment=frames``.
Builds the experiment (and what it needs: policy, data, map) from ``kpflow/conf/``, runs it, writes the resolved
config, results, plots and videos under the run's output folder and prints the table it computed (an experiment
returns its results with ``metrics`` for the loggers, ``table``: the text of its results.md, and the ``figures`` and
``videos`` it wrote).

Once the run is over, ``config.yaml`` is written again with the values it used where the config left them to the
policy or the protocol (:func:`record_used`): the policy's steps, solver, executed actions, reach and turn (a
checkpoint's own settings, :mod:`kpflow.policies.settings`) and the step limit.

The run folder is the run's alone: a second run into a folder another live run holds is refused at once
(:func:`~kpflow.utils.run.claim_run_folder`)."""

import copy
import logging

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from kpflow.cli.spellings import old_spellings_read, read_split
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.run import abandon_run, log_metrics, make_loggers, start_run, write_config

log = logging.getLogger(__name__)  # the console and the run's evaluate.log (Hydra's job logging)
KEYS = {
    "seed": SEED,
    "n_configs": Key(int, lo=1),
    "first_config": Key(int, lo=0),
    "workers": Key(int, lo=1),
    "condition": Key(str),
}


def keys_of(task) -> dict:
    """:data:`KEYS`, with ``condition`` one of the conditions the run's task declares (``task.conditions``) or ``all``."""
    conditions = getattr(task, "conditions", None)
    return {**KEYS, "condition": Key(str, choices=(*conditions, "all"))} if conditions else KEYS


def with_task_built(cfg: DictConfig) -> tuple[DictConfig, object]:
    """``(config, task)``: the run's task built once and a copy of ``cfg`` whose ``task`` is that object, so that
    every ``${task}`` of the experiment and the policy is the same task (it was built once per mention); ``cfg``
    itself keeps the task's config, for ``config.yaml``. Without a task: ``(cfg, None)``."""
    if cfg.get("task") is None:
        return cfg, None
    task = instantiate(cfg.task)
    built = copy.deepcopy(cfg)
    built._set_flag("allow_objects", True)
    with open_dict(built):
        built.task = task
    return built, task


def record_used(cfg: DictConfig, results: dict) -> None:
    """Write into ``cfg`` what the run used (``results``' ``policy_settings`` and ``max_steps``, as its trial describes
    them) where the config names the key: ``policy.<setting>`` (a goal shown as observed is ``false``, never ``null``),
    ``policy.transport`` (a transported K-CFM's options as resolved), ``policy.search`` and ``policy.fit_on`` (nearest
    neighbour's and policy transportation's, as resolved) and ``experiment.trial.max_steps`` when the conditions run share one limit."""
    policy = cfg.get("policy")
    with open_dict(cfg):
        if policy is not None and "policy_settings" in results:
            used = {
                "reach": None,
                "turn_deg": None,
                **results["policy_settings"],
            }  # no goal limit in the policy: as observed
            for name, value in used.items():
                if name in policy:
                    policy[name] = False if value is None and name in ("reach", "turn_deg") else value
        limits = results.get("max_steps")
        if isinstance(limits, dict):
            limits = {limits[c] for c in {row["condition"] for row in results.get("summary", [])} if c in limits}
            limits = limits.pop() if len(limits) == 1 else None
        if policy is not None and "transport" in results and "transport" in policy:
            policy.transport = OmegaConf.create(results["transport"])  # every option as resolved, none left null
        for name, value in results.get("resolved", {}).items():  # policy=nearest | transport: the search, the fit
            if policy is not None and name in policy:
                policy[name] = OmegaConf.create(value) if isinstance(value, (dict, list)) else value
        trial = OmegaConf.select(cfg, "experiment.trial", default=None)
        if limits is not None and trial is not None and "max_steps" in trial:
            cfg.experiment.trial.max_steps = int(limits)


@old_spellings_read
@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="evaluate")
@command
def main(cfg: DictConfig) -> dict:
    read_split(cfg)
    built, task = with_task_built(cfg)
    out = start_run(cfg, keys_of(task))
    try:
        loggers = make_loggers(cfg)
        # the policy built and checked (a checkpoint of another task is refused here)
        run = instantiate(built.experiment)
    except BaseException:
        abandon_run(out)  # nothing ran: no run folder is left behind
        raise
    results = run(output_dir=out, seed=cfg.seed)
    record_used(cfg, results)
    write_config(cfg)  # again, with the values used
    log_metrics(loggers, results["metrics"])
    log.info("what this run computed (results.md holds the same):\n%s", results["table"])
    figures = [str(out / f) for f in results.get("figures", [])]
    log.info("results: %s%s", out / "results.md", f"  plots: {', '.join(figures)}" if figures else "")
    if results.get("videos"):
        log.info("videos: %s", ", ".join(map(str, results["videos"])))
    return results


if __name__ == "__main__":
    main()
