"""A Hydra callback that joins the tables of a multirun sweep into one: ``<sweep dir>/table.md``.

Every job's rows come first. Jobs that split one evaluation by trial ranges (a sweep over
``first_config`` or ``experiment.first_index.<condition>``, with ``n_configs`` or ``experiment.n_trials`` the shard
size: configs equal but for those,
and no trial run twice) are then pooled: their trials are summarised again together by the evaluation's own report,
so the pooled row's success rate and interval are those of one run over all the trials.

Only the jobs of this sweep count: a ``results.md`` that was in the sweep folder before the sweep began (a former
run's, or one planted there) is left out. And a job's ``config.yaml`` is data, never code: the pooled table's report
is looked up by name among kpflow's reports and given plain options, so no ``_target_`` in the file, at any depth, is
ever instantiated (:func:`build_report`).
"""

from __future__ import annotations

import importlib
import json
import pkgutil
from pathlib import Path
from typing import Any, Mapping

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

import kpflow.eval.reports as reports
from kpflow.eval.trials import trial_from_record
from kpflow.utils.formats import read_yaml
from kpflow.utils.io import write_text

#: Where the reports a pooled table may build live.
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


def _report_class(target: str, where: str) -> type:
    """The report class ``target`` names: a class defined in one of the modules of :mod:`kpflow.eval.reports`, looked
    up by name (no other module is imported, nothing named is called); ``ValueError`` naming ``where`` otherwise."""
    module_name, _, class_name = target.removeprefix(REPORTS).rpartition(".")
    known = {m.name for m in pkgutil.iter_modules(reports.__path__)}
    if not target.startswith(REPORTS) or module_name not in known:
        raise ValueError(
            f"{where}: experiment.trial.report names {target!r}, not one of kpflow's reports ({REPORTS}<{'|'.join(sorted(known))}>.<Class>)"
        )
    module = importlib.import_module(REPORTS + module_name)
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and cls.__module__ == module.__name__ and class_name.endswith("Report")):
        raise ValueError(
            f"{where}: experiment.trial.report names {target!r}, which is not a report class of {module.__name__}"
        )
    return cls


def _plain_options(node: Any, where: str, key: str) -> Any:
    """``node`` (a report's options, plain data) checked to name nothing to build: a ``_target_`` (or any key
    starting with ``_``, Hydra's instructions) at any depth is refused, naming its key."""
    if isinstance(node, Mapping):
        for name, value in node.items():
            if str(name).startswith("_"):
                raise ValueError(
                    f"{where}: {key}.{name} is refused: a config read from disk may not ask for anything to be built or called"
                )
            _plain_options(value, where, f"{key}.{name}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            _plain_options(value, where, f"{key}[{i}]")
    return node


def build_report(cfg: DictConfig, job: Path):
    """The report a job's config (read from disk) names, built without instantiating anything from the file: its
    ``_target_`` is looked up among kpflow's reports by name (:func:`_report_class`) and called with the plain
    options beside it, of which none may name a target (:func:`_plain_options`)."""
    where = str(job / "config.yaml")
    try:
        options = OmegaConf.to_container(cfg.experiment.trial.report, resolve=True)
    except Exception as e:  # an interpolation that does not resolve outside the run
        raise ValueError(
            f"{where}: experiment.trial.report does not read as plain options ({type(e).__name__}: {e})"
        ) from None
    if not isinstance(options, dict):
        raise ValueError(
            f"{where}: experiment.trial.report must be a mapping with a _target_, not {type(options).__name__}"
        )
    cls = _report_class(str(options.pop("_target_", "")), where)
    try:
        return cls(**_plain_options(options, where, "experiment.trial.report"))
    except TypeError as e:
        raise ValueError(f"{where}: experiment.trial.report's options do not build {cls.__name__} ({e})") from None


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
        report = build_report(shards[0][1], shards[0][0])
        summaries = {cell: report.summarise(members) for cell, members in cells.items()}
        names = ", ".join(job.name for job, _ in shards)
        parts.append(
            f"## Pooled: jobs {names} (one evaluation split by trial ranges, {len(trials)} trials)\n\n"
            + report.table(summaries, axes)
        )
    return "\n".join(parts) if parts else None


def results_files(sweep_dir: str | Path) -> dict[str, tuple[int, int]]:
    """The ``<sweep_dir>/<job>/results.md`` present now, each with its inode and modification time: what was there
    before a sweep began, so that :func:`combine_tables` leaves it out."""
    stats = {str(p): p.stat() for p in Path(sweep_dir).glob("*/results.md") if p.is_file()}
    return {p: (st.st_ino, st.st_mtime_ns) for p, st in stats.items()}


def combine_tables(sweep_dir: str | Path, before: Mapping[str, tuple[int, int]] | None = None) -> Path | None:
    """Concatenate the table rows of every ``<sweep_dir>/<job>/results.md`` (header once) written since ``before``
    (:func:`results_files` when the sweep began; None: all of them) and pool the shards among them; None if there
    are none. Tables a former run left in the folder are not this sweep's and are left out."""
    sweep_dir = Path(sweep_dir)
    before = before or {}
    written = [p for p, stamp in results_files(sweep_dir).items() if before.get(p) != stamp]
    jobs = sorted(
        map(Path, written),
        key=lambda p: (0, int(p.parent.name), "") if p.parent.name.isdigit() else (1, 0, p.parent.name),
    )
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
    """Writes ``<sweep dir>/table.md`` at the end of a multirun from the tables its jobs wrote (module docstring)."""

    def __init__(self) -> None:
        self.before: dict[str, tuple[int, int]] = {}

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        self.before = results_files(config.hydra.sweep.dir)

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        path = combine_tables(config.hydra.sweep.dir, self.before)
        if path is not None:
            print(f"combined table: {path}\n{path.read_text()}")
