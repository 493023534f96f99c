"""Decision latency of the robosuite tasks' policies on one CPU thread: the bare K-CFM (the baseline, same run), the
transported K-CFM (Eq. 5: source search + map fit on the objects' keypoints + pull-back of the robot and of the
observation history + K-CFM + push-forward of positions and orientations) with ILWR and with a rigid map, segment by
segment (``policy.transport.segments``: the phase read from the keypoints, the source searched among that phase's, the map on
the phase's object), and policy transportation.

Run::

    python benchmarks/suite_policies.py --task lift --checkpoint release/suite_lift_kcfm.ckpt [--reps 200] [--out PATH]

Queries: the keypoints (and the frame before) of every k-th step of the released source index, moved rigidly by a
seeded random turn and shift so that no query is a source. Medians over ``--reps`` decisions after warm-up; then the
transported K-CFM's stages timed one by one on the same queries (source search, ILWR fit, pull-back of both frames,
the K-CFM's sampling, push-forward of the chunk). The markdown tables are printed and written atomically to
``--out`` (default ``outputs/benchmarks/suite_policies.md``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse
import datetime
import platform

import numpy as np
import torch
from policies import median_ms  # benchmarks/policies.py: median ms of fn over inputs after warm-up

from kpflow.data.source_index import SourceIndex
from kpflow.maps import AffineMap, ILWRMap
from kpflow.policies.chunk_transport import TransportPolicy, transport_chunk
from kpflow.policies.factory import make_kcfm, make_transported_kcfm, source_index_path
from kpflow.policies.kcfm.model import KCFM
from kpflow.tasks.suite.task import SuiteTask
from kpflow.utils.checkpoint import load_checkpoint
from kpflow.utils.io import publish


def stage_rows(model: KCFM, index: SourceIndex, layout, qs: list[dict]) -> list[str]:
    """The transported K-CFM's stages on ``qs``, each timed alone (median ms), as markdown rows."""
    fit = list(layout.indices("objects", "goals"))
    policy = make_transported_kcfm(model, index, layout, ILWRMap, fit_on=fit)
    steps = 10
    prepared = []  # per query, each stage's inputs: (query, its source's keypoints, the fitted map, both frames, a chunk)
    for q in qs:
        policy.act(q)
        frames = torch.from_numpy(q["keypoints_history"])
        condition = frames.numpy()[None] if model.hparams.n_obs > 1 else frames.numpy()[-1:]  # the K-CFM's input shape
        source = torch.from_numpy(index.keypoints[policy.last_source].astype(np.float64))
        prepared.append(
            (q, source, policy.last_map, frames, condition, model.sample(condition, steps=steps)[0].numpy())
        )
    stages = [
        ("source search (weighted nearest of every training step)", lambda p: policy.source.choose(p[0]["keypoints"])),
        (
            "ILWR fit on the objects' keypoints",
            lambda p: ILWRMap().fit(p[1][fit], torch.from_numpy(p[0]["keypoints"])[fit]),
        ),
        ("pull-back of both observation frames (phi^-1)", lambda p: p[2].inverse(p[3])),
        (f"K-CFM, {steps} Euler steps", lambda p: model.sample(p[4], steps=steps)),
        ("push-forward of the chunk (positions, polar(J) rotations)", lambda p: transport_chunk(p[2], p[5], 3, True)),
    ]
    return [f"| {name} | {median_ms(fn, prepared):.2f} |" for name, fn in stages]


def queries(index: SourceIndex, n: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for i in rng.choice(len(index) - 1, n, replace=False) + 1:
        c, s = np.cos(a := rng.uniform(-0.5, 0.5)), np.sin(a)
        rot, shift = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), np.r_[rng.uniform(-0.1, 0.1, 2), 0.0]
        frames = index.keypoints[[i - 1, i]].astype(np.float64) @ rot.T + shift
        out.append({"keypoints": frames[-1], "keypoints_history": frames})
    return out


def main() -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="lift")
    parser.add_argument("--checkpoint", required=True, help="a suite K-CFM with its source index beside it")
    parser.add_argument("--reps", type=int, default=200)
    parser.add_argument("--out", default="outputs/benchmarks/suite_policies.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    layout = SuiteTask(args.task).policy_layout
    model = load_checkpoint(KCFM, args.checkpoint)
    index = SourceIndex.load(source_index_path(args.checkpoint))
    fit = layout.indices("objects", "goals")
    qs = queries(index, args.reps)
    chunked = SourceIndex(index.keypoints, np.repeat(index.chunks, 8, axis=1), index.weights, tuple(index.reference))
    rows = [
        ("K-CFM, 10 Euler steps (baseline)", make_kcfm(model, layout)),
        ("transported K-CFM, ILWR", make_transported_kcfm(model, index, layout, ILWRMap, fit_on=fit)),
        (
            "transported K-CFM, rigid map",
            make_transported_kcfm(model, index, layout, lambda: AffineMap(kind="rigid"), fit_on=fit),
        ),
        (
            "transported K-CFM, ILWR, segment by segment",
            make_transported_kcfm(model, index, layout, ILWRMap, segments=True),
        ),
        ("policy transportation, ILWR (8 actions)", TransportPolicy(chunked, ILWRMap, 8, fit_on=fit, layout=layout)),
    ]
    base = None
    lines = [f"Decision latency on {args.task} ({len(index)} sources, {args.reps} decisions, one thread)", "",
             "| policy | median ms per decision | ratio to the K-CFM | ms over the K-CFM |", "|---|---|---|---|"]  # fmt: skip
    for name, policy in rows:
        ms = median_ms(policy.act, qs)
        base = base or ms
        lines.append(f"| {name} | {ms:.2f} | {ms / base:.2f} | {ms - base:+.2f} |")
    lines += ["", "Stages of the transported K-CFM (ILWR), each timed alone on the same queries", "",
              "| stage | median ms |", "|---|---|", *stage_rows(model, index, layout, qs)]  # fmt: skip
    lines += ["", f"{datetime.date.today()}, {platform.machine()}, torch {torch.__version__}, one thread."]
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
