"""Stacking behind the task contract (:class:`~kpflow.core.task.ArmTask`): keypoints found in images.

The source demonstration is recorded with the top-down RGB-D image taken before it. In a new scene the image is
matched to the source's (a dense backbone through the configured :class:`~.keypoints.Matcher`, or ``"oracle"``:
the simulator's exact pairs), the pairs are lifted to 3-D, and the end effector's start box is added; those are the
keypoints the policy fits its map on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpflow.core.task import ORACLE, ArmTask, Demonstration, Execution
from kpflow.tasks.arm.keypoints import end_effector_box
from kpflow.trajectory import Keypoints, Trajectory
from kpflow.vision import DenseBackbone

from .demonstrator import execute, plan_stacking
from .env import StackingEnv
from .keypoints import ImagePairs, Matcher, oracle_pairs
from .objects import BLOCKS, CHEESE, LETTUCE
from .scene import CONDITIONS, SOURCE_SCENE, Scene, sample_scene


@dataclass(frozen=True)
class StackingView:
    """A scene as the task sees it: the top-down ``image`` (rgb, depth, masks, camera), the blocks' ``poses``
    (name -> (position, rotation)) and ``boxes`` (name -> (centre, rotation, half extents)) from the simulator, the
    end effector's ``start_box`` keypoints and, in a trial, the ``pairs`` matched to the source's image."""

    image: dict
    poses: dict
    boxes: dict
    start_box: np.ndarray
    pairs: ImagePairs | None = None


class StackingTask(ArmTask):
    """Put the cheese block on the lettuce block; ``source`` overrides the demonstration's scene, ``matcher`` says
    how image keypoints are found."""

    name = "stacking"
    conditions = CONDITIONS

    def __init__(
        self,
        camera_size: tuple[int, int] = (480, 480),
        source: dict | None = None,
        matcher: Matcher | dict | None = None,
    ):
        self.camera_size = tuple(camera_size)
        self.source_scene = Scene(**{k: tuple(v) for k, v in source.items()}) if source else SOURCE_SCENE
        self.matcher = matcher if isinstance(matcher, Matcher) else Matcher(**(matcher or {}))

    def make_env(self) -> StackingEnv:
        return StackingEnv(camera_size=self.camera_size)

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Scene:
        return sample_scene(condition, index, seed, self.source_scene)

    def _view(self, env: StackingEnv) -> StackingView:
        return StackingView(
            image=env.render_topdown(),
            poses={name: env.object_pose(name) for name in BLOCKS},
            boxes={name: env.object_box(name) for name in BLOCKS},
            start_box=end_effector_box(*env.ee_pose()),
        )

    def demonstrate(self, env: StackingEnv) -> Demonstration:
        env.reset_to(self.source_scene)
        view = self._view(env)
        trajectory = plan_stacking(*env.ee_pose(), view.boxes[CHEESE], view.boxes[LETTUCE])
        return Demonstration(self.source_scene, view, trajectory, execute(env, trajectory))

    def observe(
        self, env: StackingEnv, scene: Scene, source: Demonstration, keypoint_source: DenseBackbone | str
    ) -> tuple[Keypoints | None, StackingView]:
        """The start box plus the kept pairs (None when no pair is kept), and the view with its ``pairs``."""
        if isinstance(keypoint_source, str) and keypoint_source != ORACLE:
            raise ValueError(f"a keypoint source is a DenseBackbone or {ORACLE!r}, got {keypoint_source!r}")
        env.reset_to(scene)
        now, before = self._view(env), source.observation
        if isinstance(keypoint_source, str):
            pairs = oracle_pairs(before.image, now.image, before.boxes, before.poses, now.poses)
        else:
            pairs = self.matcher.pairs(before.image, now.image, keypoint_source)
        view = StackingView(now.image, now.poses, now.boxes, now.start_box, pairs)
        if not pairs.kept.any():
            return None, view
        keypoints = Keypoints(
            np.concatenate([before.start_box, pairs.source[pairs.kept]]),
            np.concatenate([now.start_box, pairs.target[pairs.kept]]),
        )
        return keypoints, view

    def execute(self, env: StackingEnv, trajectory: Trajectory, frames: list | None = None) -> Execution:
        return execute(env, trajectory, frames=frames)
