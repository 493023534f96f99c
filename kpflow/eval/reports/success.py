"""Any task's closed-loop policy report: success with its 95% interval, failure reasons and the steps taken, per
condition (the Gymnasium tasks' ``experiment=gym_policy``; the robosuite tasks' report builds on it)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from kpflow.core.task import TrialResult
from kpflow.eval.stats import rate_cell, success_cells, success_summary


def step_limits(trial) -> str:
    """The control steps an episode of ``trial`` may take: one number, or each condition's."""
    limits = trial.describe()["max_steps"]
    if not isinstance(limits, dict):
        return str(limits)
    return (
        str(next(iter(set(limits.values()))))
        if len(set(limits.values())) == 1
        else ", ".join(f"{c}: {n}" for c, n in limits.items())
    )


def success_within(trials: list[TrialResult], steps: int) -> dict:
    """:func:`~kpflow.eval.stats.success_summary` of ``trials`` had they been stopped after ``steps`` control steps:
    an episode that succeeded later fails with ``"time limit"``. One run gives the rate at a shorter horizon, as
    another protocol counts it (MimicGen's 400 steps beside kpflow's 500), because an episode ends at its success."""
    rows = []
    for t in trials:
        success = bool(t.success and t.scores["steps"] <= steps)
        rows.append({"success": success, "failure": None if success else (t.failure or "time limit")})
    return success_summary(rows)


class SuccessReport:
    """Success [95% interval], failure reasons and the median steps to success, one row per condition; ``within``:
    shorter horizons (control steps) whose success is reported beside it (:func:`success_within`; in the summary as
    ``success_within_<steps>`` and its interval ``ci_within_<steps>``)."""

    fps = 10

    def __init__(self, within: Sequence[int] = ()):
        self.within = tuple(sorted({int(h) for h in within}))
        if any(h < 1 for h in self.within):
            raise ValueError(f"within must name horizons of at least 1 control step, got {list(within)}")

    def summarise(self, trials: list[TrialResult]) -> dict:
        rows = [{"success": t.success, "failure": t.failure} for t in trials]
        done = [t.scores["steps"] for t in trials if t.success]
        out = {**success_summary(rows), "steps_median": float(np.median(done)) if done else float("nan")}
        for h in self.within:
            short = success_within(trials, h)
            out[f"success_within_{h}"], out[f"ci_within_{h}"] = short["success"], short["ci"]
            out[f"successes_within_{h}"] = short["successes"]
        return out

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        within = "".join(f" within {h} steps [95% CI] |" for h in self.within)
        rows = [f"| variant | {' | '.join(axes)} | episodes | success [95% CI] | failure reasons |{within} steps to success, median |",
                "|---|" + "---|" * len(axes) + "---|---|---|" + "---|" * len(self.within) + "---|"]  # fmt: skip
        for cell, s in summaries.items():
            steps = "-" if np.isnan(s["steps_median"]) else f"{s['steps_median']:.0f}"  # no success, no median
            short = "".join(
                f" {rate_cell(s[f'successes_within_{h}'], s['trials'], s[f'ci_within_{h}'])} |" for h in self.within
            )
            rows.append(f"| {' | '.join(cell)} | {s['trials']} | {success_cells(s)} |{short} {steps} |")
        return "\n".join(rows) + "\n"

    def within_note(self) -> str:
        """The header's words on the shorter horizons (empty without them)."""
        return f"; success within {', '.join(map(str, self.within))} steps too" if self.within else ""

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return (f"# {trial.name}: {trial.policy_name} in closed loop\n\n"
                f"Episodes per condition: {n_trials}; at most {step_limits(trial)} control steps; the env's own success test"
                f"{self.within_note()}.\n\n")  # fmt: skip

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        return [(t, True) for t in trials if t.index == trials[0].index][:videos]

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        return []
