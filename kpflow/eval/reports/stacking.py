"""Stacking's scores (the 3-D error of the correspondences against the simulator's truth, the transported grasp's
orientation and position error, the placed block's yaw error), table and match figures.

The grasp error compares the transported grasp (the first ``seal`` step) with the source's grasp carried by the
cheese's true motion; a cup turned by a half turn counts as the same grasp of a box.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kpflow.core.task import Demonstration, Execution, TrialResult
from kpflow.eval import plots
from kpflow.eval.reports import first_map_trials
from kpflow.eval.stats import success_cells, success_summary
from kpflow.geometry.angles import yaw_of
from kpflow.tasks.stacking.demonstrator import nearest_half_turn
from kpflow.tasks.stacking.keypoints import true_targets
from kpflow.tasks.stacking.objects import BLOCKS, CHEESE, LETTUCE
from kpflow.trajectory import Trajectory
from kpflow.utils.io import save_figure

HALF_TURN = Rotation.from_euler("z", np.pi)


def grasp_errors(source: Demonstration, moved: Trajectory, poses_now: dict) -> tuple[float, float]:
    """Orientation error (deg) and position error (mm) of the transported grasp against the source's grasp carried
    by the cheese's true motion (``poses_now``: name -> (position, rotation))."""
    i = source.trajectory.step_of("seal")
    (p0, r0), (p1, r1) = source.observation.poses[CHEESE], poses_now[CHEESE]
    motion = Rotation.from_matrix(r1 @ r0.T)
    ideal = motion * Rotation.from_matrix(source.trajectory.rotations[i])
    got = Rotation.from_matrix(moved.rotations[i])
    angle = min((got.inv() * ideal).magnitude(), (got.inv() * HALF_TURN * ideal).magnitude())
    ideal_pos = motion.apply(source.trajectory.positions[i] - p0) + p1
    return float(np.rad2deg(angle)), float(1e3 * np.linalg.norm(moved.positions[i] - ideal_pos))


def pair_errors_mm(source: Demonstration, view) -> np.ndarray:
    """The 3-D error (mm) of each matched pair's target against where the simulator moved its source point."""
    pairs = view.pairs
    truth = true_targets(pairs.source, pairs.labels, source.observation.poses, view.poses)
    return 1e3 * np.linalg.norm(pairs.target - truth, axis=1)


def _median(values) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


