"""Packing evaluation (``python evaluate.py experiment=packing``): one source demonstration, transported zero-shot.

For each condition (``relocation``: the object moved; ``full``: object type, object pose and container pose all
changed) and each map family, ``n_trials`` seeded scenes (:func:`~kpflow.tasks.packing.scene.sample_scene`, the
same scenes for every map) are run in worker processes, each with its own simulator and its own (identical,
deterministic) recording of the source demonstration. Writes ``results.json`` (every trial with its failure
reason), ``results.md`` (success per condition and map with 95% Wilson intervals, failure reasons, perception
error), ``trajectories.png`` (source and transported paths with the keypoints) and mp4 videos of a few GP trials.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from kpflow.eval import plots
from kpflow.eval.parallel import map_jobs
from kpflow.eval.stats import success_cells, success_summary
from kpflow.utils.io import save_figure, write_json, write_text
from kpflow.utils.video import write_video

_WORKER: dict = {}  # this process's simulator, source demonstration and map factories


def _init(maps: dict, source: dict | None, camera_size) -> None:
    import torch

    from kpflow.tasks.packing.env import PackingEnv
    from kpflow.tasks.packing.scene import SOURCE_SCENE, Scene
    from kpflow.tasks.packing.trial import record_source

    torch.set_num_threads(1)
    env = PackingEnv(camera_size=tuple(camera_size))
    scene = Scene(**source) if source else SOURCE_SCENE
    _WORKER.update(env=env, maps=maps, source=record_source(env, scene), init=(maps, source, camera_size))


def _trial(job: tuple) -> dict:
    from kpflow.tasks.packing.scene import sample_scene
    from kpflow.tasks.packing.trial import run_trial

    condition, index, seed, map_name = job
    scene = sample_scene(condition, index, seed, _WORKER["source"]["scene"])
    r = run_trial(_WORKER["env"], _WORKER["source"], scene, _WORKER["maps"][map_name])
    keep = ("scene", "success", "failure", "min_singular_value", "max_tracking_error", "box_error_mm", "max_std")
    return {"condition": condition, "index": index, "map": map_name, **{k: r[k] for k in keep}}


def summarise(trials: list[dict]) -> dict:
    """Success rate with its 95% Wilson interval, failure reasons and perception error of a group of trials."""
    return {
        **success_summary(trials),
        "box_error_mm_median": float(np.median([t["box_error_mm"] for t in trials])),
    }


def table(summaries: dict) -> str:
    rows = [
        "| condition | map | trials | success [95% CI] | failure reasons | object box error, median (mm) |",
        "|---|---|---|---|---|---|",
    ]
    for (condition, map_name), s in summaries.items():
        rows.append(f"| {condition} | {map_name} | {s['trials']} | {success_cells(s)} | {s['box_error_mm_median']:.1f} |")
    return "\n".join(rows) + "\n"


def _plot(source: dict, examples: list[dict], path: Path) -> None:
    """Top view and side view: the source path and keypoints, and transported paths with their target keypoints."""
    fig, axes = plots.new_figure(1, 2, size=4.2)
    top, side = axes[0]
    for ax, (i, j), name in ((top, (0, 1), "top view (x, y)"), (side, (0, 2), "side view (x, z)")):
        ax.set_aspect("equal")
        ax.set_title(name)
        pos, kp = source["trajectory"]["positions"], source["keypoints"]
        ax.plot(pos[:, i], pos[:, j], "k-", lw=2, label="source")
        ax.scatter(kp[:, i], kp[:, j], c="k", s=10)
        for n, ex in enumerate(examples):
            colour = f"C{n}"
            p, k = ex["trajectory"]["positions"], ex["keypoints"]
            ax.plot(p[:, i], p[:, j], "-", color=colour, lw=1.2, label=f"{ex['scene']['object_type']} ({'ok' if ex['success'] else ex['failure']})")
            ax.plot(ex["tip"][:, i], ex["tip"][:, j], ":", color=colour, lw=1)
            ax.scatter(k[:, i], k[:, j], color=colour, s=8, marker="x")
    top.legend(fontsize=6, loc="lower right")
    save_figure(fig, path, dpi=120)
    plots.close(fig)


def run_packing_experiment(
    output_dir: str | Path,
    maps: dict[str, Callable],
    seed: int = 0,
    conditions: tuple[str, ...] = ("relocation", "full"),
    n_trials: int = 50,
    workers: int = 2,
    videos: int = 1,
    camera_size: tuple[int, int] = (480, 640),
    source: dict | None = None,
    progress: bool = True,
) -> dict:
    """Run every condition x map x trial; write results (module docstring) into ``output_dir``."""
    from kpflow.tasks.packing.scene import CONDITIONS, sample_scene
    from kpflow.tasks.packing.trial import run_trial

    conditions = list(conditions)
    if not maps:
        raise ValueError("give at least one map family (maps: {name: factory})")
    if any(c not in CONDITIONS for c in conditions):
        raise ValueError(f"unknown condition in {conditions}; choose from {CONDITIONS}")
    if n_trials < 1 or workers < 1:
        raise ValueError(f"n_trials and workers must be >= 1, got {n_trials} and {workers}")
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(c, i, seed, m) for c in conditions for m in maps for i in range(n_trials)]
    init = (dict(maps), None if source is None else dict(source), tuple(camera_size))
    trials = map_jobs(_trial, jobs, workers, _init, init, desc="packing trials", unit="trial", progress=progress)
    summaries = {(c, m): summarise([t for t in trials if t["condition"] == c and t["map"] == m]) for c in conditions for m in maps}
    md = table(summaries)

    if _WORKER.get("init") != init:  # this process has not set up this run's simulator yet
        _init(*init)
    env, src = _WORKER["env"], _WORKER["source"]
    first_map = "gp" if "gp" in maps else next(iter(maps))
    examples, video_paths = [], []
    for c in conditions:
        for i in range(min(2, n_trials)):
            frames = [] if len(video_paths) < videos * len(conditions) and i < videos else None
            ex = run_trial(env, src, sample_scene(c, i, seed, src["scene"]), maps[first_map], frames)
            examples.append(ex)
            if frames:
                name = f"{c}_{first_map}_{i:02d}_{'success' if ex['success'] else 'failure'}.mp4"
                video_paths.append(str(write_video(frames, out / name, fps=20)))
    _plot(src, examples, out / "trajectories.png")

    results = {
        "source": {"scene": src["scene"].as_dict(), "success": src["result"]["success"], "keypoints": src["keypoints"].tolist()},
        "summary": [{"condition": c, "map": m, **s} for (c, m), s in summaries.items()],
        "trials": trials,
        "videos": video_paths,
    }
    results["metrics"] = {f"{c}/{m}/success": s["success"] for (c, m), s in summaries.items()}
    write_json(out / "results.json", results)
    header = (
        "# Packing: one demonstration transported to new scenes\n\n"
        f"Source demonstration ({src['scene'].object_type}) succeeded in its own scene: {src['result']['success']}.\n\n"
    )
    write_text(out / "results.md", header + md)
    return results
