"""One demonstration, transported zero-shot through keypoints found in images.

:func:`record_source` takes the top-down RGB-D image before the demonstration and runs the scripted stacking in the
source scene. :func:`run_trial` takes the image of a new scene, matches it to the source's image (or uses the
simulator's exact pairs, ``backbone="oracle"``), lifts the pairs to 3-D, adds the end effector's start box, fits a
map ``phi`` from the source's points to the new ones, transports the demonstration through it
(:func:`kpflow.tasks.arm.transfer.transport_demo`) and executes it.

Besides success, each trial measures the 3-D error of the correspondences against where the simulator says the
source points went (:func:`~.keypoints.true_targets`), and how far the transported grasp is from the demonstrated
grasp carried by the cheese's true motion: its orientation error (deg, the cup turned by a half turn counts as the
same grasp of a box) and its position error.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from kpflow.maps.base import TransportMap
from kpflow.tasks.arm.keypoints import end_effector_box
from kpflow.tasks.arm.motion import yaw_of
from kpflow.tasks.arm.transfer import transport_demo
from kpflow.vision import DenseBackbone, rigidly_consistent

from .env import StackingEnv
from .keypoints import image_pairs, oracle_pairs, true_targets
from .objects import BLOCKS, CHEESE, LETTUCE
from .scene import SOURCE_SCENE, Scene
from .trajectory import execute, nearest_half_turn, plan_stacking

ORACLE = "oracle"
HALF_TURN = Rotation.from_euler("z", np.pi)


def _state(env: StackingEnv) -> dict:
    """The image, the blocks' poses and boxes, and the end effector's start box, now."""
    return {
        "image": env.render_topdown(),
        "poses": {name: env.object_pose(name) for name in BLOCKS},
        "boxes": {name: env.object_box(name) for name in BLOCKS},
        "start_box": end_effector_box(*env.ee_pose()),
    }


def record_source(env: StackingEnv, scene: Scene = SOURCE_SCENE) -> dict:
    """The source demonstration in ``scene``: ``image`` (before it), the blocks' ``poses`` and ``boxes``, the
    ``start_box`` keypoints, the ``trajectory`` and ``result`` (of running it, :func:`~.trajectory.execute`)."""
    env.reset_to(scene)
    state = _state(env)
    trajectory = plan_stacking(*env.ee_pose(), state["boxes"][CHEESE], state["boxes"][LETTUCE])
    return {"scene": scene, **state, "trajectory": trajectory, "result": execute(env, trajectory)}


def grasp_errors(source: dict, moved: dict, poses_now: dict) -> tuple[float, float]:
    """Orientation error (deg) and position error (mm) of the transported grasp (the first ``seal`` step) against
    the source's grasp carried by the cheese's true motion."""
    i = int(np.flatnonzero(source["trajectory"]["phases"] == "seal")[0])
    (p0, r0), (p1, r1) = source["poses"][CHEESE], poses_now[CHEESE]
    motion = Rotation.from_matrix(r1 @ r0.T)
    ideal = motion * Rotation.from_matrix(source["trajectory"]["rotations"][i])
    got = Rotation.from_matrix(moved["rotations"][i])
    angle = min((got.inv() * ideal).magnitude(), (got.inv() * HALF_TURN * ideal).magnitude())
    ideal_pos = motion.apply(source["trajectory"]["positions"][i] - p0) + p1
    return float(np.rad2deg(angle)), float(1e3 * np.linalg.norm(moved["positions"][i] - ideal_pos))


def run_trial(
    env: StackingEnv,
    source: dict,
    scene: Scene,
    backbone: DenseBackbone | str,
    make_map: Callable[[], TransportMap],
    max_pairs: int = 7,
    saliency_threshold: float = 0.2,
    seed: int = 0,
    spread: str = "descriptors",
    consistency: dict | None = None,
    frames: list | None = None,
) -> dict:
    """Set up ``scene``, find the keypoints (``backbone``, or ``"oracle"``; ``max_pairs``, ``saliency_threshold``,
    ``seed`` and ``spread`` as in :func:`kpflow.vision.match_features`), drop the image pairs that break rigidity
    (``consistency``: the arguments of :func:`kpflow.vision.rigidly_consistent`; None keeps every pair), transport
    the demonstration through the rest, execute.

    Returns ``success``/``failure`` (``"no correspondences"`` when no pair is left), the ``pairs`` (pixels, 3-D
    points, labels, ``errors_mm`` against the truth, ``kept``), ``n_pairs`` (kept) and ``rejected``, ``pairs_on``
    (block -> how many kept source points lie on it), ``pair_error_mm`` (median of the kept), ``grasp_error_deg``
    and ``grasp_error_mm``, ``place_yaw_error_deg`` (the cheese's yaw against the lettuce's at the end, half turns
    equal), ``max_std`` (of the map along the path), the ``trajectory``, the measured ``tip`` and ``now_rgb`` (the
    new scene's image).
    """
    oracle = isinstance(backbone, str)
    if oracle and backbone != ORACLE:
        raise ValueError(f"backbone must be a DenseBackbone or {ORACLE!r}, got {backbone!r}")
    env.reset_to(scene)
    now = _state(env)
    if oracle:
        pairs = oracle_pairs(source["image"], now["image"], source["boxes"], source["poses"], now["poses"])
    else:
        pairs = image_pairs(source["image"], now["image"], backbone, max_pairs, saliency_threshold, seed, spread)
    truth = true_targets(pairs["source"], pairs["labels"], source["poses"], now["poses"])
    pairs["errors_mm"] = 1e3 * np.linalg.norm(pairs["target"] - truth, axis=1)
    pairs["kept"] = np.ones(len(truth), bool)
    if consistency is not None and not oracle:
        pairs["kept"] = rigidly_consistent(pairs["source"], pairs["target"], **consistency)
    kept = pairs["kept"]
    record = {
        "scene": scene.as_dict(),
        "n_pairs": int(kept.sum()),
        "rejected": int((~kept).sum()),
        "pairs_on": {name: int(sum(bool(k) and label == name for k, label in zip(kept, pairs["labels"]))) for name in BLOCKS},
        "pair_error_mm": float(np.median(pairs["errors_mm"][kept])) if kept.any() else float("nan"),
        "pairs": pairs,
        "now_rgb": now["image"]["rgb"],
    }
    if not kept.any():
        nan = float("nan")
        return {**record, "success": False, "failure": "no correspondences", "grasp_error_deg": nan,
                "grasp_error_mm": nan, "place_yaw_error_deg": nan, "max_std": nan, "trajectory": None, "tip": None}  # fmt: skip
    kp_source = np.concatenate([source["start_box"], pairs["source"][kept]])
    kp_target = np.concatenate([now["start_box"], pairs["target"][kept]])
    moved = transport_demo(source["trajectory"], kp_source, kp_target, make_map)
    grasp_deg, grasp_mm = grasp_errors(source, moved, now["poses"])
    result = execute(env, moved, frames=frames)
    cheese_yaw, lettuce_yaw = yaw_of(env.object_pose(CHEESE)[1]), yaw_of(env.object_pose(LETTUCE)[1])
    place_yaw = abs(nearest_half_turn(cheese_yaw, lettuce_yaw) - lettuce_yaw)
    return {
        **record,
        "success": result["success"],
        "failure": result["failure"],
        "grasp_error_deg": grasp_deg,
        "grasp_error_mm": grasp_mm,
        "place_yaw_error_deg": float(np.rad2deg(place_yaw)),
        "max_std": float(moved["std"].max()),
        "trajectory": moved,
        "tip": result["tip"],
    }
