"""Benchmark of kpflow's transportation maps, single-threaded on the CPU.

Run::

    python benchmarks/maps.py [--quick] [--out PATH] [--dtype float32|float64] [--profile]

(``make bench`` runs the full version). ``--quick`` is a smoke test (fewer repetitions and sizes, < 60 s);
the full run takes a few minutes. The markdown tables are printed and written atomically to ``--out``
(default ``outputs/benchmarks/maps.md``).

Everything runs on ONE thread (``OMP_NUM_THREADS=1`` is set before numpy/torch are imported, and
``torch.set_num_threads(1)``). Times are medians over repetitions measured with ``time.perf_counter`` after
untimed warm-up repetitions (two; one for slow cells); each repetition uses a fresh random problem (seeded).

Problem: N keypoints in 2-D, ``source`` uniform in a 512 x 512 px workspace; ``target`` = a smooth deformation
of ``source`` (a ~15 px random sine field) followed by a rigid motion (rotation up to +-30 degrees about the
workspace centre, translation up to +-51 px). M query points are uniform in the workspace. Inputs are made
into tensors (or numpy arrays for the baselines) before the clock starts.

Tables:

1. "fit + transport": every map family with its default settings (AffineMap rigid, ILWRMap, GPMap, FlowMap,
   MLPMap, EnsembleMap of 5 MLPMaps) for N in (10, 25, 100, 1000) keypoints and M in (20, 10 000) query
   points: median ``fit`` time, median ``map(x)`` time, and the keypoint residual max_i |phi(s_i) - t_i| (px;
   median over repetitions). Slow cells get fewer repetitions (a per-cell time budget; the ``reps`` column
   says how many were measured).
2. "vs the authors' library" (franzesegiovanni/gaussian_process_transportation, re-implemented in
   ``benchmarks/baselines.py``) on 25 keypoints and 20 query points: kpflow ILWRMap (float32 and float64)
   against the baseline ILWR (L-BFGS-B per step, beta = 0.9, 30 steps) and kpflow GPMap against the sklearn
   GP (C * RBF + White, 5 restarts). As in the authors' ``PolicyTransportation``, both baselines are fitted
   after a rigid (Kabsch) pre-alignment, which is timed with them. Ratios are baseline time / kpflow time
   from the same run. Then the issue's targets, each printed PASS or MISS.
3. "batched": one ILWRMap (and one AffineMap) fitted on 1000 different source sets ``[1000, 25, 2]`` to one
   target ``[25, 2]``, then transporting 20 points per set ``[1000, 20, 2]``.

``--learned CKPT`` appends the learned map's tables (``benchmarks/learned_map.py``: held-out Push-T pairs, beside
ILWR and GP in the same run; ``--learned-store`` names the demonstrations the sources come from).

``--profile`` adds a cProfile listing of ILWRMap fit + 20-point transport on 25 keypoints (where the time goes).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy / torch are imported

import argparse
import cProfile
import datetime
import functools
import io
import math
import platform
import pstats
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

torch.set_num_threads(1)
try:
    torch.set_num_interop_threads(1)
except RuntimeError:  # already set
    pass

sys.path.insert(0, str(Path(__file__).resolve().parent))  # for `import baselines` when run from anywhere

import baselines  # noqa: E402

from kpflow.maps import AffineMap, EnsembleMap, FlowMap, GPMap, ILWRMap, MLPMap  # noqa: E402
from kpflow.utils.io import write_text  # noqa: E402

WORKSPACE = 512.0  # px
DTYPES = {"float32": torch.float32, "float64": torch.float64}

# ---------------------------------------------------------------------------------------------- problems


def make_problem(seed: int, n: int, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """source [n,2], target [n,2], queries [m,2] in px (module docstring)."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(size=(n, 2)) * WORKSPACE
    w, phase = rng.normal(0.0, 2.0, size=(2, 2)), rng.uniform(0.0, 2 * np.pi, size=2)
    deformed = src + 0.03 * WORKSPACE * np.sin(src / WORKSPACE @ w + phase)
    theta = rng.uniform(-np.pi / 6, np.pi / 6)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    centre = np.full(2, WORKSPACE / 2)
    shift = rng.uniform(-0.1, 0.1, size=2) * WORKSPACE
    tgt = (deformed - centre) @ rot.T + centre + shift
    return src, tgt, rng.uniform(size=(m, 2)) * WORKSPACE


def residual_max(phi, src, tgt) -> float:
    """max_i |phi(src_i) - tgt_i| (untimed)."""
    with torch.no_grad():
        out = phi(src)
    if isinstance(out, torch.Tensor):
        return float((out - tgt).norm(dim=-1).max())
    return float(np.linalg.norm(out - tgt, axis=1).max())


