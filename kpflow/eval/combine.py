"""A Hydra callback that joins the tables of a multirun sweep into one: ``<sweep dir>/table.md``.

Every job's rows come first. Jobs that split one evaluation by trial ranges (a sweep over
``first_config`` or ``experiment.first_index.<condition>``, with ``n_configs`` or ``experiment.n_trials`` the shard
size: configs equal but for those,
and no trial run twice) are then pooled: their trials are summarised again together by the evaluation's own report,
so the pooled row's success rate and interval are those of one run over all the trials.
"""

from __future__ import annotations

import json
from pathlib import Path

from hydra.experimental.callback import Callback
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.eval.trials import trial_from_record
from kpflow.utils.formats import read_yaml
from kpflow.utils.io import write_text

#: Where the reports a pooled table may instantiate live.
REPORTS = "kpflow.eval.reports."
#: The config keys in which the shards of one evaluation differ.
SHARD_KEYS = ("experiment.first_index", "experiment.n_trials", "n_configs", "first_config", "output_dir")


def _identity(cfg: DictConfig) -> str:
    """What a job's config evaluated, less its trial range."""
    cfg = cfg.copy()
    for key in SHARD_KEYS:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if node is not None and leaf in node:
            node.pop(leaf)
    return json.dumps(OmegaConf.to_container(cfg), sort_keys=True)


def _report_config(cfg: DictConfig, job: Path) -> DictConfig:
    """The job's report config, if its ``_target_`` is one of kpflow's reports: a config read from disk must not
    name any other callable, since instantiating it would call it."""
    report = cfg.experiment.trial.report
    target = str(report.get("_target_", ""))
    if not target.startswith(REPORTS):
        raise ValueError(f"{job / 'config.yaml'}: experiment.trial.report names {target!r}, not one of kpflow's reports ({REPORTS}*)")
    return report


def pool_shards(jobs: list[Path]) -> str | None:
    """The pooled tables of the jobs that split one evaluation by trial ranges (module docstring); None if none did."""
    groups: dict[str, list[tuple[Path, DictConfig]]] = {}
    for job in jobs:
        cfg = read_yaml(job / "config.yaml") if (job / "config.yaml").is_file() else None
        if cfg is not None and OmegaConf.select(cfg, "experiment.trial.report") is not None:  # a trial-loop evaluation
            groups.setdefault(_identity(cfg), []).append((job, cfg))
    parts = []
    for shards in (g for g in groups.values() if len(g) > 1):
        results = [json.loads((job / "results.json").read_text()) for job, _ in shards]
        if any("axes" not in r for r in results):
            continue
        axes = results[0]["axes"]
        trials = [trial_from_record(record, axes) for r in results for record in r["trials"]]
        if len({(t.condition, t.index, *t.variant.values()) for t in trials}) < len(trials):
            continue  # a trial ran twice: repeats, not shards of one evaluation
        cells: dict[tuple, list] = {}
        for t in trials:
            cells.setdefault((t.condition, *t.variant.values()), []).append(t)
        report = instantiate(_report_config(shards[0][1], shards[0][0]))
        summaries = {cell: report.summarise(members) for cell, members in cells.items()}
        names = ", ".join(job.name for job, _ in shards)
        parts.append(f"## Pooled: jobs {names} (one evaluation split by trial ranges, {len(trials)} trials)\n\n" + report.table(summaries, axes))
    return "\n".join(parts) if parts else None


def combine_tables(sweep_dir: str | Path) -> Path | None:
    """Concatenate the table rows of every ``<sweep_dir>/<job>/results.md`` (header once); None if there are none."""
    sweep_dir = Path(sweep_dir)
    jobs = sorted((p for p in sweep_dir.glob("*/results.md")), key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)
    header, rows = [], []
    for path in jobs:
        lines = [line for line in path.read_text().splitlines() if line.startswith("|")]
        if not lines:
            continue
        header = header or lines[:2]
        rows += lines[2:] if lines[:2] == header else lines
    if not rows:
        return None
    pooled = pool_shards([p.parent for p in jobs])
    text = "# Combined results\n\n" + "\n".join(header + rows) + "\n" + (f"\n{pooled}" if pooled else "")
    return write_text(sweep_dir / "table.md", text)


class CombineTables(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        path = combine_tables(config.hydra.sweep.dir)
        if path is not None:
            print(f"combined table: {path}\n{path.read_text()}")
