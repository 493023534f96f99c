"""Any task's closed-loop policy report: success with its 95% interval, failure reasons and the steps taken, per
condition (the Gymnasium tasks' ``experiment=gym_policy``; the robosuite tasks' report builds on it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kpflow.eval.stats import success_cells, success_summary
from kpflow.tasks.base import TrialResult


def step_limits(trial) -> str:
    """The control steps an episode of ``trial`` may take: one number, or each condition's."""
    limits = trial.describe()["max_steps"]
    if not isinstance(limits, dict):
        return str(limits)
    return str(next(iter(set(limits.values())))) if len(set(limits.values())) == 1 else ", ".join(f"{c}: {n}" for c, n in limits.items())


class SuccessReport:
    """Success [95% interval], failure reasons and the median steps to success, one row per condition."""

    fps = 10

    def summarise(self, trials: list[TrialResult]) -> dict:
        rows = [{"success": t.success, "failure": t.failure} for t in trials]
        done = [t.scores["steps"] for t in trials if t.success]
        return {**success_summary(rows), "steps_median": float(np.median(done)) if done else float("nan")}

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        rows = [f"| variant | {' | '.join(axes)} | episodes | success [95% CI] | failure reasons | steps to success, median |",
                "|---|" + "---|" * len(axes) + "---|---|---|---|"]  # fmt: skip
        for cell, s in summaries.items():
            steps = "-" if np.isnan(s["steps_median"]) else f"{s['steps_median']:.0f}"  # no success, no median
            rows.append(f"| {' | '.join(cell)} | {s['trials']} | {success_cells(s)} | {steps} |")
        return "\n".join(rows) + "\n"

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return (f"# {trial.name}: {trial.policy_name} in closed loop\n\n"
                f"Episodes per condition: {n_trials}; at most {step_limits(trial)} control steps; the env's own success test.\n\n")  # fmt: skip

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        return [(t, True) for t in trials if t.index == trials[0].index][:videos]

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        return []