# ---------------------------------------------------------------------------------------------- formatting


def fmt_ms(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "-"
    ms = seconds * 1e3
    return f"{ms:.3g}" if ms < 1000 else f"{ms:.0f}"


def fmt_px(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def warmup_reps(reps: int) -> int:
    """Untimed repetitions before the timed ones: 2 (1 for slow cells that get fewer than 5 repetitions)."""
    return 2 if reps >= 5 else 1


def median(xs) -> float:
    return float(np.median(xs)) if len(xs) else float("nan")


# ---------------------------------------------------------------------------------------------- table 1

FAMILIES = {  # name: factory of a map with default settings
    "AffineMap (rigid)": lambda: AffineMap("rigid"),
    "ILWRMap": ILWRMap,
    "GPMap": GPMap,
    "FlowMap": FlowMap,
    "MLPMap": MLPMap,
    "EnsembleMap (5 MLPMap)": functools.partial(EnsembleMap, MLPMap),
}


def bench_family(name, factory, n, ms, reps, budget, dtype):
    """Fit ``reps`` random problems (after warm-ups); returns fit times, transport times per M, residuals."""
    fit_t, res = [], []
    tr_t = {m: [] for m in ms}
    start, warmup = None, warmup_reps(reps)
    for rep in range(reps + warmup):
        src, tgt, _ = make_problem(1000 * n + rep, n, 0)
        s, t = torch.tensor(src, dtype=dtype), torch.tensor(tgt, dtype=dtype)
        queries = {m: torch.tensor(make_problem(7 + rep, 0, m)[2], dtype=dtype) for m in ms}
        t0 = time.perf_counter()
        phi = factory().fit(s, t)
        t1 = time.perf_counter()
        times = {}
        for m in ms:
            q = queries[m]
            t2 = time.perf_counter()
            phi(q)
            times[m] = time.perf_counter() - t2
        if rep < warmup:
            start = time.perf_counter()
            continue
        fit_t.append(t1 - t0)
        for m in ms:
            tr_t[m].append(times[m])
        res.append(residual_max(phi, s, t))
        if time.perf_counter() - start > budget:
            break
    return fit_t, tr_t, res


def table_fit_transport(cfg, dtype, log) -> str:
    rows = []
    for name, factory in FAMILIES.items():
        for n in cfg["sizes"]:
            skip = cfg["skip"].get((name, n))
            if skip:
                rows.append([name, str(n), "all", f"skipped ({skip})", "", "", ""])
                continue
            reps = cfg["reps"].get(name, cfg["reps_default"])
            if n >= 1000:
                reps = min(reps, cfg["reps_1000"].get(name, reps))
            t0 = time.perf_counter()
            fit_t, tr_t, res = bench_family(name, factory, n, cfg["queries"], reps, cfg["budget"], dtype)
            log(
                f"  {name:24s} N={n:5d}: fit {fmt_ms(median(fit_t))} ms, {len(fit_t)} reps, "
                f"{time.perf_counter() - t0:.1f} s"
            )
            for j, m in enumerate(cfg["queries"]):
                rows.append(
                    [
                        name if j == 0 else "",
                        str(n) if j == 0 else "",
                        str(m),
                        fmt_ms(median(fit_t)) if j == 0 else "\u2033",
                        fmt_ms(median(tr_t[m])),
                        fmt_px(median(res)) if j == 0 else "\u2033",
                        str(len(fit_t)),
                    ]
                )
    header = ["map", "N keypoints", "M queries", "fit ms", "transport ms", "residual px", "reps"]
    return table(header, rows)


# ---------------------------------------------------------------------------------------------- table 2


def kabsch_np(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid least-squares fit (rotation R, translation t) of tgt ~ src @ R.T + t, as the authors' pre-alignment."""
    ms, mt = src.mean(0), tgt.mean(0)
    u, _, vt = np.linalg.svd((src - ms).T @ (tgt - mt))
    e = np.ones(src.shape[1])
    e[-1] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ (e[:, None] * u.T)
    return r, mt - r @ ms


def baseline_ilwr(src, tgt, q):
    r, t = kabsch_np(src, tgt)
    params = baselines.ilwr_fit(src @ r.T + t, tgt, n_steps=30, beta=0.9)
    baselines.ilwr_transport(params, q @ r.T + t)
    return lambda x: baselines.ilwr_transport(params, x @ r.T + t)


def baseline_gp(src, tgt, q):
    r, t = kabsch_np(src, tgt)
    model = baselines.sklearn_gp_fit(src @ r.T + t, tgt, n_restarts=5)
    baselines.sklearn_gp_transport(model, q @ r.T + t)
    return lambda x: baselines.sklearn_gp_transport(model, x @ r.T + t)[0]


def kpflow_runner(factory, dtype, method="forward"):
    def run(src, tgt, q):
        phi = factory().fit(src, tgt)
        phi.predict(q) if method == "predict" else phi(q)
        return phi

    run.dtype = dtype
    return run


def bench_problem_runner(run, n, m, reps, budget):
    """Time ``run(src, tgt, q)`` (fit + transport) on ``reps`` random problems after warm-ups."""
    times, res = [], []
    start, warmup = None, warmup_reps(reps)
    dtype = getattr(run, "dtype", None)
    for rep in range(reps + warmup):
        src, tgt, q = make_problem(rep, n, m)
        if dtype is not None:
            src, tgt, q = (torch.tensor(a, dtype=dtype) for a in (src, tgt, q))
        t0 = time.perf_counter()
        phi = run(src, tgt, q)
        dt = time.perf_counter() - t0
        if rep < warmup:
            start = time.perf_counter()
            continue
        times.append(dt)
        res.append(residual_max(phi, src, tgt))
        if time.perf_counter() - start > budget:
            break
    return times, res


def table_vs_authors(cfg, log) -> tuple[str, dict]:
    n, m, reps, budget = 25, 20, cfg["reps_vs"], cfg["budget_vs"]
    runs = {
        "kpflow ILWRMap float32": kpflow_runner(ILWRMap, torch.float32),
        "kpflow ILWRMap float64": kpflow_runner(ILWRMap, torch.float64),
        "baseline ILWR (scipy L-BFGS-B, beta=0.9, 30 steps)": baseline_ilwr,
        "kpflow GPMap float32": kpflow_runner(GPMap, torch.float32),
        "kpflow GPMap float64": kpflow_runner(GPMap, torch.float64),
        "kpflow GPMap float64, predict (mean + var)": kpflow_runner(GPMap, torch.float64, "predict"),
        "baseline sklearn GP (C*RBF+White, 5 restarts)": baseline_gp,
    }
    out = {}
    for name, run in runs.items():
        t0 = time.perf_counter()
        out[name] = bench_problem_runner(run, n, m, reps, budget)
        log(
            f"  {name:50s} {fmt_ms(median(out[name][0]))} ms, {len(out[name][0])} reps, {time.perf_counter() - t0:.1f} s"
        )
    base_of = {
        "ILWR": "baseline ILWR (scipy L-BFGS-B, beta=0.9, 30 steps)",
        "GP": "baseline sklearn GP (C*RBF+White, 5 restarts)",
    }
    rows = []
    for name, (times, res) in out.items():
        kind = "ILWR" if "ILWR" in name else "GP"
        base_t, base_r = out[base_of[kind]]
        if name.startswith("baseline"):
            ratio, wins = "1 (reference)", "-"
        else:
            ratio = f"{median(base_t) / median(times):.2f}x"
            k = min(len(res), len(base_r))  # same seeds: problem i is the same for both
            wins = f"{np.mean(np.array(res[:k]) <= np.array(base_r[:k]) * (1 + 1e-6)):.0%}"
        rows.append(
            [name, fmt_ms(median(times)), fmt_px(median(res)), fmt_px(float(np.max(res))), ratio, wins, str(len(times))]
        )
    header = [
        "method",
        "fit + 20-pt transport ms",
        "residual px (median)",
        "residual px (worst)",
        "speed-up vs baseline (baseline ms / this ms)",
        "problems with residual <= baseline's",
        "reps",
    ]
    return table(header, rows), out


# ---------------------------------------------------------------------------------------------- table 3


def make_batch(seed: int, b: int, n: int, m: int):
    """``b`` different source sets [b,n,2] (rigid + deformed copies of one layout) -> one target [n,2]; queries [b,m,2]."""
    rng = np.random.default_rng(seed)
    tgt = rng.uniform(size=(n, 2)) * WORKSPACE
    srcs = np.empty((b, n, 2))
    for i in range(b):  # source_i = rigid_i(deform_i(target)): each set sees the layout differently
        r2 = np.random.default_rng((seed, i))
        w, phase = r2.normal(0.0, 2.0, size=(2, 2)), r2.uniform(0, 2 * np.pi, size=2)
        deformed = tgt + 0.03 * WORKSPACE * np.sin(tgt / WORKSPACE @ w + phase)
        theta = r2.uniform(-np.pi / 6, np.pi / 6)
        rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
        c = np.full(2, WORKSPACE / 2)
        srcs[i] = (deformed - c) @ rot.T + c + r2.uniform(-0.1, 0.1, size=2) * WORKSPACE
    return srcs, tgt, rng.uniform(size=(b, m, 2)) * WORKSPACE


def table_batched(cfg, log) -> tuple[str, dict]:
    b, n, m = 1000, 25, 20
    rows, out = [], {}
    for name, factory in (("ILWRMap", ILWRMap), ("AffineMap (rigid)", lambda: AffineMap("rigid"))):
        for dname, dtype in DTYPES.items():
            fit_t, tr_t, res_med, res_worst = [], [], [], []
            warmup = warmup_reps(cfg["reps_batch"])
            for rep in range(cfg["reps_batch"] + warmup):
                srcs, tgt, q = make_batch(rep, b, n, m)
                s, t, qq = (torch.tensor(a, dtype=dtype) for a in (srcs, tgt, q))
                t0 = time.perf_counter()
                phi = factory().fit(s, t)
                t1 = time.perf_counter()
                y = phi(qq)
                t2 = time.perf_counter()
                assert y.shape == (b, m, 2)
                if rep < warmup:
                    continue
                fit_t.append(t1 - t0), tr_t.append(t2 - t1)
                with torch.no_grad():
                    r = (phi(s) - t).norm(dim=-1).amax(-1)  # [b]
                res_med.append(float(r.median())), res_worst.append(float(r.max()))
            # sanity: the batched fit equals fitting each set on its own (untimed, 5 sets)
            diff = 0.0
            for i in range(5):
                single = factory().fit(s[i], t)
                diff = max(diff, float((single(qq[i]) - y[i]).abs().max()))
            total = [a + c for a, c in zip(fit_t, tr_t)]
            out[(name, dname)] = total
            log(f"  {name:20s} {dname}: fit+transport {median(total):.3f} s, {len(total)} reps")
            rows.append(
                [
                    name,
                    dname,
                    f"{median(fit_t):.4f}",
                    f"{median(tr_t):.4f}",
                    f"{median(total):.4f}",
                    f"{median(total) / b * 1e3:.3g}",
                    fmt_px(median(res_med)),
                    fmt_px(max(res_worst)),
                    f"{diff:.1e}",
                    str(len(total)),
                ]
            )
    header = [
        "map",
        "dtype",
        "fit s",
        "transport s (20 pts/set)",
        "fit + transport s",
        "ms per set",
        "residual px (median set)",
        "residual px (worst set)",
        "max abs diff vs unbatched fits (5 sets)",
        "reps",
    ]
    return table(header, rows), out


# ---------------------------------------------------------------------------------------------- targets


def targets_section(vs, batch) -> str:
    rows = []
    base_t, base_r = vs["baseline ILWR (scipy L-BFGS-B, beta=0.9, 30 steps)"]
    for dname in DTYPES:
        t, r = vs[f"kpflow ILWRMap {dname}"]
        ok = median(t) <= 1e-3 and median(r) <= median(base_r)
        rows.append(
            [
                f"ILWRMap {dname}: fit + 20-pt transport <= 1 ms, residual <= baseline's",
                f"{fmt_ms(median(t))} ms; residual {fmt_px(median(r))} px vs baseline {fmt_px(median(base_r))} px",
                "PASS" if ok else "MISS",
            ]
        )
    for dname in DTYPES:
        t, _ = vs[f"kpflow GPMap {dname}"]
        rows.append(
            [
                f"GPMap {dname}: fit + 20-pt transport <= 15 ms",
                f"{fmt_ms(median(t))} ms",
                "PASS" if median(t) <= 15e-3 else "MISS",
            ]
        )
    for dname in DTYPES:
        t = batch[("ILWRMap", dname)]
        rows.append(
            [
                f"ILWRMap {dname}: batch of 1000 source sets (fit + 20-pt transport) <= 0.5 s",
                f"{median(t):.3f} s",
                "PASS" if median(t) <= 0.5 else "MISS",
            ]
        )
    return table(["target", "measured (median)", "verdict"], rows)


def profile_ilwr(reps: int = 200) -> str:
    src, tgt, q = (torch.tensor(a, dtype=torch.float32) for a in make_problem(0, 25, 20))
    ILWRMap().fit(src, tgt)(q)
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(reps):
        ILWRMap().fit(src, tgt)(q)
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(15)
    return f"cProfile of {reps} x (ILWRMap().fit(25 keypoints) + 20-point transport), float32, sorted by own time:\n\n```\n{buf.getvalue().strip()}\n```"


# ---------------------------------------------------------------------------------------------- main


def config(quick: bool) -> dict:
    if quick:
        return dict(
            sizes=(10, 25),
            queries=(20, 10_000),
            reps_default=5,
            budget=2.0,
            reps={"FlowMap": 1, "MLPMap": 2, "EnsembleMap (5 MLPMap)": 1},
            reps_1000={},
            skip={},
            reps_vs=10,
            budget_vs=3.0,
            reps_batch=2,
        )
    return dict(
        sizes=(10, 25, 100, 1000),
        queries=(20, 10_000),
        reps_default=30,
        budget=15.0,
        reps={"FlowMap": 7, "MLPMap": 11, "GPMap": 21, "EnsembleMap (5 MLPMap)": 5},
        reps_1000={"GPMap": 3, "FlowMap": 3, "MLPMap": 5, "EnsembleMap (5 MLPMap)": 1},
        skip={},
        reps_vs=50,
        budget_vs=30.0,
        reps_batch=10,
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="smoke test: fewer repetitions and sizes (< 60 s)")
    ap.add_argument("--out", type=Path, default=Path("outputs/benchmarks/maps.md"), help="markdown output file")
    ap.add_argument("--dtype", choices=tuple(DTYPES), default="float32", help="dtype of table 1 (default float32)")
    ap.add_argument("--profile", action="store_true", help="append a cProfile of ILWRMap fit on 25 keypoints")
    ap.add_argument("--learned", help="a learned-map checkpoint: append its tables on held-out Push-T pairs")
    ap.add_argument(
        "--learned-store",
        default="data/pusht_expert_200.zarr",
        help="the store the learned map's pair sources come from",
    )
    args = ap.parse_args(argv)

    warnings.filterwarnings("ignore")  # sklearn ConvergenceWarning, gpytorch NumericalWarning (jitter added)
    cfg = config(args.quick)
    t_start, load_start = time.perf_counter(), os.getloadavg()[0]

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    import scipy
    import sklearn

    head = (
        f"# kpflow transportation-map benchmark{' (--quick)' if args.quick else ''}\n\n"
        f"{datetime.datetime.now().isoformat(timespec='seconds')}; {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}, torch {torch.__version__} ({torch.get_num_threads()} thread), "
        f"numpy {np.__version__}, scipy {scipy.__version__}, scikit-learn {sklearn.__version__}; "
        f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}. Medians after untimed warm-up repetitions; "
        f"2-D keypoints in a 512 px workspace, target = rigid motion + ~15 px smooth deformation; residual = "
        f"max_i |phi(source_i) - target_i| in px."
    )
    sections = [head]

    log("table 1: fit + transport")
    sections.append(
        f"## 1. fit + transport (default settings, {args.dtype})\n\n"
        "Fit time does not depend on M (\u2033 = as above); transport = `phi(x)` on M points.\n\n"
        + table_fit_transport(cfg, DTYPES[args.dtype], log)
    )
    log("table 2: vs the authors' library")
    t2, vs = table_vs_authors(cfg, log)
    sections.append(
        "## 2. vs the authors' library (25 keypoints, 20 query points, fit + transport)\n\n"
        "Baselines from `benchmarks/baselines.py` (numpy/scipy/sklearn, float64) with the authors' rigid (Kabsch) "
        "pre-alignment, timed. kpflow inputs are tensors made before timing. Each repetition is a new random "
        "problem; the same problems for every method.\n\n" + t2
    )
    log("table 3: batched")
    t3, batch = table_batched(cfg, log)
    sections.append(
        "## 3. batched fit: 1000 source sets [1000, 25, 2] -> one target [25, 2], 20 query points per set\n\n" + t3
    )
    sections.append("## targets from the issue\n\n" + targets_section(vs, batch))
    if args.learned:
        from learned_map import learned_map_tables

        log("table 4: learned map")
        n = 10 if args.quick else 200
        sections.append(
            f"## 4. learned map on held-out Push-T pairs ({n} per kind)\n\n"
            + learned_map_tables(args.learned, args.learned_store, n, log)
        )
    if args.profile:
        log("profile")
        sections.append("## where ILWRMap.fit spends its time\n\n" + profile_ilwr())
    load_end = os.getloadavg()[0]
    sections.append(
        f"_total run time {time.perf_counter() - t_start:.0f} s; 1-min load average {load_start:.2f} at "
        f"start, {load_end:.2f} at end on {os.cpu_count()} CPUs (above ~1 means other processes shared "
        f"the CPUs and timings are noisier)_"
    )
    text = "\n\n".join(sections) + "\n"
    print(text)
    write_text(args.out, text)
    log(f"wrote {args.out}")


if __name__ == "__main__":
    main()
