"""RGB-D cameras in the benchmark tasks: robosuite's renderer as the sensor, robosuite's camera utilities as the
calibration.

:class:`SuiteCameras` renders, for each named camera of the task's model (``frontview``, ``birdview``,
``agentview``, ``sideview``, ...), the colour image, the depth (MuJoCo's normalised z-buffer turned into metres by
``robosuite.utils.camera_utils.get_real_depth_map``; a broken one refused, :func:`kpflow.utils.offscreen.metric_depth`)
and the instance segmentation (the geom under each pixel), and
returns :class:`~kpflow.vision.cameras.CameraFrame` s with the intrinsics and the camera's world pose from
``get_camera_intrinsic_matrix`` / ``get_camera_extrinsic_matrix`` (OpenCV axes). OpenGL reads images bottom row
first; frames are flipped to a camera's top-row-first order, the order robosuite's intrinsics assume. The
environment must be built with ``render=True``.

:func:`object_geoms` names the instance ids of an object or fixture (every geom of its body and the bodies under
it), which is what the renderer's segmentation gives for a mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from robosuite.utils import camera_utils

from kpflow.utils.offscreen import metric_depth, render
from kpflow.vision.cameras import CameraFrame

#: the cameras used unless a config names others: one in front of the table, looking down at 15 degrees from the
#: horizontal... and one above it (the robot's arm hides less of the table from two sides)
DEFAULT_CAMERAS = ("frontview", "birdview", "agentview")


@dataclass(frozen=True)
class SuiteCameras:
    """Cameras of a :class:`~.env.SuiteEnv` (module docstring): their names and one image size."""

    names: tuple[str, ...] = DEFAULT_CAMERAS
    height: int = 480
    width: int = 640

    def __post_init__(self) -> None:
        if not self.names:
            raise ValueError("name at least one camera")
        if int(self.height) < 8 or int(self.width) < 8:
            raise ValueError(f"image size must be at least 8 x 8 pixels; got {self.height} x {self.width}")
        object.__setattr__(self, "names", tuple(self.names))

    def check_names(self, env) -> None:
        """Refuse cameras the model lacks (``ValueError`` naming them and the model's cameras)."""
        model = env.sim.model
        have = [model.camera_id2name(i) for i in range(model.ncam)]
        missing = [n for n in self.names if n not in have]
        if missing:
            raise ValueError(
                f"{env.spec.name} has no camera {missing}; its cameras are {have} (keypoints.cameras=[...])"
            )

    def check(self, env) -> None:
        """Refuse cameras the model lacks, or an environment that cannot render."""
        self.check_names(env)
        if not env.env.has_offscreen_renderer:
            raise ValueError(f"{env.spec.name}: build the environment with render=True to capture camera frames")

    def capture(self, env) -> list[CameraFrame]:
        """One :class:`CameraFrame` per camera, of the scene as it is now."""
        self.check(env)
        sim, h, w = env.sim, int(self.height), int(self.width)
        frames = []
        for name in self.names:  # each render in the env's own GL context (kpflow/utils/offscreen.py)
            rgb, depth = render(env, name, h, w, depth=True)
            seg = render(env, name, h, w, segmentation=True)
            ids = np.where(seg[..., 0] == mujoco.mjtObj.mjOBJ_GEOM, seg[..., 1], -1)
            frames.append(
                CameraFrame(
                    name,
                    np.ascontiguousarray(rgb[::-1]),
                    np.ascontiguousarray(
                        metric_depth(sim, depth, name)[::-1]
                    ),  # a broken z-buffer refused, not clipped
                    camera_utils.get_camera_intrinsic_matrix(sim, name, h, w),
                    camera_utils.get_camera_extrinsic_matrix(sim, name),
                    np.ascontiguousarray(ids[::-1]),
                )
            )
        return frames


def object_geoms(env, name: str) -> np.ndarray:
    """The geom ids (the renderer's instance ids) of object or fixture ``name``: every geom of its body and of the
    bodies under it."""
    model = env.sim.model
    root = env.object_body[name] if name in env.object_body else env.fixture_body[name]
    bodies, grew = {root}, True
    while grew:
        children = {b for b in range(model.nbody) if model.body_parentid[b] in bodies} - bodies
        bodies |= children
        grew = bool(children)
    return np.flatnonzero(np.isin(model.geom_bodyid, sorted(bodies)))
