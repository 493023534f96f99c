"""The frames task behind one class: reaching between a start and a goal frame, each described by five keypoints.

It has no simulator: a scene (:class:`~.scene.Scene`) is the two frames and the demonstration between them, its
keypoints are the frames' (:func:`~.frames.scene_keypoints`), and a policy is judged against the scene's own
demonstration (:mod:`kpflow.eval.frames_experiment`). Conditions: ``lasa`` is the paper's Figure 1 (one LASA
handwriting demonstration; its goal frame moved, then both frames), ``random`` Figure 2's seeded configurations
with a minimum-jerk demonstration each.
"""

from __future__ import annotations

import torch

from kpflow.core.task import Task

from .frames import scene_keypoints
from .lasa import lasa_frames, load_lasa
from .scene import Scene, moved, random_scenes

CONDITIONS = ("lasa", "random")
LASA_MOVES = ("goal moved", "both moved")  # Figure 1's scenes, in order


class FramesTask(Task):
    """The frames task, a :class:`~kpflow.core.task.Task` of scenes and keypoints only (no simulator):
    ``frame_size``: the keypoints' distance from a frame's origin; ``n_points``: samples per demonstration;
    ``lasa_shape``: Figure 1's LASA motion."""

    name = "frames"
    conditions = CONDITIONS

    def __init__(self, frame_size: float = 0.1, n_points: int = 200, lasa_shape: str = "Sshape"):
        if frame_size <= 0 or n_points < 2:
            raise ValueError(f"frame_size must be > 0 and n_points >= 2, got {frame_size} and {n_points}")
        self.frame_size, self.n_points, self.lasa_shape = float(frame_size), int(n_points), lasa_shape

    def source_scene(self) -> Scene:
        """Figure 1's demonstration (LASA ``lasa_shape``) between the frames at its ends."""
        demo = load_lasa(self.lasa_shape, n=self.n_points, dtype=torch.float64)
        return Scene(*lasa_frames(demo), demo)

    def sample_scenes(self, condition: str, n: int, seed: int = 0) -> list[Scene]:
        """The first ``n`` scenes of ``condition``: for ``lasa`` the source's frames moved (:data:`LASA_MOVES`, its
        demonstration kept: it is what a map transports), for ``random`` seeded configurations."""
        if condition == "lasa":
            source = self.source_scene()
            start, goal, demo = source.start, source.goal, source.demo
            span = float((demo.positions.amax(0) - demo.positions.amin(0)).norm())
            moves = [(start, moved(goal, 0.2 * span, 0.1 * span, 0.4)),
                     (moved(start, -0.15 * span, 0.2 * span, -0.3), moved(goal, 0.25 * span, -0.1 * span, -0.4))]  # fmt: skip
            if n > len(moves):
                raise ValueError(f"the lasa condition has {len(moves)} scenes ({LASA_MOVES}), not {n}")
            return [Scene(s, g, demo) for s, g in moves[:n]]
        if condition == "random":
            return random_scenes(n, self.n_points, seed)
        self.check_condition(condition)

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Scene:
        """Scene ``index`` of ``condition`` (the scenes are drawn in sequence from ``seed``)."""
        return self.sample_scenes(condition, index + 1, seed)[index]

    def keypoints(self, scene: Scene) -> torch.Tensor:
        """The ten keypoints of the scene's start and goal frames ``[10, D]``."""
        return scene_keypoints([scene.start, scene.goal], self.frame_size)
