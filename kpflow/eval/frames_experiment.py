"""Multi-frame reaching: the paper's Figures 1 and 2, with a metrics table.

Figure 1: one demonstration (a LASA handwriting motion) between a start and a goal frame, each described by
five keypoints; the goal frame moves, then both frames move; the demonstration is transported by a map fitted
from the original to the new keypoints, with its 2-sigma band and its transported orientations.

Figure 2: eight frame configurations, one demonstration each. For each configuration, the other seven are
transported into it, a motion policy xdot = g(x) (a GP vector field on a linear attractor to the goal) is fitted on the transported data and rolled
out from the held-out start; it is compared with the held-out demonstration (discrete Frechet distance, DTW
normalised by length, final position error, final orientation error of the transported demonstrations, and
calibration: the share of held-out points inside the transported 2-sigma bands).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from kpflow.eval import metrics, plots
from kpflow.maps.base import TransportMap
from kpflow.maps.learned import check_map_factory
from kpflow.policies.euler_rollout import euler_rollout
from kpflow.policies.vector_field import GPVectorField
from kpflow.tasks.frames.task import LASA_MOVES, FramesTask
from kpflow.tasks.frames.transported_demos import transport_into
from kpflow.transport import transport_trajectory
from kpflow.utils.io import save_figure, write_json, write_text

MapFactory = Callable[[], TransportMap]


def figure1(task: FramesTask, make_map: MapFactory, out: Path) -> dict:
    original = task.source_scene()
    start, goal, demo, frame_size = original.start, original.goal, original.demo, task.frame_size
    scenes = dict(zip(LASA_MOVES, task.sample_scenes("lasa", len(LASA_MOVES))))
    fig, axes = plots.new_figure(1, 3, size=3.6)
    ax = axes[0, 0]
    plots.draw_curve(ax, demo.positions, color="k", lw=1.5)
    plots.draw_frame(ax, start.position, start.rotation, frame_size, "start")
    plots.draw_frame(ax, goal.position, goal.rotation, frame_size, "goal")
    ax.set_title(f"demonstration (LASA {task.lasa_shape})", fontsize=8)
    rows = []
    for ax, (name, scene) in zip(axes[0, 1:], scenes.items()):
        s, g = scene.start, scene.goal
        phi = make_map().fit(task.keypoints(original), task.keypoints(scene))
        tr = transport_trajectory(phi, demo.positions, demo.velocities, demo.orientations)
        plots.draw_curve(ax, demo.positions, color="0.7", lw=1, ls="--")
        plots.draw_band(ax, tr.positions, tr.std, color="tab:blue")
        plots.draw_curve(ax, tr.positions, color="tab:blue", lw=1.5)
        for f, lab in ((s, "start"), (g, "goal")):
            plots.draw_frame(ax, f.position, f.rotation, frame_size, lab)
        ax.set_title(f"{name}: transported, 2-sigma band", fontsize=8)
        rows.append(
            {
                "scene": name,
                "start_error": float((tr.positions[0] - s.position).norm()),
                "final_position_error": float((tr.positions[-1] - g.position).norm()),
                "final_orientation_error_deg": math.degrees(
                    float(metrics.rotation_angle_error(tr.orientations[-1], g.rotation))
                ),
                "max_std": float(tr.std.norm(dim=-1).max()),
            }
        )
    fig.tight_layout()
    save_figure(fig, out / "figure1.png", dpi=150)
    plots.close(fig)
    return {"scenes": rows}


def figure2(task: FramesTask, make_map: MapFactory, out: Path, n_configs: int, seed: int, horizon: float) -> dict:
    scenes, frame_size, n_points = task.sample_scenes("random", n_configs, seed), task.frame_size, task.n_points
    cols = min(4, n_configs)
    fig, axes = plots.new_figure(math.ceil(n_configs / cols), cols)
    rows = []
    for i, held in enumerate(tqdm(scenes, desc="figure 2: leave-one-out", unit="config")):
        demos = transport_into(scenes, i, make_map, frame_size, horizon)  # Eq. 6
        transported = [d.trajectory for d in demos]
        dt = float(held.demo.times[1] - held.demo.times[0])
        pos = torch.cat([t.positions for t in transported])
        vel = torch.cat([d.velocities for d in demos])
        field = GPVectorField().fit(pos, vel, goal=held.goal.position)
        rollout = euler_rollout(field, held.demo.positions[0], dt, 2 * n_points)
        truth = held.demo.positions
        rows.append(
            {
                "config": i,
                "frechet": float(metrics.discrete_frechet(rollout, truth)),
                "dtw_mean": float(metrics.dtw(rollout, truth)) / max(len(rollout), len(truth)),
                "final_position_error": float(metrics.final_position_error(rollout, truth)),
                "final_orientation_error_deg": float(
                    np.mean(
                        [
                            math.degrees(
                                float(metrics.rotation_angle_error(t.orientations[-1], held.demo.orientations[-1]))
                            )
                            for t in transported
                        ]
                    )
                ),
                "calibration_2sigma": float(
                    np.mean([float(metrics.band_coverage(t.positions, t.std, truth)) for t in transported])
                ),
            }
        )
        ax = axes.flat[i]
        lo = (torch.cat([pos, truth]).amin(0) - 0.3).numpy()
        hi = (torch.cat([pos, truth]).amax(0) + 0.3).numpy()
        plots.draw_field(ax, field, lo, hi)
        for t in transported:
            plots.draw_band(ax, t.positions, t.std, color="tab:blue", alpha=0.1)
            plots.draw_curve(ax, t.positions, color="tab:blue", lw=0.6, alpha=0.6)
        plots.draw_curve(ax, truth, color="k", lw=1.2, ls="--", label="held out")
        plots.draw_curve(ax, rollout, color="tab:orange", lw=1.8, label="policy")
        plots.draw_frame(ax, held.start.position, held.start.rotation, frame_size)
        plots.draw_frame(ax, held.goal.position, held.goal.rotation, frame_size)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_title(f"config {i}: Frechet {rows[-1]['frechet']:.3f}", fontsize=8)
    axes.flat[0].legend(fontsize=6, loc="best")
    for ax in list(axes.flat)[n_configs:]:
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, out / "figure2.png", dpi=150)
    plots.close(fig)
    keys = [k for k in rows[0] if k != "config"]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    return {"configs": rows, "mean": mean}


def markdown_table(rows: list[dict], columns: list[str], fmt: str = "{:.4f}") -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = "".join(
        "| " + " | ".join(fmt.format(r[c]) if isinstance(r[c], float) else str(r[c]) for c in columns) + " |\n"
        for r in rows
    )
    return head + body


def run_frames_experiment(
    task: FramesTask,
    make_map: MapFactory,
    output_dir: str | Path,
    seed: int = 0,
    n_configs: int = 8,
    horizon: float = 0.05,
) -> dict:
    """Run both figures (a learned map first checked against the task's keypoints:
    :func:`~kpflow.maps.learned.check_map_factory`), write ``figure1.png``, ``figure2.png``, ``results.md`` and
    ``results.json`` into ``output_dir``; return what ``results.json`` holds (with a flat ``metrics`` dict for
    loggers and the ``figures`` written) plus ``table``: the text of ``results.md``."""
    out = Path(output_dir)
    check_map_factory(make_map, *task.keypoints(task.source_scene()).shape, "the frames task")
    torch.manual_seed(seed)
    f1 = figure1(task, make_map, out)
    f2 = figure2(task, make_map, out, n_configs, seed, horizon)
    cols2 = [
        "config",
        "frechet",
        "dtw_mean",
        "final_position_error",
        "final_orientation_error_deg",
        "calibration_2sigma",
    ]
    table = (
        "## Figure 1: one demonstration, frames moved\n\n"
        + markdown_table(
            f1["scenes"], ["scene", "start_error", "final_position_error", "final_orientation_error_deg", "max_std"]
        )
        + "\n## Figure 2: leave-one-out over eight configurations (policy on transported data vs held-out demo)\n\n"
        + markdown_table(f2["configs"] + [{"config": "mean", **f2["mean"]}], cols2)
    )
    write_text(out / "results.md", table)
    results = {
        "figure1": f1,
        "figure2": f2,
        "figures": ["figure1.png", "figure2.png"],
        "metrics": {f"fig2/{k}": v for k, v in f2["mean"].items()},
    }
    write_json(out / "results.json", results)
    return {**results, "table": table}
