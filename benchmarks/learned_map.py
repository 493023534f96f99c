"""Benchmark of the learned map (``map=learned``) beside ILWR and GP on held-out Push-T keypoint pairs, one CPU thread.

Run::

    python benchmarks/learned_map.py --checkpoint outputs/pusht_map/<run>/checkpoints/last.ckpt \\
        [--store data/pusht_expert_200.zarr] [--pairs 200] [--out PATH] [--quick]

(``python benchmarks/maps.py --learned CKPT`` appends the same tables to the maps benchmark.) The pairs come from
:class:`kpflow.tasks.pusht.pairs.PushTPairs` with seeds the training never uses (``1000 + kind``), one kind at a time:
resets of each split (``in_distribution`` in the 512-px workspace; ``robot_ood`` and ``object_ood`` in the 1024-px
one) and jittered demonstration steps. The source is one of the 5 nearest demonstrated steps, as the policies draw
it. All maps run in float64 on tensors made before the clock starts.

Tables:

1. keypoint residual ``max_i |phi(s_i) - t_i|`` (px), median and p90 over the pairs, per kind and map (``--also
   NAME=CKPT`` adds other learned maps, e.g. trained with other regularisers); then their regularity
   (:func:`regularity`);
2. time per scene: fit + transport of 20 query points, and the inverse of those 20 points (medians over the pairs,
   after two untimed warm-ups); a batch of 1,000 scenes ``[1000, 25, 2]`` fitted at once and 20 points each
   transported (median of 3), for the maps that fit batches;
3. the learned map's invertibility on every pair: the share of points of a grid three times the keypoints' extent
   with det J > 0 (by construction: 100 %), and the largest inverse round-trip error there (px);
4. decision latency of the Push-T policies with each map (medians over 50 in-distribution resets after warm-up):
   policy transportation (``kpflow/conf/policy/transport.yaml``'s options) and, with ``--kcfm CKPT``, the transported K-CFM.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy / torch are imported

import argparse
import functools
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

torch.set_num_threads(1)

from kpflow.maps import AffineMap, GPMap, ILWRMap, LearnedMap  # noqa: E402
from kpflow.tasks.pusht.pairs import PushTPairs  # noqa: E402
from kpflow.utils.io import write_text  # noqa: E402

KINDS = {  # name: PushTPairs options
    "in-distribution resets": dict(splits=("in_distribution",), demo_fraction=0.0),
    "robot-OOD resets (1024 px)": dict(splits=("robot_ood",), demo_fraction=0.0),
    "object-OOD resets (1024 px)": dict(splits=("object_ood",), demo_fraction=0.0),
    "demonstration steps, jittered": dict(demo_fraction=1.0),
}


def maps(checkpoint: str, also: dict[str, str] | None = None) -> dict:
    variants = {name: functools.partial(LearnedMap, ckpt) for name, ckpt in (also or {}).items()}
    return variants | {
        "rigid": functools.partial(AffineMap, "rigid"),
        "ILWRMap": ILWRMap,
        "GPMap": GPMap,
        "LearnedMap": functools.partial(LearnedMap, checkpoint),
        "LearnedMap + 3 ILWR steps": functools.partial(LearnedMap, checkpoint, refine_steps=3),
        "LearnedMap + 10 ILWR steps": functools.partial(LearnedMap, checkpoint, refine_steps=10),
    }


def held_out_pairs(store: str, n: int) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    out = {}
    for k, (name, options) in enumerate(KINDS.items()):
        sampler = PushTPairs(store, n_episodes=None, **options)
        src, tgt = sampler(n, np.random.default_rng(1000 + k))
        out[name] = (torch.from_numpy(src), torch.from_numpy(tgt))
    return out


def queries(src: torch.Tensor, m: int = 20, seed: int = 0) -> torch.Tensor:
    """``m`` points uniform over the source keypoints' bounding box ``[m, D]``."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = src.amin(0), src.amax(0)
    return lo + (hi - lo) * torch.rand(m, src.shape[-1], generator=g, dtype=src.dtype)


def residuals(factory, src, tgt) -> np.ndarray:
    out = []
    for s, t in zip(src, tgt):
        with torch.no_grad():
            out.append(float((factory().fit(s, t)(s) - t).norm(dim=-1).max()))
    return np.asarray(out)


def time_scene(factory, src, tgt) -> tuple[float, float]:
    """Median fit + 20-point transport and median 20-point inverse (s) over the pairs."""
    fit, inv = [], []
    for i in range(len(src) + 2):
        s, t = src[i % len(src)], tgt[i % len(src)]
        q = queries(s, seed=i)
        with torch.no_grad():
            t0 = time.perf_counter()
            phi = factory().fit(s, t)
            y = phi(q)
            t1 = time.perf_counter()
            phi.inverse(y)
            t2 = time.perf_counter()
        if i >= 2:
            fit.append(t1 - t0)
            inv.append(t2 - t1)
    return float(np.median(fit)), float(np.median(inv))


