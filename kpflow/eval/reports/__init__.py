"""What each robosuite task scores and draws, beside the one trial loop (:mod:`kpflow.eval.trials`).

A report turns a trial's outcome into ``scores`` (plain numbers and lists for ``results.json``), groups of trials
into a summary and a markdown table, and a few re-run trials into figures. One report per task, one file each.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from kpflow.tasks.base import Demonstration, Execution, Trajectory, TrialResult


class Report(Protocol):
    #: showcase trials per condition and keypoint source that :meth:`figures` draws (re-run with the first map)
    examples: int

    def scores(self, env, source: Demonstration, view: Any, trajectory: Trajectory | None, execution: Execution | None) -> dict:
        """The trial's scores (``trajectory`` and ``execution`` are None when no keypoints were found)."""

    def summarise(self, trials: list[TrialResult]) -> dict:
        """Success with its interval and the task's own figures of merit for one cell of the grid."""

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        """The markdown table: one row per (condition, *variant) cell."""

    def header(self, task, source: Demonstration, n_trials: int) -> str:
        """The first lines of ``results.md``."""

    def figures(self, out: Path, source: Demonstration, showcase: list[TrialResult]) -> list[str]:
        """Write the figures of the showcase trials into ``out``; their file names."""
