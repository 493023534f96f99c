"""The robosuite benchmark tasks' policy report: success with its 95% interval and the steps taken, per variant."""

from __future__ import annotations

from .success import SuccessReport


class SuiteReport(SuccessReport):
    """The robosuite benchmark tasks' report (their variants, robosuite's success check)."""

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return (f"# {trial.name}: {trial.policy_name} in closed loop\n\n"
                f"Episodes per variant: {n_trials}; at most {trial.max_steps} control steps; robosuite's own success check.\n\n")  # fmt: skip
