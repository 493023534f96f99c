"""Recovery of the true keypoint order by each matcher of ``kpflow.maps.match_keypoints``.

Run::

    python benchmarks/matching.py [--trials N] [--slow-trials N] [--methods NAME ...] [--out PATH]

Sets: Push-T's 12 T keypoints (px; any rotation in the plane, 2 px noise), a box's 8 corners plus an off-centre
handle (m; any yaw, 2 mm noise: one true order) and the bare 8 corners (symmetric under half turns: an order
counts as recovered when it is one of the equivalent ones and ``ambiguous`` is set; so does a box with a handle
whose visible keypoints have lost what broke the symmetry). Each trial rotates the set
by a random angle, translates it, adds Gaussian noise, shuffles it, and then adds outliers (uniform points over
the set's bounding box, grown by a quarter) or drops a share of the target's points (missing). A trial succeeds
when every source keypoint with a counterpart is matched to it and every one without is left unmatched.
``max_distance`` is five times the noise. Rates over ``--trials`` seeded trials per cell, with 95% Wilson
intervals (``--slow-trials`` for CPD and entropic OT, which take 10-100x longer), and the median time per match.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy and torch are imported

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from kpflow.eval.stats import wilson_interval  # noqa: E402
from kpflow.maps.matching import METHODS, match_keypoints  # noqa: E402
from kpflow.tasks.pusht.geometry import T_KEYPOINTS  # noqa: E402
from kpflow.utils.io import write_text  # noqa: E402

BOX = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.03, 0.03) for z in (-0.02, 0.02)])
SETS = {  # name -> (points, noise, under the box's symmetries, in the plane)
    "Push-T T (12, px)": (np.asarray(T_KEYPOINTS, float), 2.0, False, True),
    "box + handle (9, m)": (np.concatenate([BOX, [[0.03, 0.05, 0.0]]]), 0.002, False, False),
    "box corners (8, m)": (BOX, 0.002, True, False),
}
BOX_SYMMETRIES = [np.diag(s) for s in ([1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1])]
CONDITIONS = ("clean", "outliers 10%", "outliers 30%", "missing 10%", "missing 30%")


def trial(points: np.ndarray, noise: float, planar: bool, condition: str, rng: np.random.Generator):
    """A corrupted, moved, shuffled copy of ``points`` and the true ``perm`` (-1 where the target lacks it)."""
    n, d = points.shape
    angle = rng.uniform(-np.pi, np.pi)
    rot = (
        np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        if planar
        else Rotation.from_euler("z", angle).as_matrix()
    )
    spread = np.linalg.norm(points - points.mean(0), axis=1).mean()
    moved = points @ rot.T + rng.normal(0, spread, d) + rng.normal(0, noise, (n, d))
    order = rng.permutation(n)
    target, truth = moved[order], np.argsort(order)  # target[truth[i]] is source i
    share = float(condition.split()[-1].rstrip("%")) / 100 if condition != "clean" else 0.0
    k = int(round(share * n))
    if condition.startswith("outliers") and k:
        lo, hi = moved.min(0), moved.max(0)
        pad = 0.25 * (hi - lo)
        target = np.concatenate([target, rng.uniform(lo - pad, hi + pad, (k, d))])
    if condition.startswith("missing") and k:
        drop = rng.choice(n, k, replace=False)  # target rows removed
        keep = np.setdiff1d(np.arange(n), drop)
        new_index = np.full(n, -1)
        new_index[keep] = np.arange(len(keep))
        target, truth = target[keep], new_index[truth]
    return target, truth


def symmetry_images(points: np.ndarray, symmetric_group: bool) -> list[np.ndarray]:
    """For each proper symmetry of the box (identity first), source index i -> the index of its image (-1: its
    image is no keypoint, e.g. the handle's)."""
    if not symmetric_group:
        return [np.arange(len(points))]
    images = []
    for sym in BOX_SYMMETRIES:
        d = ((points[:, None] - (points @ sym.T)[None]) ** 2).sum(-1)  # [image candidate j, i]
        images.append(np.where(d.min(0) < 1e-12, d.argmin(0), -1))
    return images


def recovered(result, truth: np.ndarray, images: list[np.ndarray]) -> tuple[bool, bool]:
    """(recovered, order unique). A symmetry g of the source set explains the target as well as the truth when
    every keypoint it sends off the set (the handle, for a half turn) is missing from the target: then the source
    sent onto each visible target point under g is another, equally good answer. The order is unique when only the
    identity qualifies; otherwise any of the equivalent orders counts, with ``ambiguous`` set."""
    perm = result.perm.numpy()
    expected = []
    for image in images:
        if np.all(truth[image < 0] < 0):
            expected.append(np.where(image >= 0, truth[np.maximum(image, 0)], -1))
    unique = len(expected) == 1
    hit = any(np.array_equal(perm, e) for e in expected)
    return bool(hit and (unique or result.ambiguous)), unique


SLOW = ("cpd", "cpd_nonrigid", "ot")


def run(
    trials: int, slow_trials: int, methods: list[str], sets: list[str] | None = None, progress: bool = True
) -> list[dict]:
    rows = []
    cells = [(s, c, m) for s in (sets or SETS) for c in CONDITIONS for m in methods]
    for set_name, condition, method in tqdm(cells, desc="matching cells", unit="cell", disable=not progress):
        points, noise, boxlike, planar = SETS[set_name]
        images = symmetry_images(points, boxlike)
        rng = np.random.default_rng(0)  # the same trials for every method
        hits, unique_hits, unique, times, n = 0, 0, 0, [], slow_trials if method in SLOW else trials
        for _ in range(n):
            target, truth = trial(points, noise, planar, condition, rng)
            start = time.perf_counter()
            result = match_keypoints(
                points, target, method=method, max_distance=5 * noise, n_starts=12 if planar else 8
            )
            times.append(time.perf_counter() - start)
            hit, is_unique = recovered(result, truth, images)
            hits, unique, unique_hits = hits + hit, unique + is_unique, unique_hits + (hit and is_unique)
        rows.append({"set": set_name, "condition": condition, "method": method, "trials": n, "hits": hits,
                     "ci": wilson_interval(hits, n), "unique": unique, "unique_hits": unique_hits,
                     "ms": 1e3 * float(np.median(times))})  # fmt: skip
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        "# Keypoint matching: true order recovered (any rotation, 2 px / 2 mm noise, max_distance = 5 x noise)",
        "",
        "| set | condition | method | recovered [95% CI] | of the trials with a unique order | median ms |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lo, hi = r["ci"]
        lines.append(f"| {r['set']} | {r['condition']} | {r['method']} | {100 * r['hits'] / r['trials']:.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]"
                     f" of {r['trials']} | {r['unique_hits']}/{r['unique']} | {r['ms']:.1f} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--slow-trials", type=int, default=20)
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--sets", nargs="*", default=list(SETS), choices=list(SETS))
    parser.add_argument("--out", default="outputs/benchmarks/matching.md")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")  # POT's and pycpd's convergence chatter
    text = table(run(args.trials, args.slow_trials, args.methods, args.sets))
    write_text(Path(args.out), text)
    print(text)
    return text


if __name__ == "__main__":
    main()
