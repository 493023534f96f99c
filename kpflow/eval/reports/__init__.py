"""What each task scores, summarises and draws, beside the one trial loop (:mod:`kpflow.eval.trials`).

A report groups trials into a summary and a markdown table, picks the showcase trials that the loop re-runs (and
films), and draws figures from them. The robosuite tasks' reports also turn a trial's outcome into ``scores``
(:class:`ArmReport`). One report per task, one file each.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any, Callable, Protocol

from kpflow.core.task import Demonstration, Execution, TrialResult
from kpflow.trajectory import Trajectory


class Report(Protocol):
    def summarise(self, trials: list[TrialResult]) -> dict:
        """Success with its interval and the task's own figures of merit for one cell of the grid."""

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        """The markdown table: one row per (condition, *variant) cell."""

    def header(self, trial, n_trials: dict[str, int]) -> str:
        """The first lines of ``results.md`` (``n_trials``: condition -> trials run)."""

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        """The trials to re-run for the figures, each with whether to film it (at most ``videos`` per cell)."""

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        """Write the figures of the run (``trials``: every result; ``showcase``: the re-run ones, with their
        artefacts) into ``out``; their file names."""


class ArmReport(Report, Protocol):
    #: showcase trials per condition and keypoint source that :meth:`figures` draws (re-run with the first map)
    examples: int

    def scores(
        self, env, source: Demonstration, view: Any, trajectory: Trajectory | None, execution: Execution | None
    ) -> dict:
        """The trial's scores (``trajectory`` and ``execution`` are None when no keypoints were found)."""


def first_trials(
    trials: list[TrialResult], n: int, videos: int, keep: Callable[[TrialResult], bool] = lambda t: True
) -> list[tuple[TrialResult, bool]]:
    """The first ``n`` trials that ``keep`` accepts of every (condition, variant) cell, the first ``videos`` of each
    filmed."""
    seen: Counter = Counter()
    chosen = []
    for t in trials:
        cell = (t.condition, *t.variant.values())
        if keep(t) and seen[cell] < n:
            chosen.append((t, seen[cell] < videos))
            seen[cell] += 1
    return chosen


def first_map_trials(trials: list[TrialResult], examples: int, videos: int) -> list[tuple[TrialResult, bool]]:
    """The robosuite tasks' showcase: the first ``max(examples, videos)`` trials of every condition and keypoint
    source with the first map, the first ``videos`` filmed."""
    first_map = trials[0].variant["map"] if trials else None
    return first_trials(trials, max(examples, videos), videos, lambda t: t.variant["map"] == first_map)
