"""The one trial loop: any task x policy x map grid, in parallel workers, into the usual results.

A :class:`Trial` knows how to run one trial of one task: an open-loop transport of a recorded demonstration for the
robosuite tasks (:class:`~kpflow.eval.demo_transport_trial.DemoTransportTrial`), a closed-loop policy episode on a
Gymnasium task, Push-T's and the robosuite benchmark tasks' too (:class:`~kpflow.eval.policy_trial.PolicyTrial`). Its ``variants`` are the grid's other axes (keypoint
source and map, or policy), and its ``report`` (:mod:`kpflow.eval.reports`) summarises, tabulates and draws.

For each condition, variant and trial index (``first_index``, ``first_index + 1``, ...: the same scenes for every
variant), :meth:`Trial.run` runs in a worker process set up once by :meth:`Trial.setup`. Afterwards the report
picks showcase trials (:meth:`~kpflow.eval.reports.Report.showcase`), which are re-run deterministically in this
process for its figures, the first ones filmed.

Writes ``results.json`` (what the trial ran on, the summary per cell, every trial with its failure reason and
scores, figures, videos), ``results.md`` (the report's table) and the report's figures and mp4s into the run folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

from kpflow.core.task import TrialResult
from kpflow.eval.parallel import map_jobs
from kpflow.utils.io import write_json, write_text
from kpflow.utils.video import write_video

#: ``conditions`` value meaning "the trial's default conditions" (Push-T: its three splits)
ALL = "all"


class Trial(Protocol):
    """One kind of trial of one task, run by :func:`run_trials`."""

    name: str  #: the task's name (``results.json``'s ``task``)
    conditions: tuple[str, ...]  #: every condition it can run
    default_conditions: tuple[str, ...]  #: the conditions of ``conditions: all``
    report: Any  #: its :class:`~kpflow.eval.reports.Report`

    def variants(self) -> list[dict[str, str]]:
        """The grid's cells within one condition: axis -> option (e.g. ``{"keypoints": "sift", "map": "gp"}``)."""

    def setup(self) -> None:
        """Build this process's simulator and anything else a worker needs (called once per worker)."""

    def run(
        self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None
    ) -> TrialResult:
        """Trial ``index`` of ``condition`` in ``variant``; video frames are appended to ``frames`` when given."""

    def describe(self) -> dict:
        """What every trial ran on (the source demonstration, the policy), for ``results.json``."""


_TRIAL: list = []  # this process's set-up trial (a worker's, or the parent's for workers=1 and the showcase)


def _setup(trial: Trial) -> None:
    trial.setup()
    _TRIAL[:] = [trial]


def _run(job: tuple) -> dict:
    condition, index, variant, seed = job
    return _TRIAL[0].run(condition, index, variant, seed).record()


def _per_condition(value: int | Mapping[str, int], condition: str, what: str) -> int:
    if isinstance(value, Mapping):
        if condition not in value:
            raise ValueError(f"{what} names no value for condition {condition!r} (it has {sorted(value)})")
        value = value[condition]
    return int(value)


def trial_from_record(record: dict, axes: list[str]) -> TrialResult:
    """The :class:`TrialResult` of one of ``results.json``'s ``trials`` records (``axes``: the variant's keys)."""
    fixed = {"condition", "index", "scene", "success", "failure", *axes}
    scores = {k: v for k, v in record.items() if k not in fixed}
    variant = {a: record[a] for a in axes}
    return TrialResult(
        record["condition"], record["index"], variant, record["scene"], record["success"], record["failure"], scores
    )


def video_name(trial: TrialResult) -> str:
    """``<condition>_<variant options>_<index>_<outcome>.mp4``."""
    outcome = "success" if trial.success else str(trial.failure).replace(" ", "_")
    return "_".join([trial.condition, *trial.variant.values(), f"{trial.index:02d}", outcome]) + ".mp4"


