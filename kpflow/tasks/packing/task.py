"""Packing behind the task contract (:class:`~kpflow.tasks.base.ArmTask`): the scripted demonstration in the
source scene, then in each new scene the 32 keypoints from the camera (start box, object box, lifted box,
container) that the policy fits its map on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpflow.tasks.arm.motion import yaw_of
from kpflow.tasks.base import ArmTask, Demonstration, Execution, Keypoints, Trajectory

from .demonstrator import execute, plan_packing
from .env import PackingEnv
from .keypoints import packing_keypoints
from .scene import CONDITIONS, SOURCE_SCENE, TABLE_TOP, Scene, sample_scene

CAMERA = "camera"  # packing's one keypoint source


@dataclass(frozen=True)
class PackingView:
    """What the camera gave in a scene: the 32 ``keypoints [32, 3]``, the object ``box`` they came from
    (:func:`~.perception.object_box`) and, for scoring the perception, the simulator's ``true_box``
    ``(centre, rotation, half extents)``, read before anything moved."""

    keypoints: np.ndarray
    box: dict
    true_box: tuple


class PackingTask(ArmTask):
    """Pack one object into the container; ``source`` overrides the demonstration's scene (a dict of
    :class:`~.scene.Scene` fields)."""

    name = "packing"
    conditions = CONDITIONS
    keypoint_sources = (CAMERA,)

    def __init__(self, camera_size: tuple[int, int] = (480, 640), source: dict | None = None):
        self.camera_size = tuple(camera_size)
        self.source_scene = Scene(**{k: (tuple(v) if k != "object_type" else v) for k, v in source.items()}) if source else SOURCE_SCENE

    def make_env(self) -> PackingEnv:
        return PackingEnv(camera_size=self.camera_size)

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Scene:
        return sample_scene(condition, index, seed, self.source_scene)

    def _view(self, env: PackingEnv, scene: Scene, reference_yaw: float) -> PackingView:
        env.reset_to(scene)
        kp = packing_keypoints(env, reference_yaw=reference_yaw)
        return PackingView(kp["keypoints"], kp["box"], env.object_box())

    def demonstrate(self, env: PackingEnv) -> Demonstration:
        scene = self.source_scene
        view = self._view(env, scene, scene.object_pose[2])
        container_pos, container_rot = env.container_frame()
        trajectory = plan_packing(*env.ee_pose(), view.box, container_pos, yaw_of(container_rot), TABLE_TOP)
        return Demonstration(scene, view, trajectory, execute(env, trajectory))

    def observe(self, env: PackingEnv, scene: Scene, source: Demonstration, keypoint_source=CAMERA) -> tuple[Keypoints, PackingView]:
        if keypoint_source != CAMERA:
            raise ValueError(f"packing finds its keypoints with the {CAMERA!r} only, not {keypoint_source!r}")
        view = self._view(env, scene, source.observation.box["yaw"])
        return Keypoints(source.observation.keypoints, view.keypoints), view

    def execute(self, env: PackingEnv, trajectory: Trajectory, frames: list | None = None) -> Execution:
        return execute(env, trajectory, frames=frames)