class StackingReport:
    """``good_mm``: a pair is good when its 3-D error is below it; ``examples``: match figures per condition and
    keypoint source."""

    def __init__(self, good_mm: float = 20.0, examples: int = 2):
        self.good_mm, self.examples = float(good_mm), int(examples)

    def scores(
        self, env, source: Demonstration, view, trajectory: Trajectory | None, execution: Execution | None
    ) -> dict:
        kept, errors = view.pairs.kept, pair_errors_mm(source, view)
        out = {
            "n_pairs": int(kept.sum()),
            "rejected": int((~kept).sum()),
            "pairs_on": {
                name: int(sum(bool(k) and label == name for k, label in zip(kept, view.pairs.labels)))
                for name in BLOCKS
            },
            "pair_error_mm": float(np.median(errors[kept])) if kept.any() else float("nan"),
            "grasp_error_deg": float("nan"),
            "grasp_error_mm": float("nan"),
            "place_yaw_error_deg": float("nan"),
            "max_std": float("nan"),
            "pair_errors_mm": errors[kept].tolist(),
            "rejected_errors_mm": errors[~kept].tolist(),
        }
        if trajectory is not None:
            out["grasp_error_deg"], out["grasp_error_mm"] = grasp_errors(source, trajectory, view.poses)
            cheese_yaw, lettuce_yaw = yaw_of(env.object_pose(CHEESE)[1]), yaw_of(env.object_pose(LETTUCE)[1])
            out["place_yaw_error_deg"] = float(
                np.rad2deg(abs(nearest_half_turn(cheese_yaw, lettuce_yaw) - lettuce_yaw))
            )
            out["max_std"] = float(trajectory.std.max())
        return out

    def summarise(self, trials: list[TrialResult]) -> dict:
        scores = [t.scores for t in trials]
        errors = np.concatenate([s["pair_errors_mm"] for s in scores]) if scores else np.empty(0)
        rejected = np.concatenate([s["rejected_errors_mm"] for s in scores]) if scores else np.empty(0)
        return {
            **success_summary([{"success": t.success, "failure": t.failure} for t in trials]),
            "pairs_mean": float(np.mean([s["n_pairs"] for s in scores])),
            "no_pair_on_cheese": sum(s["pairs_on"][CHEESE] == 0 for s in scores),
            "rejected": len(rejected),
            "rejected_wrong": int((rejected >= self.good_mm).sum()),
            "pair_error_mm_median": _median(errors),
            "pairs_good": float(np.mean(errors < self.good_mm)) if len(errors) else float("nan"),
            "grasp_error_deg_median": _median([s["grasp_error_deg"] for s in scores]),
            "grasp_error_mm_median": _median([s["grasp_error_mm"] for s in scores]),
            "place_yaw_error_deg_median": _median([t.scores["place_yaw_error_deg"] for t in trials if t.success]),
        }

    def table(self, summaries: dict[tuple, dict], axes: list[str]) -> str:
        rows = [
            f"| condition | {' | '.join(axes)} | success [95% CI] | failure reasons | pairs kept | pairs dropped (of them wrong) "
            "| no pair on the cheese (trials) | pair error, median (mm) "
            f"| pairs within {self.good_mm:.0f} mm | grasp orientation error, median (deg) | grasp position error, median (mm) "
            "| placed yaw error, median of successes (deg) |",
            "|---|" + "---|" * len(axes) + "---|---|---|---|---|---|---|---|---|---|",
        ]
        for cell, s in summaries.items():
            rows.append(
                f"| {' | '.join(cell)} | {success_cells(s)} | {s['pairs_mean']:.1f} "
                f"| {s['rejected']} ({s['rejected_wrong']}) | {s['no_pair_on_cheese']} | {s['pair_error_mm_median']:.1f} "
                f"| {100 * s['pairs_good']:.0f}% | {s['grasp_error_deg_median']:.1f} | {s['grasp_error_mm_median']:.1f} "
                f"| {s['place_yaw_error_deg_median']:.1f} |"
            )
        return "\n".join(rows) + "\n"

    def header(self, trial, n_trials: dict[str, int]) -> str:
        m, source = trial.task.matcher, trial.source
        counts = sorted(set(n_trials.values()))
        return (
            "# Stacking: keypoints from images, one demonstration transported to new scenes\n\n"
            f"Source demonstration succeeded in its own scene: {source.execution.success}. "
            f"{', '.join(map(str, counts))} seeded scenes per condition; at most {m.max_pairs} pairs per image pair, spread over {m.spread}; "
            f"pairs breaking rigidity dropped: {m.consistency or 'no'}.\n\n"
        )

    def showcase(self, trials: list[TrialResult], videos: int) -> list[tuple[TrialResult, bool]]:
        return first_map_trials(trials, self.examples, videos)

    def figures(self, out: Path, trial, trials: list[TrialResult], showcase: list[TrialResult]) -> list[str]:
        """``matches_<condition>_<keypoints>_<index>_<outcome>.png``: the pairs drawn on the two images, green within
        ``good_mm`` of the truth, red beyond, dashed where dropped as breaking rigidity."""
        names, source = [], trial.source
        for shown in (t for t in showcase if t.index < self.examples):
            view = shown.artefacts["view"]
            errors = pair_errors_mm(source, view)
            outcome = "success" if shown.success else shown.failure.replace(" ", "_")
            name = f"matches_{shown.condition}_{shown.variant['keypoints']}_{shown.index:02d}_{outcome}.png"
            title = (
                f"{shown.condition} #{shown.index}, {shown.variant['keypoints']}: {shown.scores['n_pairs']} pairs kept, median"
                f" error {shown.scores['pair_error_mm']:.0f} mm, {shown.variant['map']}: {outcome}"
            )
            fig, axes = plots.new_figure(1, 1, size=6.0)
            plots.draw_matches(axes[0, 0], source.observation.image["rgb"], view.image["rgb"], view.pairs.pixels_before,
                               view.pairs.pixels_now, errors < self.good_mm, title, dropped=~view.pairs.kept)  # fmt: skip
            save_figure(fig, out / name, dpi=110, bbox_inches="tight")
            plots.close(fig)
            names.append(name)
        return names
