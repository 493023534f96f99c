"""The robosuite tasks' trial: transport the one recorded demonstration into a new scene, open loop.

A trial resets the simulator to its scene, finds the keypoints with one keypoint source (the task's
``keypoint_sources``, or the dense backbones given, plus ``"oracle"``), fits one map family and transports the
demonstration (:class:`~kpflow.policies.demo_transport.DemoTransportPolicy`), executes it, and the task's report
scores it. Each worker process has its own simulator and its own (identical, deterministic) recording of the source
demonstration.
"""

from __future__ import annotations

from typing import Any, Callable

from kpflow.core.task import ORACLE, ArmTask, TrialResult
from kpflow.policies.demo_transport import DemoTransportPolicy, check_uncertainty_options


def keypoint_sources(task: ArmTask, backbones: dict | None, oracle: bool) -> dict[str, Any]:
    """name -> keypoint source: the backbones (plus ``"oracle"``), or the task's own sources."""
    if backbones and ORACLE in backbones:
        raise ValueError(f"{ORACLE!r} is reserved for the simulator's exact pairs: rename that backbone")
    if backbones or oracle:
        return {**(backbones or {}), **({ORACLE: ORACLE} if oracle else {})}
    return {name: name for name in getattr(task, "keypoint_sources", ())}


class DemoTransportTrial:
    """``task`` x keypoint sources x ``maps`` (name -> factory of a transportation map), scored by ``report``
    (:mod:`kpflow.eval.reports`: packing's or stacking's). ``backbones``: name -> dense backbone, for tasks that find
    keypoints in images, with ``oracle`` adding the simulator's exact pairs; without them the task's own
    ``keypoint_sources`` are used. ``max_std`` and ``on_uncertain``: the policy's action where the map is unsure
    (:class:`~kpflow.policies.demo_transport.DemoTransportPolicy`; None: transport everything)."""

    def __init__(self, task: ArmTask, report, maps: dict[str, Callable], backbones: dict[str, Any] | None = None, oracle: bool = False,
                 max_std: float | None = None, on_uncertain: str = "rigid"):  # fmt: skip
        self.task, self.report, self.maps = task, report, dict(maps)
        self.max_std, self.on_uncertain = max_std, on_uncertain
        check_uncertainty_options(max_std, on_uncertain)
        self.sources = keypoint_sources(task, backbones, oracle)
        if not self.sources or not self.maps:
            raise ValueError(
                f"{task.name}: give at least one keypoint source (backbones, or oracle: true) and one map family"
            )
        self.name, self.conditions = task.name, tuple(task.conditions)
        self.default_conditions = self.conditions
        #: the grid's keypoint axis is shown when there is a choice to show (backbones, oracle, several sources)
        self.axes = (("keypoints",) if backbones or oracle or len(self.sources) > 1 else ()) + ("map",)
        self.env = self.source = None

    def variants(self) -> list[dict[str, str]]:
        return [
            {**({"keypoints": s} if "keypoints" in self.axes else {}), "map": m}
            for s in self.sources
            for m in self.maps
        ]

    def setup(self, env=None) -> None:
        """One thread, the simulator (``env``, or a new one) and the recorded source demonstration."""
        import torch

        torch.set_num_threads(1)
        self.env = env if env is not None else self.task.make_env()
        self.source = self.task.demonstrate(self.env)

    def run(
        self, condition: str, index: int, variant: dict[str, str], seed: int, frames: list | None = None
    ) -> TrialResult:
        """Trial ``index`` of ``condition`` with ``variant``'s keypoint source and map (module docstring)."""
        scene = self.task.sample_scene(condition, index, seed)
        keypoint_source = self.sources[variant.get("keypoints", next(iter(self.sources)))]
        return self.run_scene(scene, keypoint_source, self.maps[variant["map"]], frames, condition, index, variant)

    def run_scene(self, scene, keypoint_source: Any, make_map: Callable, frames: list | None = None, condition: str = "",
                  index: int = 0, variant: dict[str, str] | None = None) -> TrialResult:  # fmt: skip
        """One trial in ``scene`` (labelled ``condition``, ``index`` and ``variant``) after :meth:`setup`;
        ``artefacts`` keep the trajectory, execution, keypoints and the task's view."""
        task, env, source = self.task, self.env, self.source
        keypoints, view = task.observe(env, scene, source, keypoint_source)
        trajectory = execution = None
        if keypoints is not None:
            trajectory, _ = DemoTransportPolicy(make_map, self.max_std, self.on_uncertain).plan(
                source.trajectory, keypoints
            )
            execution = task.execute(env, trajectory, frames)
        scores = self.report.scores(env, source, view, trajectory, execution)
        success = bool(execution is not None and execution.success)
        failure = task.no_keypoints if execution is None else execution.failure
        artefacts = {"trajectory": trajectory, "execution": execution, "keypoints": keypoints, "view": view}
        return TrialResult(condition, index, dict(variant or {}), scene.as_dict(), success, failure, scores, artefacts)

    def describe(self) -> dict:
        s = self.source
        return {"source": {"scene": s.scene.as_dict(), "success": s.execution.success, "failure": s.execution.failure}}
