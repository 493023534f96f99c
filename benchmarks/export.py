"""Does exporting the K-CFM velocity network pay on one CPU thread? Eager against TorchScript, torch.export and
torch.compile, one network call at batch size 1 and 8.

Run::

    python benchmarks/export.py [--checkpoint release/pusht_standard_kcfm_human.ckpt] [--reps 300] [--warmup 50]
                                [--batches 1 8] [--out outputs/benchmarks/export.md]

The released Push-T K-CFM's EMA network (:class:`~kpflow.policies.kcfm.networks.unet1d.ConditionalUnet1D`) is called as the
sampler calls it, ``net(x [B, H, A], t [B], c [B, C])``, in these forms (each built for the batch size of its row
group, since traced and exported graphs fix the shapes):

* eager: ``net(x, t, c)`` under ``torch.inference_mode``;
* TorchScript ``torch.jit.trace``, as traced and frozen (``torch.jit.freeze`` + ``torch.jit.optimize_for_inference``);
  ``torch.jit.script`` is tried and its error reported if it does not compile;
* ``torch.export.export(net, (x, t, c)).module()``;
* ``torch.compile(net, dynamic=False)`` with the default inductor backend, compiled into a fresh temporary cache (so
  the compile time shown is a cold start, C++ compiler included; in-process, ``TORCHINDUCTOR_COMPILE_THREADS=1``),
  and again with inductor's ``freezing=True`` (its build time is shorter because it reuses the kernels just compiled);
* ONNX Runtime, only if ``onnxruntime`` is already importable (nothing is installed).

Timing: ``--warmup`` calls each, then ``--reps`` rounds; in every round each variant makes one call (in a shuffled
order, so load from other jobs falls on all alike) on one of 8 random inputs. Median and p90 ms per call, and the
ratio of each median to eager's median of the same run; a chunk of ``n`` flow steps is ``n`` such calls (1, 2, 4, 10
or 20) plus a few element-wise ops. Agreement: the max abs difference to eager's output over 16 other random
``(x, t, c)`` (``t`` uniform in [0, 1)), PASS at <= 1e-5. The markdown table is printed and written atomically to
``--out``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import tempfile  # noqa: E402

_CACHE = tempfile.TemporaryDirectory(prefix="kpflow-inductor-")
os.environ["TORCHINDUCTOR_CACHE_DIR"] = _CACHE.name  # a cold inductor cache: the compile time is a first start's
# Inductor compiles in this process: its default pool of compile workers stays busy for seconds after a compile and,
# on a machine of few cores, slowed the eager calls timed next (batch 8: 4.7 -> 8.7 ms).
os.environ["TORCHINDUCTOR_COMPILE_THREADS"] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import random  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from kpflow.policies.kcfm.model import KCFM  # noqa: E402
from kpflow.utils.checkpoint import load_checkpoint  # noqa: E402
from kpflow.utils.io import publish  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TOL = 1e-5
CHUNK_CALLS = (1, 2, 4, 10, 20)


def random_inputs(n: int, batch: int, horizon: int, action_dim: int, cond_dim: int, seed: int) -> list[tuple]:
    g = torch.Generator().manual_seed(seed)
    return [
        (
            torch.randn(batch, horizon, action_dim, generator=g),
            torch.rand(batch, generator=g),
            torch.randn(batch, cond_dim, generator=g),
        )
        for _ in range(n)
    ]


_SCRIPT_FAILED: dict = {}


def short_error(e: Exception) -> str:
    """The error's first line and, for a TorchScript error, the source line it points at."""
    lines = [ln.strip() for ln in str(e).strip().splitlines()]
    here = [lines[i - 1] for i, ln in enumerate(lines) if "<--- HERE" in ln and i > 0]
    text = " ".join(lines[:1] + [f"`{h}`" for h in here[:1]])
    return f"{type(e).__name__}: {text}"[:160].replace("|", "\\|")


