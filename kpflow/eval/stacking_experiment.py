"""Stacking evaluation (``python evaluate.py experiment=stacking``): keypoints found in images, one demonstration
transported zero-shot.

For each condition (``moved``: both blocks moved, same sides; ``swapped``: sides exchanged), each correspondence
source (a dense backbone, or ``oracle``: the simulator's exact pairs) and each map family, ``n_trials`` seeded scenes
(:func:`~kpflow.tasks.stacking.scene.sample_scene`, the same for every backbone and map) are run in worker
processes, each with its own simulator and its own (identical, deterministic) recording of the source
demonstration. Writes ``results.json`` (every trial: failure reason, correspondence errors, grasp errors),
``results.md`` (per condition, backbone and map: success with its 95% Wilson interval, failure reasons, the 3-D
error of the correspondences against the simulator's truth, the orientation and position error of the transported
grasp, the placed block's yaw error), ``matches_*.png`` (the pairs drawn on the two images, green within
``good_mm`` of the truth, red beyond, dashed where dropped as breaking rigidity) and mp4s of the first ``videos``
trials per condition and keypoint source (with the first map).
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

_WORKER: dict = {}  # this process's simulator, source demonstration, backbones and maps


def _init(backbones: dict, maps: dict, source: dict | None, camera_size, pairs: dict) -> None:
    import torch

    from kpflow.tasks.stacking.env import StackingEnv
    from kpflow.tasks.stacking.scene import SOURCE_SCENE, Scene
    from kpflow.tasks.stacking.trial import record_source

    torch.set_num_threads(1)
    env = StackingEnv(camera_size=tuple(camera_size))
    scene = Scene(**{k: tuple(v) for k, v in source.items()}) if source else SOURCE_SCENE
    _WORKER.update(env=env, backbones=backbones, maps=maps, pairs=pairs, source=record_source(env, scene))
    _WORKER["init"] = (backbones, maps, source, camera_size, pairs)


def _run(condition: str, index: int, seed: int, backbone: str, map_name: str, frames: list | None = None) -> dict:
    from kpflow.tasks.stacking.scene import sample_scene
    from kpflow.tasks.stacking.trial import ORACLE, run_trial

    scene = sample_scene(condition, index, seed, _WORKER["source"]["scene"])
    bb = ORACLE if backbone == ORACLE else _WORKER["backbones"][backbone]
    env, source, make_map = _WORKER["env"], _WORKER["source"], _WORKER["maps"][map_name]
    return run_trial(env, source, scene, bb, make_map, seed=seed, frames=frames, **_WORKER["pairs"])


def _trial(job: tuple) -> dict:
    condition, index, seed, backbone, map_name = job
    r = _run(*job)
    keep = ("scene", "success", "failure", "n_pairs", "rejected", "pairs_on", "pair_error_mm", "grasp_error_deg",
            "grasp_error_mm", "place_yaw_error_deg", "max_std")  # fmt: skip
    return {
        "condition": condition, "index": index, "backbone": backbone, "map": map_name, **{k: r[k] for k in keep},
        "pair_errors_mm": r["pairs"]["errors_mm"][r["pairs"]["kept"]].tolist(),
        "rejected_errors_mm": r["pairs"]["errors_mm"][~r["pairs"]["kept"]].tolist(),
    }  # fmt: skip


def _median(values) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


def summarise(trials: list[dict], good_mm: float) -> dict:
    """Success with its 95% Wilson interval, failure reasons, correspondence and grasp errors of a group of trials."""
    errors = np.concatenate([t["pair_errors_mm"] for t in trials]) if trials else np.empty(0)
    rejected = np.concatenate([t["rejected_errors_mm"] for t in trials]) if trials else np.empty(0)
    return {
        **success_summary(trials),
        "pairs_mean": float(np.mean([t["n_pairs"] for t in trials])),
        "no_pair_on_cheese": sum(t["pairs_on"]["cheese"] == 0 for t in trials),
        "rejected": len(rejected),
        "rejected_wrong": int((rejected >= good_mm).sum()),
        "pair_error_mm_median": _median(errors),
        "pairs_good": float(np.mean(errors < good_mm)) if len(errors) else float("nan"),
        "grasp_error_deg_median": _median([t["grasp_error_deg"] for t in trials]),
        "grasp_error_mm_median": _median([t["grasp_error_mm"] for t in trials]),
        "place_yaw_error_deg_median": _median([t["place_yaw_error_deg"] for t in trials if t["success"]]),
    }


def table(summaries: dict, good_mm: float) -> str:
    rows = [
        "| condition | keypoints | map | success [95% CI] | failure reasons | pairs kept | pairs dropped (of them wrong) "
        "| no pair on the cheese (trials) | pair error, median (mm) "
        f"| pairs within {good_mm:.0f} mm | grasp orientation error, median (deg) | grasp position error, median (mm) "
        f"| placed yaw error, median of successes (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (condition, backbone, map_name), s in summaries.items():
        rows.append(
            f"| {condition} | {backbone} | {map_name} | {success_cells(s)} | {s['pairs_mean']:.1f} "
            f"| {s['rejected']} ({s['rejected_wrong']}) | {s['no_pair_on_cheese']} | {s['pair_error_mm_median']:.1f} "
            f"| {100 * s['pairs_good']:.0f}% | {s['grasp_error_deg_median']:.1f} | {s['grasp_error_mm_median']:.1f} "
            f"| {s['place_yaw_error_deg_median']:.1f} |"
        )
    return "\n".join(rows) + "\n"


def _match_figure(source: dict, trial: dict, title: str, path: Path, good_mm: float) -> None:
    pairs = trial["pairs"]
    fig, axes = plots.new_figure(1, 1, size=6.0)
    plots.draw_matches(axes[0, 0], source["image"]["rgb"], trial["now_rgb"], pairs["pixels_before"], pairs["pixels_now"],
                       pairs["errors_mm"] < good_mm, title, dropped=~pairs["kept"])  # fmt: skip
    save_figure(fig, path, dpi=110, bbox_inches="tight")
    plots.close(fig)


def run_stacking_experiment(
    output_dir: str | Path,
    backbones: dict[str, Callable],
    maps: dict[str, Callable],
    seed: int = 0,
    conditions: tuple[str, ...] = ("moved", "swapped"),
    n_trials: int = 20,
    oracle: bool = True,
    max_pairs: int = 7,
    saliency_threshold: float = 0.2,
    spread: str = "descriptors",
    consistency: dict | None = None,
    good_mm: float = 20.0,
    match_images: int = 2,
    videos: int = 1,
    workers: int = 2,
    camera_size: tuple[int, int] = (480, 480),
    source: dict | None = None,
    progress: bool = True,
) -> dict:
    """Run every condition x keypoint source x map x trial; write the results (module docstring) to ``output_dir``.

    ``backbones``: name -> a dense backbone (:class:`kpflow.vision.DenseBackbone`), already built; ``maps``: name ->
    factory of a transportation map; ``oracle`` adds the simulator's exact pairs as a keypoint source.
    """
    from kpflow.tasks.stacking.scene import CONDITIONS
    from kpflow.tasks.stacking.trial import ORACLE

    conditions = list(conditions)
    sources = [*backbones, *([ORACLE] if oracle else [])]
    if not sources or not maps:
        raise ValueError("give at least one backbone (or oracle: true) and one map family")
    if ORACLE in backbones:
        raise ValueError(f"{ORACLE!r} is reserved for the simulator's exact pairs: rename that backbone")
    if any(c not in CONDITIONS for c in conditions):
        raise ValueError(f"unknown condition in {conditions}; choose from {CONDITIONS}")
    if n_trials < 1 or workers < 1 or max_pairs < 1:
        raise ValueError(f"n_trials, workers and max_pairs must be >= 1, got {n_trials}, {workers}, {max_pairs}")
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(c, i, seed, b, m) for c in conditions for b in sources for m in maps for i in range(n_trials)]
    pairs = {"max_pairs": max_pairs, "saliency_threshold": saliency_threshold, "spread": spread, "consistency": consistency}
    init = (dict(backbones), dict(maps), None if source is None else dict(source), tuple(camera_size), pairs)
    trials = map_jobs(_trial, jobs, workers, _init, init, desc="stacking trials", unit="trial", progress=progress)
    summaries = {
        (c, b, m): summarise([t for t in trials if (t["condition"], t["backbone"], t["map"]) == (c, b, m)], good_mm)
        for c in conditions for b in sources for m in maps
    }  # fmt: skip

    if _WORKER.get("init") != init:  # this process has not set up this run's simulator yet
        _init(*init)
    src = _WORKER["source"]
    first_map = next(iter(maps))
    images, video_paths = [], []
    for c in conditions:
        for b in sources:
            for i in range(min(max(match_images, videos), n_trials)):
                frames = [] if i < videos else None
                r = _run(c, i, seed, b, first_map, frames)
                outcome = "success" if r["success"] else r["failure"].replace(" ", "_")
                if i < match_images:
                    name = f"matches_{c}_{b}_{i:02d}_{outcome}.png"
                    title = (
                        f"{c} #{i}, {b}: {r['n_pairs']} pairs kept, median error {r['pair_error_mm']:.0f} mm, "
                        f"{first_map}: {outcome}"
                    )
                    _match_figure(src, r, title, out / name, good_mm)
                    images.append(name)
                if frames:
                    video_paths.append(str(write_video(frames, out / f"{c}_{b}_{first_map}_{i:02d}_{outcome}.mp4", fps=20)))

    results = {
        "source": {"scene": src["scene"].as_dict(), "success": src["result"]["success"]},
        "summary": [{"condition": c, "backbone": b, "map": m, **s} for (c, b, m), s in summaries.items()],
        "trials": trials,
        "match_images": images,
        "videos": video_paths,
    }
    results["metrics"] = {f"{c}/{b}/{m}/success": s["success"] for (c, b, m), s in summaries.items()}
    write_json(out / "results.json", results)
    header = (
        "# Stacking: keypoints from images, one demonstration transported to new scenes\n\n"
        f"Source demonstration succeeded in its own scene: {src['result']['success']}. "
        f"{n_trials} seeded scenes per condition; at most {max_pairs} pairs per image pair, spread over {spread}; "
        f"pairs breaking rigidity dropped: {consistency or 'no'}.\n\n"
    )
    write_text(out / "results.md", header + table(summaries, good_mm))
    return results
