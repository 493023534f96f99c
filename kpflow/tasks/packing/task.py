"""Packing behind the task contract (:class:`~kpflow.core.task.ArmTask`): the scripted demonstration in the
source scene, then in each new scene the 32 keypoints from the camera (start box, object box, lifted box,
container) that the policy fits its map on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpflow.core.task import ArmTask, Demonstration, Execution
from kpflow.geometry.angles import yaw_of
from kpflow.trajectory import Keypoints, Trajectory
from kpflow.vision.keypoint_source import KeypointSource

from .demonstrator import execute, plan_packing
from .env import PackingEnv
from .keypoints import packing_keypoints
from .perception import PackingCamera, container_pose, object_box, true_object_box
from .scene import CONDITIONS, SOURCE_SCENE, TABLE_TOP, Scene, sample_scene


@dataclass(frozen=True)
class PackingView:
    """What a scene showed: the 32 ``keypoints [32, 3]``, the object ``box`` they came from
    (:func:`~.perception.object_box` or :func:`~.perception.true_object_box`), the ``container_yaw`` they used and,
    for scoring the perception, the simulator's ``true_box`` ``(centre, rotation, half extents)``, read before
    anything moved."""

    keypoints: np.ndarray
    box: dict
    true_box: tuple
    container_yaw: float = 0.0


class PackingTask(ArmTask):
    """Pack one object into the container; ``source`` overrides the demonstration's scene (a dict of
    :class:`~.scene.Scene` fields); ``keypoints`` says where the object's box and the container's pose come from
    (:class:`~kpflow.vision.keypoint_source.KeypointSource`; None: the simulator's; ``kind="camera"``: the top-down
    camera with its ``noise``, at its own ``camera_size``)."""

    name = "packing"
    conditions = CONDITIONS

    def __init__(
        self,
        camera_size: tuple[int, int] = (480, 640),
        source: dict | None = None,
        keypoints: KeypointSource | None = None,
    ):
        self.camera_size = tuple(camera_size)
        self.source_scene = (
            Scene(**{k: (tuple(v) if k != "object_type" else v) for k, v in source.items()}) if source else SOURCE_SCENE
        )
        self.keypoints = keypoints or KeypointSource()
        self.keypoint_sources = (self.keypoints.kind,)
        if self.keypoints.camera and (self.keypoints.segmenter is not None or self.keypoints.cameras or
                                      (self.keypoints.height, self.keypoints.width) != self.camera_size):  # fmt: skip
            raise ValueError("packing's camera is its one top-down camera at camera_size, with the renderer's masks: "
                             "keypoints.cameras, keypoints.height/width and keypoints.segmenter are not used here")  # fmt: skip
        self.camera = PackingCamera(self.keypoints.noise, self.keypoints.seed) if self.keypoints.camera else None

    def make_env(self) -> PackingEnv:
        return PackingEnv(camera_size=self.camera_size)

    def sample_scene(self, condition: str, index: int, seed: int = 0) -> Scene:
        return sample_scene(condition, index, seed, self.source_scene)

    def _view(
        self, env: PackingEnv, scene: Scene, reference_yaw: float, container_yaw: float | None = None
    ) -> PackingView:
        """The scene's keypoints: the object's box and the container's pose from the simulator, or from the camera
        (reseeded by the scene, so a scene shows the same whichever came before); the symmetric ones ordered by
        the turns nearest ``reference_yaw`` (the object's) and ``container_yaw``."""
        env.reset_to(scene)
        true_box = env.object_box()
        if self.camera is None:
            box = true_object_box(env, TABLE_TOP, reference_yaw)
            pos, rot = env.container_frame()
            centre, yaw = pos, yaw_of(rot)
        else:
            self.camera.reseed(*(round(1e4 * v) % 2**31 for v in (*scene.object_pose, *scene.container_pose)))
            image = self.camera.image(env)
            box = object_box(image, TABLE_TOP, reference_yaw)
            centre, yaw = container_pose(image, container_yaw)
        return PackingView(packing_keypoints(env.ee_pose(), box, centre, yaw), box, true_box, yaw)

    def demonstrate(self, env: PackingEnv) -> Demonstration:
        scene = self.source_scene
        view = self._view(env, scene, scene.object_pose[2])
        container_pos, container_rot = env.container_frame()
        trajectory = plan_packing(*env.ee_pose(), view.box, container_pos, yaw_of(container_rot), TABLE_TOP)
        return Demonstration(scene, view, trajectory, execute(env, trajectory))

    def observe(
        self, env: PackingEnv, scene: Scene, source: Demonstration, keypoint_source: str | None = None
    ) -> tuple[Keypoints, PackingView]:
        if keypoint_source not in (None, self.keypoints.kind):
            raise ValueError(
                f"this packing task reads its keypoints from {self.keypoints.kind!r}, not {keypoint_source!r} (keypoints=...)"
            )
        view = self._view(env, scene, source.observation.box["yaw"], source.observation.container_yaw)
        return Keypoints(source.observation.keypoints, view.keypoints), view

    def execute(self, env: PackingEnv, trajectory: Trajectory, frames: list | None = None) -> Execution:
        return execute(env, trajectory, frames=frames)
