"""The robosuite benchmark tasks' policy report: success with its 95% interval and the steps taken, per variant; on
a perception other than the simulator's, where its keypoints went wrong, stage by stage, in the episodes that failed
against those that succeeded (the ``error_<stage>_mm`` scores of :mod:`kpflow.tasks.suite.perception_errors`)."""

from __future__ import annotations

import re

import numpy as np

from kpflow.core.task import TrialResult

from .success import SuccessReport, step_limits

_ERROR = re.compile(r"^error_(\w+)_mm$")
_FAILED = re.compile(r"^error_(\w+)_mm_failed$")


def stage_errors(trials: list[TrialResult]) -> list[str]:
    """The stages whose keypoint errors ``trials`` scored (``error_<stage>_mm``), in the order first seen."""
    return list(dict.fromkeys(m.group(1) for t in trials for key in t.scores if (m := _ERROR.match(key))))


class SuiteReport(SuccessReport):
    """The robosuite benchmark tasks' report (their variants, robosuite's success check); videos in real time (a frame
    per control step at 20 Hz). With perception errors scored, the summary holds ``error_<stage>_mm_<outcome>``:
    the median over the ``failed`` / ``succeeded`` episodes of each one's largest error in that stage (NaN: no such
    episode), and the table a second one with them."""

    fps = 20

    def summarise(self, trials: list[TrialResult]) -> dict:
        out = super().summarise(trials)
        for stage in stage_errors(trials):
            key = f"error_{stage}_mm"
            for outcome, success in (("failed", False), ("succeeded", True)):
                values = [t.scores[key] for t in trials if t.success == success and key in t.scores]
                out[f"{key}_{outcome}"] = float(np.median(values)) if values else float("nan")
        return out

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        text = super().table(summaries, axes)
        stages = list(dict.fromkeys(m.group(1) for s in summaries.values() for k in s if (m := _FAILED.match(k))))
        if not stages:
            return text
        columns = ["variant", *axes, *stages]
        rows = ["", "Perceived keypoints against the simulator's, by stage: the median over episodes of each one's largest "
                "error (mm), failed / succeeded episodes (kpflow/tasks/suite/perception_errors.py).", "",
                f"| {' | '.join(columns)} |", "|" + "---|" * len(columns)]  # fmt: skip

        def cell(s: dict, stage: str) -> str:
            values = [s.get(f"error_{stage}_mm_{o}", float("nan")) for o in ("failed", "succeeded")]
            return " / ".join("-" if np.isnan(v) else f"{v:.1f}" for v in values)

        for key, s in summaries.items():
            rows.append(f"| {' | '.join(key)} | {' | '.join(cell(s, st) for st in stages)} |")
        return text + "\n".join(rows) + "\n"

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return (f"# {trial.name}: {trial.policy_name} in closed loop\n\n"
                f"Episodes per variant: {n_trials}; at most {step_limits(trial)} control steps; robosuite's own success check"
                f"{self.within_note()}.\n\n")  # fmt: skip