def build_variants(net: torch.nn.Module, example: tuple, compile_: bool = True) -> tuple[dict, dict]:
    """``{label: callable}`` of the forms that built, and ``{label: (build s, note)}`` for every form tried."""
    variants, info = {"eager": net}, {"eager": (0.0, "")}

    def attempt(label: str, build) -> None:
        start = time.perf_counter()
        try:
            with warnings.catch_warnings(), torch.no_grad():
                warnings.simplefilter("ignore")
                fn = build()
            with warnings.catch_warnings(), torch.inference_mode():
                warnings.simplefilter("ignore")
                fn(*example)  # the first call as timed: torch.compile compiles here
            variants[label] = fn
            info[label] = (time.perf_counter() - start, "")
        except Exception as e:  # a form that does not build is a result, not a crash
            info[label] = (time.perf_counter() - start, f"fails: {short_error(e)}")

    attempt("TorchScript trace", lambda: torch.jit.trace(net, example))
    attempt("TorchScript trace + freeze + optimize_for_inference",
            lambda: torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(net, example).eval())))  # fmt: skip
    if "TorchScript script" in _SCRIPT_FAILED:  # a failed script leaves half-made classes behind: try it once
        info["TorchScript script"] = _SCRIPT_FAILED["TorchScript script"]
    else:
        attempt(
            "TorchScript script",
            lambda: torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.script(net).eval())),
        )
        if "TorchScript script" not in variants:
            _SCRIPT_FAILED["TorchScript script"] = (
                info["TorchScript script"][0],
                info["TorchScript script"][1] + " (as at the first batch)",
            )
    attempt("torch.export .module()", lambda: torch.export.export(net, example).module())
    if compile_:
        attempt("torch.compile (inductor, cold cache)", lambda: torch.compile(net, dynamic=False))
        attempt(
            "torch.compile (inductor, freezing=True; kernels cached by the row above)",
            lambda: torch.compile(net, dynamic=False, options={"freezing": True}),
        )
    else:
        info["torch.compile"] = (0.0, "skipped (--no-compile)")
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        info["ONNX Runtime"] = (0.0, "not installed (onnxruntime not importable)")
    else:
        attempt("ONNX Runtime", lambda: onnx_runner(net, example))
    return variants, info


def onnx_runner(net: torch.nn.Module, example: tuple):
    import onnxruntime as ort

    path = Path(_CACHE.name) / "unet.onnx"
    torch.onnx.export(net, example, str(path), input_names=["x", "t", "c"], output_names=["v"])
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return lambda x, t, c: torch.from_numpy(session.run(None, {"x": x.numpy(), "t": t.numpy(), "c": c.numpy()})[0])


def max_diff(fn, net, inputs) -> float:
    with torch.inference_mode():
        return max(float((fn(*i) - net(*i)).abs().max()) for i in inputs)


def time_rounds(variants: dict, inputs: list[tuple], reps: int, warmup: int, seed: int) -> dict[str, list[float]]:
    """ms per call of every variant: ``warmup + reps`` rounds, one call of each variant per round, shuffled order."""
    order = list(variants)
    rng = random.Random(seed)
    times = {k: [] for k in order}
    with torch.inference_mode():
        for r in range(warmup + reps):
            rng.shuffle(order)
            x, t, c = inputs[r % len(inputs)]
            for k in order:
                fn = variants[k]
                start = time.perf_counter()
                fn(x, t, c)
                elapsed = 1e3 * (time.perf_counter() - start)
                if r >= warmup:
                    times[k].append(elapsed)
    return times


