"""Draw docs/guides/robot-tasks.md's camera figure: one Stack and one Square scene as the front camera sees them, with
the simulator's keypoints (circles) and the ones perceived from the cameras with the default sensor noise (crosses).

Run: ``MUJOCO_GL=osmesa python docs/make_camera_figure.py`` (writes results/camera_keypoints.png).
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from kpflow.tasks.suite.cameras import SuiteCameras  # noqa: E402
from kpflow.tasks.suite.env import SuiteEnv  # noqa: E402
from kpflow.tasks.suite.keypoints import scene_keypoints  # noqa: E402
from kpflow.tasks.suite.perception import CameraKeypoints  # noqa: E402
from kpflow.tasks.suite.scene import sample_scene  # noqa: E402
from kpflow.tasks.suite.specs import task_spec  # noqa: E402
from kpflow.utils.io import atomic_path  # noqa: E402
from kpflow.vision.lifting import project_points  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "results" / "camera_keypoints.png"


def main() -> None:
    envs, panels = [], []
    for task, index in (("stack", 1), ("square", 0)):
        spec = task_spec(task)
        env = SuiteEnv(spec, render=True)
        envs.append(env)  # kept alive: freeing one environment's GL context while another renders breaks it
        env.reset_to(sample_scene(spec, env, "wide", index))
        perception = CameraKeypoints(seed=0)
        frames = perception.frames(env)
        names = [spec.grasp, spec.target]
        true = np.concatenate([scene_keypoints(env, spec, n) for n in names])
        seen = np.concatenate([perception.scene_keypoints(env, spec, frames, n) for n in names])
        front = frames[0]
        clean = SuiteCameras().capture(env)[0]  # the true calibration, for drawing
        panels.append((f"{spec.env_name}, wide scene {index}", front.rgb, [project_points(p, clean.intrinsics, clean.cam_to_world, 0.5)[0].numpy() for p in (true, seen)],
                       np.linalg.norm(seen - true, axis=1)))  # fmt: skip
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.8))
    for ax, (title, rgb, (true_px, seen_px), errors) in zip(axes, panels):
        lo, hi = np.floor(true_px.min(0)) - 70, np.ceil(true_px.max(0)) + 70  # the table around the objects
        x0, y0 = np.maximum(lo, 0).astype(int)
        x1, y1 = np.minimum(hi, [rgb.shape[1], rgb.shape[0]]).astype(int)
        ax.imshow(rgb[y0:y1, x0:x1], extent=(x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5))
        ax.scatter(*true_px.T, s=60, facecolors="none", edgecolors="lime", linewidths=1.5, label="simulator")
        ax.scatter(*seen_px.T, s=40, marker="x", color="red", linewidths=1.5, label="cameras (D435 noise)")
        ax.set_title(f"{title}: median error {1e3 * np.median(errors):.1f} mm")
        ax.set_axis_off()
    axes[0].legend(loc="lower left")
    fig.tight_layout()
    with atomic_path(OUT) as tmp:
        fig.savefig(tmp, format="png", dpi=90)


if __name__ == "__main__":
    main()
