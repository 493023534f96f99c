"""The robosuite benchmark tasks' policy report: success with its 95% interval and the steps taken, per variant."""

from __future__ import annotations

from .success import SuccessReport, step_limits


class SuiteReport(SuccessReport):
    """The robosuite benchmark tasks' report (their variants, robosuite's success check); videos in real time (a frame
    per control step at 20 Hz)."""

    fps = 20

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return (f"# {trial.name}: {trial.policy_name} in closed loop\n\n"
                f"Episodes per variant: {n_trials}; at most {step_limits(trial)} control steps; robosuite's own success check"
                f"{self.within_note()}.\n\n")  # fmt: skip