def time_chunks(variants: dict, model, inputs: list[tuple], steps: int, reps: int, seed: int) -> dict[str, list[float]]:
    """ms per chunk of ``steps`` network calls through the model's own sampler loop (``model.objective.sample``),
    interleaved and shuffled as :func:`time_rounds`."""
    chunk = {
        k: (lambda f: lambda x, t, c: model.objective.sample(lambda x_, t_: f(x_, t_, c), x, steps))(fn)
        for k, fn in variants.items()
    }
    return time_rounds(chunk, inputs, reps, min(5, reps), seed)


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=str(ROOT / "release" / "pusht_standard_kcfm_human.ckpt"))
    parser.add_argument("--reps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=50)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--chunk-steps", type=int, default=10, help="network calls of the measured chunk")
    parser.add_argument(
        "--no-compile", action="store_true", help="skip torch.compile (about 30 s of compiling per row)"
    )
    parser.add_argument("--out", default=str(ROOT / "outputs" / "benchmarks" / "export.md"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()

    model = load_checkpoint(KCFM, args.checkpoint, map_location="cpu")
    net = model.ema_net.eval().requires_grad_(False)
    hp = model.hparams
    horizon, action_dim, cond_dim = int(hp.horizon), int(hp.action_dim), int(net.cond_dim)
    n_params = sum(p.numel() for p in net.parameters())

    lines = [
        f"# Exporting the K-CFM network ({Path(args.checkpoint).name}, EMA net, one CPU thread)",
        "",
        f"`ConditionalUnet1D`, down_dims {tuple(hp.network['down_dims'])}, horizon {horizon}, action_dim {action_dim}, cond_dim {cond_dim}"
        f" ({hp.n_keypoints} keypoints x {hp.keypoint_dim} coords x n_obs {hp.n_obs}), {n_params:,} parameters."
        f" One network call, median and p90 of {args.reps} interleaved rounds after {args.warmup} warm-up;"
        f" ratio = median / eager median of the same run (< 1: faster). Chunk columns: {' / '.join(map(str, CHUNK_CALLS))}"
        " calls x the median; measured chunk: median of --reps / 5 chunks through the model's own sampler"
        f" (`model.objective.sample`, {args.chunk_steps} calls, interleaved the same way). Max |diff|: against eager over 16 random (x, t, c), PASS at <= 1e-5.",
        "",
        "| batch | form | build s | median ms | p90 ms | ratio | chunk ms ("
        + " / ".join(f"{n}" for n in CHUNK_CALLS)
        + " calls)"
        f" | measured {args.chunk_steps}-call chunk ms (ratio) | max abs diff | <= 1e-5 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for batch in args.batches:
        example = random_inputs(1, batch, horizon, action_dim, cond_dim, seed=batch)[0]
        variants, info = build_variants(net, example, not args.no_compile)
        check = random_inputs(16, batch, horizon, action_dim, cond_dim, seed=1000 + batch)
        diffs = {k: max_diff(fn, net, check) for k, fn in variants.items()}
        times = time_rounds(
            variants,
            random_inputs(8, batch, horizon, action_dim, cond_dim, seed=2000 + batch),
            args.reps,
            args.warmup,
            seed=batch,
        )
        chunk_times = time_chunks(variants, model, random_inputs(8, batch, horizon, action_dim, cond_dim, seed=3000 + batch),
                                  args.chunk_steps, max(args.reps // 5, 1), seed=batch)  # fmt: skip
        base, chunk_base = float(np.median(times["eager"])), float(np.median(chunk_times["eager"]))
        for label, (build_s, note) in info.items():
            if label not in variants:
                lines.append(f"| {batch} | {label} | {build_s:.1f} | {note} | - | - | - | - | - | - |")
                continue
            med, p90 = (float(v) for v in np.percentile(times[label], [50, 90]))
            chunk = " / ".join(f"{n * med:.1f}" for n in CHUNK_CALLS)
            ok = "PASS" if diffs[label] <= TOL else "FAIL"
            cm = float(np.median(chunk_times[label]))
            lines.append(
                f"| {batch} | {label} | {build_s:.1f} | {med:.3f} | {p90:.3f} | {med / base:.2f} | {chunk} | {cm:.1f} ({cm / chunk_base:.2f}) | {diffs[label]:.1e} | {ok} |"
            )

    lines += [
        "",
        f"{datetime.date.today()}, {platform.machine()}, torch {torch.__version__}, one thread,"
        f" {time.perf_counter() - started:.0f} s in all.",
    ]
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
