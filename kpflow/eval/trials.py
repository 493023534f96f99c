"""The one trial loop of the robosuite tasks: any task x keypoint source x map grid, in parallel workers.

For each condition, keypoint source (the task's ``keypoint_sources``, or the dense backbones given, plus
``"oracle"``) and map family, ``n_trials`` seeded scenes (the same scenes for every cell) are run in worker
processes, each with its own simulator and its own (identical, deterministic) recording of the source
demonstration. A trial resets the simulator to its scene, finds the keypoints, fits the map and transports the
demonstration (:class:`~kpflow.policies.demo_transport.DemoTransportPolicy`), executes it, and the task's report
scores it. Afterwards the first trials of every condition and keypoint source are re-run with the first map to
draw the report's figures and write videos.

Writes ``results.json`` (source, summary per cell, every trial with its failure reason and scores, figures,
videos), ``results.md`` (the report's table) and the report's figures and mp4s into the run folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from kpflow.eval.parallel import map_jobs
from kpflow.eval.reports import Report
from kpflow.policies.demo_transport import DemoTransportPolicy
from kpflow.tasks.base import ORACLE, ArmTask, Demonstration, TrialResult
from kpflow.utils.io import write_json, write_text
from kpflow.utils.video import write_video

_WORKER: dict = {}  # this process's task, simulator, source demonstration, keypoint sources and maps


def _init(task: ArmTask, report: Report, sources: dict, maps: dict) -> None:
    import torch

    torch.set_num_threads(1)
    env = task.make_env()
    _WORKER.update(task=task, report=report, env=env, sources=sources, maps=maps, demo=task.demonstrate(env))


def run_trial(task: ArmTask, report: Report, env, demo: Demonstration, scene, keypoint_source: Any, make_map: Callable,
              frames: list | None = None, *, condition: str = "", index: int = 0, variant: dict | None = None) -> TrialResult:  # fmt: skip
    """One trial in ``scene`` (module docstring), labelled ``condition``, ``index`` and ``variant``; ``artefacts``
    keep the trajectory, execution, keypoints and the task's view."""
    keypoints, view = task.observe(env, scene, demo, keypoint_source)
    trajectory = execution = None
    if keypoints is not None:
        trajectory, _ = DemoTransportPolicy(make_map).plan(demo.trajectory, keypoints)
        execution = task.execute(env, trajectory, frames)
    scores = report.scores(env, demo, view, trajectory, execution)
    success = bool(execution is not None and execution.success)
    failure = task.no_keypoints if execution is None else execution.failure
    artefacts = {"trajectory": trajectory, "execution": execution, "keypoints": keypoints, "view": view}
    return TrialResult(condition, index, dict(variant or {}), scene.as_dict(), success, failure, scores, artefacts)


def _variant(axes: dict[str, str], source: str, map_name: str) -> dict[str, str]:
    return {**({"keypoints": source} if "keypoints" in axes else {}), "map": map_name}


def _trial(job: tuple) -> dict:
    condition, index, seed, source, map_name, axes = job
    w = _WORKER
    scene = w["task"].sample_scene(condition, index, seed)
    trial = run_trial(w["task"], w["report"], w["env"], w["demo"], scene, w["sources"][source], w["maps"][map_name],
                      condition=condition, index=index, variant=_variant(axes, source, map_name))  # fmt: skip
    return trial.record()


def keypoint_sources(task: ArmTask, backbones: dict | None, oracle: bool) -> dict[str, Any]:
    """name -> keypoint source: the backbones (plus ``"oracle"``), or the task's own sources."""
    if backbones and ORACLE in backbones:
        raise ValueError(f"{ORACLE!r} is reserved for the simulator's exact pairs: rename that backbone")
    if backbones or oracle:
        return {**(backbones or {}), **({ORACLE: ORACLE} if oracle else {})}
    return {name: name for name in getattr(task, "keypoint_sources", ())}


