"""Keypoints from cameras against the simulator's, per task and object kind, clean and with the default sensor noise,
and what perceiving costs.

Run::

    MUJOCO_GL=osmesa python benchmarks/camera_keypoints.py [--scenes 100] [--variants d0 wide] [--out PATH]

For each task (Lift, Stack, PickPlaceCan, NutAssemblySquare) and variant, ``--scenes`` scenes of the evaluation
stream (seed 0, the scenes the suite's policy rows use) are set up with the arm at home; the default cameras
(``frontview``, ``birdview``, ``agentview``, 640 x 480) capture them, and every keypoint of the object picked and of
its goal (:func:`~kpflow.tasks.suite.keypoints.scene_keypoints`, in the simulator's order and symmetry) is compared
with :class:`~kpflow.tasks.suite.perception.CameraKeypoints`' (``CameraNoise.off()``: clean; ``CameraNoise()``: a
RealSense D435's noise, mask errors and a calibration's pose error, seeded). Errors: per keypoint, the distance in
mm; medians and 90th percentiles over all keypoints of a kind. Cost, one thread: the capture (rendering three
RGB-D-segmentation frames, which a real camera does itself) and the extraction (noise, masks, lifting, boxes,
keypoints) per scene, medians.

Symmetric keypoints are ordered by the turn nearest the demonstration's yaw (the d0 source scene's, ``SOURCE_SEED``),
as generation orders them. Order lost: each object's noisy keypoints are shuffled and
:func:`kpflow.maps.match_keypoints` (``hungarian``) puts them back in the order of the demonstration's (the
simulator's keypoints of that object in the source scene); a scene counts as recovered when every keypoint of every
object lands on its own place. Again with one keypoint of the object picked dropped at random (an occluded corner;
``max_distance`` 3 cm leaves its partner unmatched). The markdown table is printed and written atomically to ``--out`` (default
``outputs/benchmarks/camera_keypoints.md``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse
import datetime
import platform
import time
from collections import defaultdict

import numpy as np
import torch

from kpflow.eval.stats import wilson_interval
from kpflow.generation.generate import SOURCE_SEED
from kpflow.geometry.angles import yaw_of
from kpflow.maps import match_keypoints
from kpflow.tasks.suite.cameras import SuiteCameras
from kpflow.tasks.suite.env import SuiteEnv
from kpflow.tasks.suite.keypoints import scene_keypoints
from kpflow.tasks.suite.perception import CameraKeypoints
from kpflow.tasks.suite.scene import sample_scene
from kpflow.tasks.suite.specs import task_spec
from kpflow.utils.io import publish
from kpflow.vision.noise import CameraNoise

TASKS = ("lift", "stack", "can", "square")


def order_recovered(demo: np.ndarray, seen: np.ndarray, rng: np.random.Generator, drop: bool) -> bool:
    """Whether :func:`match_keypoints` puts ``seen`` (ordered as ``demo``), shuffled and with one keypoint dropped
    when ``drop``, back in its order."""
    order = rng.permutation(len(seen))
    if drop:
        order = order[1:]
    match = match_keypoints(demo, seen[order], max_distance=0.03 if drop else None)
    perm = match.perm.numpy()
    truth = np.full(len(seen), -1)
    truth[order] = np.arange(len(order))  # where each keypoint went in the shuffled set
    return bool(np.array_equal(perm, truth))


def measure(tasks, variants, scenes: int):
    """Errors in mm per ``(task, variant, kind, noise)``, failures per the same, per task the capture and the
    noisy extraction times (ms), and per ``(task, variant, drop)`` whether matching recovered each scene's order."""
    errors, failures, recovered = defaultdict(list), defaultdict(int), defaultdict(list)
    capture_ms, extract_ms = defaultdict(list), defaultdict(list)
    envs = []  # every environment kept alive: freeing one's GL context while another renders breaks the other
    for task in tasks:
        spec = task_spec(task)
        env = SuiteEnv(spec, render=True)
        envs.append(env)
        cameras = SuiteCameras()
        names = [spec.grasp] + ([spec.target] if spec.target else [])
        env.reset_to(sample_scene(spec, env, "d0", 0, seed=SOURCE_SEED))
        demo_yaw = {n: yaw_of(env.object_pose(n)[1]) for n in names}
        demo = {n: scene_keypoints(env, spec, n, demo_yaw[n]) for n in names}
        match_rng = np.random.default_rng(0)
        for variant in (v for v in variants if v in spec.variants):
            perceivers = {
                "clean": CameraKeypoints(cameras, CameraNoise.off(), seed=0),
                "D435 noise": CameraKeypoints(cameras, CameraNoise(), seed=0),
            }
            for i in range(scenes):
                env.reset_to(sample_scene(spec, env, variant, i, seed=0))
                start = time.perf_counter()
                clean_frames = cameras.capture(env)
                capture_ms[task].append(1e3 * (time.perf_counter() - start))
                for label, perceiver in perceivers.items():
                    start = time.perf_counter()
                    frames = perceiver.sense(clean_frames)
                    seen = {}
                    for name in names:
                        key = (task, variant, spec.kinds[name], label)
                        try:
                            seen[name] = perceiver.scene_keypoints(env, spec, frames, name, demo_yaw[name])
                        except ValueError:
                            failures[key] += 1
                            continue
                        errors[key].extend(
                            1e3 * np.linalg.norm(seen[name] - scene_keypoints(env, spec, name, demo_yaw[name]), axis=1)
                        )
                    if label == "D435 noise":
                        extract_ms[task].append(1e3 * (time.perf_counter() - start))
                        if len(seen) == len(names):
                            for drop in (False, True):
                                ok = [
                                    order_recovered(demo[n], seen[n], match_rng, drop and n == spec.grasp)
                                    for n in names
                                ]
                                recovered[(task, variant, drop)].append(all(ok))
            print(f"{task} {variant}: {scenes} scenes", flush=True)
    return errors, failures, capture_ms, extract_ms, recovered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=100)
    parser.add_argument("--variants", nargs="+", default=["d0", "wide"])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--out", default="outputs/benchmarks/camera_keypoints.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    errors, failures, capture_ms, extract_ms, recovered = measure(args.tasks, args.variants, args.scenes)
    rows = [
        f"# Keypoints from cameras against the simulator's ({datetime.date.today()}, {platform.processor() or platform.machine()}, one thread)",
        "",
        f"`python benchmarks/camera_keypoints.py --scenes {args.scenes} --variants {' '.join(args.variants)}`: cameras "
        f"{', '.join(SuiteCameras().names)} at {SuiteCameras().width} x {SuiteCameras().height}; the arm at home.",
        "",
        "| task | variant | object kind | clean: median / p90 mm | D435 noise: median / p90 mm | not placed (clean / noisy) |",
        "|---|---|---|---|---|---|",
    ]
    for (task, variant, kind, label), e in sorted(errors.items()):
        if label != "clean":
            continue
        noisy = np.asarray(errors[(task, variant, kind, "D435 noise")])
        cells = [f"{np.median(x):.1f} / {np.percentile(x, 90):.1f}" if len(x) else "-" for x in (np.asarray(e), noisy)]
        rows.append(f"| {task} | {variant} | {kind} | {cells[0]} | {cells[1]} | "
                    f"{failures[(task, variant, kind, 'clean')]} / {failures[(task, variant, kind, 'D435 noise')]} |")  # fmt: skip
    rows += [
        "",
        "| task | capture: 3 RGB-D + segmentation renders, ms (median) | extraction with noise, ms per scene (median) |",
        "|---|---|---|",
    ]
    rows += [
        f"| {task} | {np.median(capture_ms[task]):.0f} | {np.median(extract_ms[task]):.0f} |"
        for task in args.tasks
        if capture_ms[task]
    ]
    rows += ["", "Order lost (D435 noise): scenes whose shuffled keypoints `match_keypoints` put back in the demonstration's order.", "",
             "| task | variant | all keypoints [95% CI] | one keypoint dropped [95% CI] |", "|---|---|---|---|"]  # fmt: skip
    for task in args.tasks:
        for variant in args.variants:
            cells = []
            for drop in (False, True):
                r = recovered.get((task, variant, drop), [])
                lo, hi = wilson_interval(sum(r), len(r)) if r else (0.0, 0.0)
                cells.append(f"{sum(r)}/{len(r)} [{100 * lo:.0f}, {100 * hi:.0f}]" if r else "-")
            if any(c != "-" for c in cells):
                rows.append(f"| {task} | {variant} | {cells[0]} | {cells[1]} |")
    publish(args.out, rows)


if __name__ == "__main__":
    main()