def time_batch(factory, src, tgt, b: int = 1000, reps: int = 3) -> float:
    idx = torch.arange(b) % len(src)
    s, t = src[idx], tgt[idx]
    q = torch.stack([queries(x, seed=i) for i, x in enumerate(s)])
    times = []
    for _ in range(reps + 1):
        with torch.no_grad():
            t0 = time.perf_counter()
            factory().fit(s, t)(q)
            times.append(time.perf_counter() - t0)
    return float(np.median(times[1:]))


def grid_checks(checkpoint: str, src, tgt, n: int = 15) -> tuple[float, float]:
    """Share of grid points with det J > 0 and the largest round-trip error (px) over all pairs."""
    positive, total, worst = 0, 0, 0.0
    for s, t in zip(src, tgt):
        centre, half = s.mean(0), (s.amax(0) - s.amin(0)).amax() * 1.5
        axis = torch.linspace(-1, 1, n, dtype=s.dtype)
        grid = centre + half * torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
        phi = LearnedMap(checkpoint).fit(s, t)
        with torch.no_grad():
            worst = max(worst, float((phi.inverse(phi(grid)) - grid).norm(dim=-1).max()))
        positive += int((torch.linalg.det(phi.jacobian(grid)) > 0).sum())
        total += len(grid)
    return positive / total, worst


def decision_latency(make_map, store: str, kcfm: str | None, n: int = 50) -> tuple[float, float | None]:
    """Median seconds per ``act`` of policy transportation and (with a K-CFM checkpoint) the transported K-CFM."""
    from kpflow.data.episode_store import EpisodeStore
    from kpflow.data.source_index import SourceIndex
    from kpflow.policies.chunk_transport import TransportPolicy
    from kpflow.policies.kcfm.model import KCFM
    from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
    from kpflow.tasks.pusht import PushTEnv, split_config
    from kpflow.tasks.pusht.geometry import PUSHT_BLOCK, pusht_weights
    from kpflow.tasks.pusht.task import PushTTask
    from kpflow.utils.checkpoint import load_checkpoint

    env = PushTEnv()
    observations = [env.reset(options={"config": split_config("in_distribution", i, seed=7)})[0] for i in range(n)]
    index = SourceIndex.from_store(EpisodeStore(store), 20, pusht_weights(agent=4.0), PUSHT_BLOCK)
    policies = [
        TransportPolicy(index, make_map, execute=8, candidates=5, temperature=1.2, layout=PushTTask.policy_layout)
    ]
    if kcfm:
        model = load_checkpoint(KCFM, kcfm)
        index_h = SourceIndex.from_store(
            EpisodeStore(store), int(model.hparams.horizon), pusht_weights(agent=4.0), PUSHT_BLOCK
        )
        policies.append(TransportedKCFMPolicy(model, index_h, make_map, layout=PushTTask.policy_layout))
    out = []
    for policy in policies:
        policy.reset(0)
        times = []
        for i, obs in enumerate(observations[:3] + observations):
            t0 = time.perf_counter()
            policy.act(obs)
            if i >= 3:
                times.append(time.perf_counter() - t0)
        out.append(float(np.median(times)))
    return out[0], (out[1] if kcfm else None)


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.2f} ms" if s < 1 else f"{s:.2f} s"


def regularity(factory, src, tgt, n: int = 12) -> tuple[float, float]:
    """Medians over the pairs of ``max |log det J|`` on a grid over the sources' box widened by half (how much the map
    stretches or squeezes area anywhere near the keypoints) and of the mean distance (px) from the rigid alignment at
    points 2-3 box half-sizes from the keypoints' centre (how far from rigid the map is far away)."""
    stretch, far = [], []
    g = torch.Generator().manual_seed(0)
    for s, t in zip(src, tgt):
        lo, hi = s.amin(0), s.amax(0)
        lo, hi = lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo)
        axis = torch.linspace(0, 1, n, dtype=s.dtype)
        grid = lo + (hi - lo) * torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
        direction = torch.randn(64, 2, generator=g, dtype=s.dtype)
        ring = s.mean(0) + direction / direction.norm(dim=-1, keepdim=True) * (0.5 * (hi - lo).amax()) * (
            2 + torch.rand(64, 1, generator=g, dtype=s.dtype)
        )
        phi, rigid = factory().fit(s, t), AffineMap("rigid").fit(s, t)
        stretch.append(float(torch.linalg.slogdet(phi.jacobian(grid)).logabsdet.abs().max()))
        with torch.no_grad():
            far.append(float((phi(ring) - rigid(ring)).norm(dim=-1).mean()))
    return float(np.median(stretch)), float(np.median(far))


