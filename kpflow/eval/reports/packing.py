"""Packing's scores (perception error of the object box, the arm's margins, the map's uncertainty), table and
trajectory figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from kpflow.core.task import Demonstration, Execution, TrialResult
from kpflow.eval import plots
from kpflow.eval.reports import first_map_trials
from kpflow.eval.stats import success_cells, success_summary
from kpflow.trajectory import Trajectory
from kpflow.utils.io import save_figure


def box_corner_error(corners: np.ndarray, truth: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """Mean distance (m) between estimated box corners ``[8, 3]`` and the true box ``(centre, rotation, half)``,
    corners matched one to one (Hungarian assignment, scipy)."""
    centre, rot, half = truth
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    true = centre + (signs * half) @ rot.T
    d = np.linalg.norm(np.asarray(corners)[:, None] - true[None], axis=-1)
    rows, cols = linear_sum_assignment(d)
    return float(d[rows, cols].mean())


class PackingReport:
    examples = 2

    def scores(
        self, env, source: Demonstration, view, trajectory: Trajectory | None, execution: Execution | None
    ) -> dict:
        return {
            "min_singular_value": execution.min_singular_value,
            "max_tracking_error": float(execution.tracking_error.max()),
            "box_error_mm": 1e3 * box_corner_error(view.box["corners"], view.true_box),
            "max_std": float(trajectory.std.max()),
        }

    def summarise(self, trials: list[TrialResult]) -> dict:
        rows = [{"success": t.success, "failure": t.failure} for t in trials]
        return {
            **success_summary(rows),
            "box_error_mm_median": float(np.median([t.scores["box_error_mm"] for t in trials])),
        }

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        names = " | ".join(axes)
        rows = [
            f"| condition | {names} | trials | success [95% CI] | failure reasons | object box error, median (mm) |",
            "|---|" + "---|" * len(axes) + "---|---|---|---|",
        ]
        for cell, s in summaries.items():
            rows.append(f"| {' | '.join(cell)} | {s['trials']} | {success_cells(s)} | {s['box_error_mm_median']:.1f} |")
        return "\n".join(rows) + "\n"

    def header(self, trial, n_trials: dict[str, int]) -> str:
        source = trial.source
        return (
            "# Packing: one demonstration transported to new scenes\n\n"
            f"Source demonstration ({source.scene.object_type}) succeeded in its own scene: {source.execution.success}.\n\n"
        )

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        return first_map_trials(trials, self.examples, videos)

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        """``trajectories.png``: top and side views of the source path and keypoints, and the transported paths
        (solid), the measured tip (dotted) and the target keypoints of the showcase trials."""
        source = trial.source
        fig, axes = plots.new_figure(1, 2, size=4.2)
        top, side = axes[0]
        for ax, (i, j), name in ((top, (0, 1), "top view (x, y)"), (side, (0, 2), "side view (x, z)")):
            ax.set_aspect("equal")
            ax.set_title(name)
            pos, kp = source.trajectory.positions, source.observation.keypoints
            ax.plot(pos[:, i], pos[:, j], "k-", lw=2, label="source")
            ax.scatter(kp[:, i], kp[:, j], c="k", s=10)
            for n, shown in enumerate(t for t in showcase if t.index < self.examples):
                colour = f"C{n}"
                p, k, tip = (
                    shown.artefacts["trajectory"].positions,
                    shown.artefacts["keypoints"].target,
                    shown.artefacts["execution"].tip,
                )
                label = f"{shown.scene['object_type']} ({'ok' if shown.success else shown.failure})"
                ax.plot(p[:, i], p[:, j], "-", color=colour, lw=1.2, label=label)
                ax.plot(tip[:, i], tip[:, j], ":", color=colour, lw=1)
                ax.scatter(k[:, i], k[:, j], color=colour, s=8, marker="x")
        top.legend(fontsize=6, loc="lower right")
        save_figure(fig, out / "trajectories.png", dpi=120)
        plots.close(fig)
        return ["trajectories.png"]