def _showcase(conditions: list[str], axes: dict, seed: int, n: int, videos: int, out: Path) -> tuple[list[TrialResult], list[str]]:
    """Re-run the first ``n`` trials of every condition and keypoint source with the first map, in this process;
    the first ``videos`` of them are filmed."""
    w = _WORKER
    first_map = next(iter(w["maps"]))
    showcase, video_paths = [], []
    for c in conditions:
        for s in w["sources"]:
            for i in range(n):
                frames = [] if i < videos else None
                scene = w["task"].sample_scene(c, i, seed)
                trial = run_trial(w["task"], w["report"], w["env"], w["demo"], scene, w["sources"][s], w["maps"][first_map],
                                  frames, condition=c, index=i, variant=_variant(axes, s, first_map))  # fmt: skip
                showcase.append(trial)
                if frames:
                    outcome = "success" if trial.success else trial.failure.replace(" ", "_")
                    name = "_".join([c, *trial.variant.values(), f"{i:02d}", outcome]) + ".mp4"
                    video_paths.append(str(write_video(frames, out / name, fps=20)))
    return showcase, video_paths


def _from_record(record: dict, axes: list[str]) -> TrialResult:
    fixed = {"condition", "index", "scene", "success", "failure", *axes}
    variant = {a: record[a] for a in axes}
    scores = {k: v for k, v in record.items() if k not in fixed}
    return TrialResult(record["condition"], record["index"], variant, record["scene"], record["success"], record["failure"], scores)


def run_trials(
    output_dir: str | Path,
    task: ArmTask,
    report: Report,
    maps: dict[str, Callable],
    backbones: dict[str, Any] | None = None,
    oracle: bool = False,
    seed: int = 0,
    conditions: tuple[str, ...] | None = None,
    n_trials: int = 50,
    workers: int = 2,
    videos: int = 1,
    progress: bool = True,
) -> dict:
    """Run every condition x keypoint source x map x trial of ``task`` (module docstring) into ``output_dir``.

    ``maps``: name -> factory of a transportation map. ``backbones``: name -> dense backbone, for tasks that find
    keypoints in images (their keypoint sources, with ``oracle`` adding the simulator's exact pairs); without them
    the task's own ``keypoint_sources`` are used. Returns the results with a flat ``metrics`` dict for loggers.
    """
    conditions = list(task.conditions if conditions is None else conditions)
    sources = keypoint_sources(task, backbones, oracle)
    if not sources or not maps:
        raise ValueError(f"{task.name}: give at least one keypoint source (backbones, or oracle: true) and one map family")
    if any(c not in task.conditions for c in conditions):
        raise ValueError(f"unknown condition in {conditions}; choose from {task.conditions}")
    if n_trials < 1 or workers < 1 or videos < 0:
        raise ValueError(f"n_trials and workers must be >= 1 and videos >= 0, got {n_trials}, {workers}, {videos}")
    axes = ({"keypoints": "keypoints"} if backbones or oracle or len(sources) > 1 else {}) | {"map": "map"}
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)

    jobs = [(c, i, seed, s, m, axes) for c in conditions for s in sources for m in maps for i in range(n_trials)]
    init = (task, report, dict(sources), dict(maps))
    records = map_jobs(_trial, jobs, workers, _init, init, desc=f"{task.name} trials", unit="trial", progress=progress)
    trials = [_from_record(r, list(axes)) for r in records]
    cells = [(c, s, m) for c in conditions for s in sources for m in maps]
    summaries = {}
    for c, s, m in cells:
        variant = _variant(axes, s, m)
        summaries[(c, *variant.values())] = report.summarise([t for t in trials if t.condition == c and t.variant == variant])

    if _WORKER.get("task") is not task:  # this process has not set up this run's simulator yet
        _init(*init)
    demo = _WORKER["demo"]
    showcase, video_paths = _showcase(conditions, axes, seed, min(max(report.examples, videos), n_trials), videos, out)
    figures = report.figures(out, demo, showcase)

    results = {
        "task": task.name,
        "source": {"scene": demo.scene.as_dict(), "success": demo.execution.success, "failure": demo.execution.failure},
        "summary": [{"condition": cell[0], **dict(zip(axes, cell[1:])), **s} for cell, s in summaries.items()],
        "trials": records,
        "figures": figures,
        "videos": video_paths,
    }
    results["metrics"] = {"/".join(cell) + "/success": s["success"] for cell, s in summaries.items()}
    write_json(out / "results.json", results)
    write_text(out / "results.md", report.header(task, demo, n_trials) + report.table(summaries, list(axes)))
    return results