def cell_summary(results: dict, condition: str, **variant: str) -> dict:
    """The summary row of ``condition`` (and ``variant``'s options, when the grid has several cells) in a
    :func:`run_trials` result."""
    rows = [
        s for s in results["summary"] if s["condition"] == condition and all(s.get(k) == v for k, v in variant.items())
    ]
    if len(rows) != 1:
        raise KeyError(
            f"{len(rows)} summary rows match condition {condition!r} and {variant}; give the variant's options"
        )
    return rows[0]


def run_trials(
    output_dir: str | Path,
    trial: Trial,
    conditions: str | Sequence[str] | None = None,
    n_trials: int | Mapping[str, int] = 50,
    first_index: int | Mapping[str, int] = 0,
    seed: int = 0,
    workers: int = 2,
    videos: int = 1,
    progress: bool = True,
) -> dict:
    """Run every condition x variant x trial of ``trial`` (module docstring) into ``output_dir``.

    ``conditions``: a list, one condition, or ``"all"``/None for the trial's default conditions. ``n_trials`` and
    ``first_index``: one number, or one per condition (Push-T's ``standard`` protocol runs 500 episodes from seed
    100000). ``videos``: how many showcase trials to film. Returns what ``results.json`` holds, with a flat
    ``metrics`` dict (``<condition>/<options>/<figure>``) for loggers, plus ``table``: the text of ``results.md``.
    """
    if conditions is None or conditions == ALL:
        conditions = list(trial.default_conditions)
    elif isinstance(conditions, str):
        conditions = [conditions]
    conditions = list(conditions)
    if not conditions or any(c not in trial.conditions for c in conditions):
        raise ValueError(f"unknown condition in {conditions}; choose {ALL!r} or from {trial.conditions}")
    counts = {
        c: (_per_condition(first_index, c, "first_index"), _per_condition(n_trials, c, "n_trials")) for c in conditions
    }
    if any(n < 1 for _, n in counts.values()) or workers < 1 or videos < 0:
        raise ValueError(f"n_trials and workers must be >= 1 and videos >= 0, got {n_trials}, {workers}, {videos}")
    variants = trial.variants()
    if not variants:
        raise ValueError(
            f"{trial.name}: the trial has no variant to run (give at least one keypoint source and one map)"
        )
    axes = list(variants[0])
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)

    jobs = [(c, first + i, v, seed) for c in conditions for v in variants for first, n in [counts[c]] for i in range(n)]
    records = map_jobs(
        _run,
        jobs,
        workers,
        initializer=_setup,
        initargs=(trial,),
        desc=f"{trial.name} trials",
        unit="trial",
        progress=progress,
    )
    trials = [trial_from_record(r, axes) for r in records]
    report = trial.report
    summaries = {
        (c, *v.values()): report.summarise([t for t in trials if t.condition == c and t.variant == v])
        for c in conditions
        for v in variants
    }

    if not _TRIAL or _TRIAL[0] is not trial:  # this process has not set up this run's trial yet
        _setup(trial)
    showcase, video_paths = [], []
    for chosen, film in report.showcase(trials, videos):
        frames = [] if film else None
        again = trial.run(chosen.condition, chosen.index, chosen.variant, seed, frames)
        showcase.append(again)
        if frames:
            video_paths.append(str(write_video(frames, out / video_name(again), fps=getattr(report, "fps", 20))))
    figures = report.figures(out, trial, trials, showcase)

    results = {
        "task": trial.name,
        **trial.describe(),
        "axes": axes,
        "summary": [{"condition": cell[0], **dict(zip(axes, cell[1:])), **s} for cell, s in summaries.items()],
        "trials": records,
        "figures": figures,
        "videos": video_paths,
    }
    results["metrics"] = {
        "/".join((*cell, k)): v for cell, s in summaries.items() for k, v in s.items() if isinstance(v, float)
    }
    write_json(out / "results.json", results)
    table = report.header(trial, {c: n for c, (_, n) in counts.items()}) + report.table(summaries, axes)
    write_text(out / "results.md", table)
    return {**results, "table": table}
