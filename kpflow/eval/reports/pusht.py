"""Push-T's summary (success at coverage 0.85 and 0.95 with 95% Wilson intervals, coverage, steps to success, the
standard score, latency), table and success figure; its showcase is the first successes and failures of each split."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kpflow.core.task import TrialResult
from kpflow.eval import plots
from kpflow.eval.reports import first_trials
from kpflow.eval.stats import wilson_interval
from kpflow.utils.io import save_figure


class PushTReport:
    fps = 10  # the env's control rate

    def summarise(self, trials: list[TrialResult]) -> dict:
        """Success rates with 95% Wilson intervals, coverage, steps to success, the standard score
        (mean of clip(max coverage / 0.95, 0, 1)) and the median latency of one cell's episodes."""
        n = len(trials)
        out = {"episodes": n}
        for th in ("085", "095"):
            hit = [t.success if th == "095" else t.scores["success_085"] for t in trials]
            steps = [t.scores[f"steps_{th}"] for t, h in zip(trials, hit) if h]
            out[f"success_{th}"] = sum(hit) / n
            out[f"ci_{th}"] = wilson_interval(sum(hit), n)
            out[f"steps_{th}"] = float(np.mean(steps)) if steps else float("nan")
        out["final_coverage"] = float(np.mean([t.scores["final_coverage"] for t in trials]))
        out["max_coverage"] = float(np.mean([t.scores["max_coverage"] for t in trials]))
        out["score"] = float(np.mean([min(t.scores["max_coverage"] / 0.95, 1.0) for t in trials]))
        out["latency_ms"] = float(np.nanmedian([t.scores["latency_ms"] for t in trials]))
        return out

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        rows = [
            "| policy | split | episodes | success @0.85 [95% CI] | success @0.95 [95% CI] | mean final / max coverage"
            " | steps to 0.85 / 0.95 | standard score | latency ms (median) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for (split, *options), s in summaries.items():
            ci85, ci95 = s["ci_085"], s["ci_095"]
            rows.append(
                f"| {' '.join(options)} | {split} | {s['episodes']} | {100 * s['success_085']:.1f}% [{100 * ci85[0]:.1f}, {100 * ci85[1]:.1f}]"
                f" | {100 * s['success_095']:.1f}% [{100 * ci95[0]:.1f}, {100 * ci95[1]:.1f}]"
                f" | {s['final_coverage']:.3f} / {s['max_coverage']:.3f} | {s['steps_085']:.0f} / {s['steps_095']:.0f}"
                f" | {s['score']:.3f} | {s['latency_ms']:.2f} |"
            )
        return "\n".join(rows) + "\n"

    def header(self, trial, n_trials: dict[str, int]) -> str:
        return f"# Push-T evaluation: {trial.policy_name}\n\n"

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        """The first ``videos`` successes and the first ``videos`` failures of each split, all filmed."""
        successes = first_trials(trials, videos, videos, lambda t: t.success)
        failures = first_trials(trials, videos, videos, lambda t: not t.success)
        return [
            pick
            for condition in dict.fromkeys(t.condition for t in trials)
            for pick in successes + failures
            if pick[0].condition == condition
        ]

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        """``success.png``: success per split at both thresholds with 95% intervals, and the histogram of each
        episode's maximum coverage."""
        splits = list(dict.fromkeys(t.condition for t in trials))
        summaries = {p: self.summarise([t for t in trials if t.condition == p]) for p in splits}
        fig, axes = plots.new_figure(1, 2, size=4.4)
        ax, bx = axes[0]
        for a in (ax, bx):
            a.set_aspect("auto")
            a.tick_params(labelsize=10)
        x = np.arange(len(splits))
        for offset, th in ((-0.18, "085"), (0.18, "095")):
            rate = np.array([summaries[p][f"success_{th}"] for p in splits])
            ci = np.array([summaries[p][f"ci_{th}"] for p in splits])
            ax.bar(x + offset, 100 * rate, 0.34, label=f"coverage >= 0.{th[1:]}")
            ax.errorbar(x + offset, 100 * rate, yerr=100 * np.abs(ci.T - rate), fmt="none", ecolor="k", capsize=3)
        ax.set_xticks(x, [p.replace("_", "\n") for p in splits])
        ax.set_ylim(0, 105)
        ax.set_ylabel("success (%) with 95% CI", fontsize=11)
        ax.set_title(trial.policy_name, fontsize=12)
        ax.grid(axis="y", alpha=0.3)
        for p in splits:
            bx.hist(
                [t.scores["max_coverage"] for t in trials if t.condition == p],
                bins=20,
                range=(0, 1),
                alpha=0.6,
                label=p,
            )
        bx.set_xlabel("max coverage in the episode", fontsize=11)
        bx.set_ylabel("episodes", fontsize=11)
        bx.set_title("max coverage per episode", fontsize=12)
        # the legends under the axes, where they cover no bar whatever the rates and coverages
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, fontsize=10, frameon=False)
        bx.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=min(len(splits), 3), fontsize=10, frameon=False)
        fig.tight_layout()
        save_figure(fig, out / "success.png", dpi=110, bbox_inches="tight")
        plots.close(fig)
        return ["success.png"]