def learned_map_tables(
    checkpoint: str,
    store: str,
    n: int,
    log=print,
    batch: int = 1000,
    kcfm: str | None = None,
    also: dict[str, str] | None = None,
) -> str:
    """The tables of the module docstring, as markdown."""
    warnings.filterwarnings("ignore")
    pairs = held_out_pairs(store, n)
    family = maps(checkpoint, also)
    rows = []
    for kind, (src, tgt) in pairs.items():
        log(f"residuals: {kind}")
        cells = []
        for name, factory in family.items():
            r = residuals(factory, src, tgt)
            cells.append(f"{np.median(r):.2f} / {np.quantile(r, 0.9):.2f}")
        rows.append(f"| {kind} | " + " | ".join(cells) + " |")
    t1 = "\n".join([f"| pairs ({n} each) | " + " | ".join(family) + " |", "|---" * (len(family) + 1) + "|", *rows])

    src, tgt = pairs["in-distribution resets"]
    rows = []
    for name in [*(also or {}), "ILWRMap", "GPMap", "LearnedMap"]:
        log(f"regularity: {name}")
        st, far = regularity(family[name], src[:50], tgt[:50])
        rows.append(f"| {name} | {st:.2f} | {far:.1f} |")
    t1b = "\n".join(
        [
            "| map | max abs log det J near the keypoints | distance from the rigid motion far away (px) |",
            "|---|---|---|",
            *rows,
        ]
    )

    src, tgt = pairs["in-distribution resets"]
    rows = []
    for name in ("ILWRMap", "GPMap", "LearnedMap", "LearnedMap + 3 ILWR steps", "LearnedMap + 10 ILWR steps"):
        log(f"timing: {name}")
        fit, inv = time_scene(family[name], src, tgt)
        at_once = time_batch(family[name], src, tgt, batch) if name != "GPMap" else None
        rows.append(f"| {name} | {fmt_ms(fit)} | {fmt_ms(inv)} | {fmt_ms(at_once) if at_once else 'no batched fit'} |")
    t2 = "\n".join(
        [
            f"| map | fit + 20-point transport, per scene | inverse of 20 points | {batch:,} scenes at once |",
            "|---|---|---|---|",
            *rows,
        ]
    )

    log("grid checks")
    all_src = torch.cat([p[0] for p in pairs.values()])
    all_tgt = torch.cat([p[1] for p in pairs.values()])
    share, worst = grid_checks(checkpoint, all_src, all_tgt)
    t3 = (
        f"{len(all_src)} pairs, a 15 x 15 grid over three times each source's extent: det J > 0 at "
        f"{100 * share:.2f} % of the points; largest |phi^-1(phi(x)) - x| = {worst:.2e} px."
    )
    rows = []
    base = None
    for name in ("ILWRMap", "LearnedMap", "LearnedMap + 3 ILWR steps"):
        log(f"decision latency: {name}")
        pt, tk = decision_latency(family[name], store, kcfm, 10 if n <= 10 else 50)
        base = base or (pt, tk)
        ratio = lambda x, b: f" ({x / b:.2f}x ILWR's)" if b and name != "ILWRMap" else ""  # noqa: E731
        rows.append(
            f"| {name} | {fmt_ms(pt)}{ratio(pt, base[0])} | "
            + (f"{fmt_ms(tk)}{ratio(tk, base[1])}" if tk else "-")
            + " |"
        )
    t4 = "\n".join(["| map | policy transportation | transported K-CFM |", "|---|---|---|", *rows])
    return "\n\n".join(
        [
            "### residual (px; median / p90 over pairs)",
            t1,
            "### regularity (medians over 50 in-distribution pairs)",
            t1b,
            "### time (float64, one thread; in-distribution pairs)",
            t2,
            "### invertibility",
            t3,
            "### decision latency (one thread; median over in-distribution resets)",
            t4,
        ]
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True, help="a MapModule checkpoint (train.py experiment=pusht_map)")
    ap.add_argument("--store", default="data/pusht_expert_200.zarr", help="the demonstrations the sources come from")
    ap.add_argument("--pairs", type=int, default=200, help="held-out pairs per kind")
    ap.add_argument("--quick", action="store_true", help="smoke test: 10 pairs per kind")
    ap.add_argument("--batch", type=int, default=1000, help="scenes fitted at once in the batched timing")
    ap.add_argument("--kcfm", help="a K-CFM checkpoint (n_obs=1): adds the transported K-CFM's decision latency")
    ap.add_argument(
        "--also",
        nargs="*",
        default=[],
        metavar="NAME=CKPT",
        help="more learned maps for the residual and regularity tables",
    )
    ap.add_argument("--out", type=Path, default=Path("outputs/benchmarks/learned_map.md"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    text = (
        f"# learned map vs ILWR and GP on held-out Push-T pairs{' (--quick)' if args.quick else ''}\n\n"
        f"checkpoint `{args.checkpoint}`, sources from `{args.store}`; torch {torch.__version__}, 1 thread.\n\n"
        + learned_map_tables(
            args.checkpoint,
            args.store,
            10 if args.quick else args.pairs,
            log,
            args.batch,
            args.kcfm,
            dict(a.split("=", 1) for a in args.also),
        )
        + "\n"
    )
    print(text)
    write_text(args.out, text)
    log(f"wrote {args.out}")


if __name__ == "__main__":
    main()
