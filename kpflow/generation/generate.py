"""Generating demonstrations for a robosuite benchmark task by transporting a few scripted ones, MimicGen-style.

Each worker records the ``n_sources`` scripted source demonstrations (scenes of the shipped ``d0`` distribution
drawn with the seed ``SOURCE_SEED + seed``, kept when they succeed), then runs attempts: attempt ``i`` of a
variant resets to that variant's scene ``i``, takes a source (seeded by ``seed`` and ``i``, so every family gets
the same source in the same scene), and for each segment observes its start, plans it with the family's
:class:`~kpflow.generation.segment_transport.SegmentTransport`, and runs it; a segment that fails (the arm stuck or at
a joint limit, the object not in the jaws) ends the attempt with its reason, otherwise robosuite's success test
decides; with ``stop_early`` False every segment runs and the success test decides anyway (MimicGen's way: it checks
only the task's success), the first failed check kept as the reason of an attempt that fails. Successes are kept:
:func:`generate` writes them into one :class:`~kpflow.data.episode_store.EpisodeStore` per family and exports them
in robomimic's hdf5 layout.

An attempt is a function of the settings, ``seed``, its variant, index and family only: not of the attempts the
same worker ran before it (every attempt resets the simulator, :meth:`~kpflow.tasks.suite.env.SuiteEnv.reset_to`,
and every worker builds the same model, :data:`~kpflow.tasks.suite.env.MODEL_SEED`), so the number of workers and
how the attempts fall to them change nothing, and a run stopped at any point and resumed
(:mod:`.generation_journal`) ends with the numbers of one that was not.

That also makes sharding exact. :func:`generate` with ``shards`` S > 1 runs shard ``shard`` K only: the attempts
``i`` with ``i % S == K`` of every variant and family (strided rather than in blocks, so that every shard meets scenes
from the whole index range and the shards' sizes differ by one at most), in a run folder of its own that records the
shard; the S shards run anywhere (a Hydra launcher's jobs: :mod:`kpflow.cli.generate`). :func:`merge_shards` then
joins the finished shards into the folder an unsharded run writes: the stores merged in attempt order
(:func:`~kpflow.data.store_merge.merge_stores`), the same to the bit, and the results summarised over all the
attempts (:mod:`kpflow.cli.merge`).
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np
from omegaconf import OmegaConf, open_dict

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.store_merge import merge_stores
from kpflow.eval.parallel import iter_jobs
from kpflow.eval.stats import success_cells, success_summary
from kpflow.generation.journal import (
    JOURNAL,
    STORE,
    CellJournal,
    check_output,
    read_shards,
    run_manifest,
    shard_indices,
    write_manifest,
)
from kpflow.generation.robomimic_export import export_robomimic
from kpflow.generation.segment_transport import SegmentTransport
from kpflow.tasks.suite.env import MODEL_SEED, controller_config
from kpflow.tasks.suite.task import SuiteTask
from kpflow.utils.formats import read_yaml
from kpflow.utils.io import atomic_dir, write_json, write_text
from kpflow.utils.video import write_video

SOURCE_SEED = 10_000
EXPORT = "demos.hdf5"  # a cell's robomimic export
CONTROL_FREQ = 20  # Hz: robosuite's control rate, for the real-time ratio


class Generator:
    """One worker's simulator and source demonstrations, and one generation attempt (module docstring)."""

    def __init__(self, task: SuiteTask, families: dict[str, SegmentTransport], n_sources: int = 1, seed: int = 0, render: bool = False,
                 candidates: int | None = None, stop_early: bool = True):  # fmt: skip
        if n_sources < 1:
            raise ValueError(f"n_sources must be >= 1, got {n_sources}")
        if candidates is not None and (
            isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1
        ):
            raise ValueError(f"candidates must be None (a source at random) or an integer >= 1; got {candidates!r}")
        self.task, self.families, self.n_sources, self.seed, self.render = task, dict(families), n_sources, seed, render
        self.candidates, self.stop_early = candidates, stop_early
        self.env = self.sources = None

    def setup(self) -> None:
        import torch

        torch.set_num_threads(1)
        if self.env is None:  # one simulator per worker: a rendering one freed while another renders breaks that one
            self.env = self.task.make_sim(render=self.render)
        self.sources = []
        for i in range(self.n_sources):
            scene = self.task.sample_scene(self.env, "d0", i, SOURCE_SEED + self.seed)
            segments, success, _ = self.task.demonstrate(self.env, scene)
            if success:
                self.sources.append(segments)
        if not self.sources:
            raise RuntimeError(
                f"{self.task.name}: none of the {self.n_sources} scripted source demonstrations succeeded"
            )

    def choose_source(self, transport: SegmentTransport, index: int) -> int:
        """The source an attempt follows, from the scene just reset: with ``candidates`` None any source (drawn
        with ``seed`` and ``index``: MimicGen's ``random``), else one drawn uniformly among the ``candidates``
        sources whose first segment's reference object lies nearest, by ``transport``'s
        :meth:`~kpflow.generation.segment_transport.SegmentTransport.distance` (MimicGen's
        ``nearest_neighbor_object``, its ``nn_k`` being 3)."""
        rng = np.random.default_rng([self.seed, index])
        if self.candidates is None:
            return int(rng.integers(len(self.sources)))
        first = [segments[0] for segments in self.sources]
        distances = [transport.distance(s.start, self.task.observe(self.env, s.name, reference=s.start)) for s in first]
        nearest = np.argsort(distances, kind="stable")[: self.candidates]
        return int(nearest[rng.integers(len(nearest))])

    def attempt(self, variant: str, index: int, family: str, frames: list | None = None) -> tuple[dict, dict | None]:
        """One attempt: its record and, if it succeeded, the episode (``action [T, 7]``, robosuite's; ``ee_target
        [T, 10]``, the same as position, 6-D rotation and gripper; ``keypoints [T, K, 3]``; ``state [T, S]``;
        ``ee_pos [T, 3]``). Both are the same, to the bit, whichever attempts this generator ran before."""
        task, env, transport = self.task, self.env, self.families[family]
        scene = task.sample_scene(env, variant, index, self.seed)
        env.reset_to(scene)
        task.perception.reseed(task.conditions.index(variant), index)
        source_id = self.choose_source(transport, index)
        segments = self.sources[source_id]
        runs, failure, trajectory = [], None, None
        for segment in segments:
            try:
                now = task.observe(env, segment.name, reference=segment.start)
            except ValueError:  # the cameras did not see the object (keypoints=camera)
                failure = failure or "not perceived"
                break
            try:
                trajectory = transport.plan(segment, now, *env.ee_pose())
            except (ValueError, RuntimeError) as error:  # a map that cannot be fitted on these keypoints
                failure = failure or f"map failed: {type(error).__name__}"
                break
            run = task.run_segment(env, trajectory, frames)
            runs.append(run)
            failure = failure or run.failure or task.segment_failure(env, segment.name)
            if failure and self.stop_early:
                break
        success = False
        if len(runs) == len(segments) and (failure is None or not self.stop_early):
            success, end_failure = task.finish(env, trajectory)
            failure = None if success else failure or end_failure
        steps = int(sum(len(r.actions) for r in runs))
        record = {"variant": variant, "index": index, "family": family, "source": source_id, "success": bool(success),
                  "failure": failure, "steps": steps, "scene": scene.as_dict()}  # fmt: skip
        episode = None
        if success:
            episode = {
                "action": np.concatenate([r.actions for r in runs]),
                "ee_target": np.concatenate([r.ee_targets for r in runs]),
                "keypoints": np.concatenate([r.keypoints for r in runs]),
                "state": np.concatenate([r.states for r in runs]),
                "ee_pos": np.concatenate([r.tip for r in runs]),
            }
        return record, episode


_GENERATOR: list = []


def _setup(generator: Generator) -> None:
    generator.setup()
    _GENERATOR[:] = [generator]


def _attempt(job: tuple) -> tuple[dict, dict | None]:
    return _GENERATOR[0].attempt(*job)


def rate_table(summaries: dict[tuple[str, str], dict], throughput: dict[tuple[str, str], dict]) -> str:
    """The markdown table of generation rates per variant and family (throughput ``-`` where this process ran none
    of a cell's attempts)."""
    rows = [
        "| variant | family | attempts | generated [95% CI] | failure reasons | attempts / min | sim time / wall time |",
        "|---|---|---|---|---|---|---|",
    ]
    for (variant, family), s in summaries.items():
        t = throughput[(variant, family)]
        rate, real = (
            ("-", "-") if not t["attempts_run"] else (f"{t['attempts_per_minute']:.1f}", f"{t['real_time']:.2f}")
        )
        rows.append(f"| {variant} | {family} | {s['trials']} | {success_cells(s)} | {rate} | {real} |")
    return "\n".join(rows) + "\n"


def generate(
    output_dir: str | Path,
    task: SuiteTask,
    families: dict[str, SegmentTransport],
    variants: list[str],
    n: int = 200,
    n_sources: int = 1,
    seed: int = 0,
    candidates: int | None = None,
    stop_early: bool = True,
    workers: int = 2,
    videos: int = 1,
    export: bool = True,
    progress: bool = True,
    resume: bool = False,
    shards: int = 1,
    shard: int = 0,
) -> dict:
    """``n`` attempts per variant and family into ``output_dir`` (module docstring): ``results.json`` (every
    attempt and the summary), ``results.md``, ``<variant>/<family>/episodes.zarr`` (the successes, in attempt
    order) and, with ``export``, ``<variant>/<family>/demos.hdf5`` (robomimic's layout); ``videos`` attempts of the
    first family filmed. Returns the results.

    Each attempt is committed as it finishes, in attempt order (:mod:`.generation_journal`). With ``resume`` a run
    that was stopped continues in its folder from the first attempt it had not committed (the settings in its
    ``generation.json`` must be these; ``workers``, ``videos`` and ``export`` may differ) and ends with the stores
    and results an uninterrupted run writes, but for the throughput, which counts only the attempts this call ran
    (``attempts_run``). Without ``resume`` a folder that holds a generation run is refused.

    With ``shards`` > 1 the call runs shard ``shard`` of the attempts only: those ``i`` with ``i % shards == shard``
    (:func:`~.generation_journal.shard_indices`), everything else as above (its videos are its own first attempts);
    :func:`merge_shards` joins the shards' folders into the folder one run writes."""
    if n < 1 or workers < 1 or videos < 0:
        raise ValueError(f"n and workers must be >= 1 and videos >= 0; got {n}, {workers}, {videos}")
    indices = shard_indices(n, shards, shard)
    bad = [v for v in variants if v not in task.conditions]
    if bad or not variants:
        raise ValueError(f"unknown variants {bad or variants}; choose from {task.conditions}")
    if not families:
        raise ValueError("give at least one family")
    out = Path(output_dir)
    manifest = run_manifest(task, families, variants, n, n_sources, seed, candidates, stop_early, shards, shard)
    check_output(out, manifest, resume)
    out.mkdir(parents=True, exist_ok=True)
    write_manifest(out, manifest)
    generator = Generator(task, families, n_sources, seed, candidates=candidates, stop_early=stop_early)
    summaries, throughput, records = {}, {}, []
    for variant in variants:
        for family in families:
            cell, run = _run_cell(out / variant / family, generator, variant, family, indices, workers, progress)
            records += cell
            summaries[(variant, family)], throughput[(variant, family)] = success_summary(cell), run
            if export:
                _export(out / variant / family, task.spec.env_name, generator_env_kwargs(task))
    video_paths = _film(out, generator, variants[0], next(iter(families)), list(indices[:videos]))
    return write_results(out, manifest, summaries, throughput, records, video_paths)


def write_results(folder: Path, manifest: dict, summaries: dict[tuple[str, str], dict], throughput: dict[tuple[str, str], dict],
                  records: list[dict], videos: list[str], merged_from: list[str] | None = None) -> dict:  # fmt: skip
    """``results.json`` and ``results.md`` of a run (or a shard's, or a merged run's: ``merged_from``, the shards'
    folders) into ``folder``; returns the results."""
    n, n_sources, seed, candidates = manifest["n"], manifest["n_sources"], manifest["seed"], manifest["candidates"]
    results = {
        "task": manifest["task"],
        "n_sources": n_sources,
        "candidates": candidates,
        "stop_early": manifest["stop_early"],
        "seed": seed,
        "summary": [{"variant": v, "family": f, **s, **throughput[(v, f)]} for (v, f), s in summaries.items()],
        "attempts": records,
        "videos": videos,
    }
    shards, shard = manifest.get("shards", 1), manifest.get("shard", 0)
    if shards > 1:
        results.update(shards=shards, shard=shard)
    if merged_from is not None:
        results["merged_from"] = list(merged_from)
    write_json(Path(folder) / "results.json", results)
    header = f"# Generation: {manifest['task']}\n\n"
    if shards > 1:
        header += (
            f"Shard {shard} of {shards}: of {n} attempts per variant and family, the {len(range(shard, n, shards))} "
        )
        header += f"with index i % {shards} = {shard}"
    else:
        header += f"{n} attempts per variant and family"
    header += f", {n_sources} scripted source(s), seed {seed}"
    header += f", each attempt's source among the {candidates} nearest" if candidates else ""
    header += "." if manifest["stop_early"] else ", every segment run to the success test."
    if merged_from is not None:
        header += (f" Merged from {len(merged_from)} shards; the throughput columns pool the shards' processes (attempts "
                   "and wall time summed: per process, not the sweep's).")  # fmt: skip
    ran = sum(t["attempts_run"] for t in throughput.values())
    if ran < len(records):
        header += f" Resumed: {len(records) - ran} of the {len(records)} attempts were committed by an earlier run; "
        header += (
            f"the throughput columns time the {ran} this run made." if ran else "this run made none, so no throughput."
        )
    write_text(Path(folder) / "results.md", header + "\n\n" + rate_table(summaries, throughput))
    return results


def merge_shards(folders: Sequence[str | Path], out: str | Path, progress: bool = False) -> dict:
    """Join the finished shards of one run (``folders``, each :func:`generate` with the same settings and
    ``shards``, one per ``shard``) into ``out``, the folder one unsharded run writes: ``generation.json`` (the run's,
    without a shard), per variant and family ``attempts.jsonl`` and ``episodes.zarr`` with every attempt in index
    order (:func:`~kpflow.data.store_merge.merge_stores`: the same arrays, to the bit) and, if the shards exported
    any, ``demos.hdf5``; ``results.json`` and ``results.md`` summarised over all the attempts (the throughput pooled:
    attempts and wall time summed over the shards); the shards' videos; and ``config.yaml``, the first shard's resolved
    config with ``shards=1 shard=0`` and ``output_dir`` the merged folder, if the shards have one. Returns the
    results.

    Refused before anything is written, with an error naming the folders (:func:`~.generation_journal.read_shards`,
    :meth:`~.generation_journal.CellJournal.finished`): shards of different settings, a shard missing or given twice,
    an unfinished or damaged shard, an existing ``out``. Everything is written into a temporary folder beside ``out``
    and renamed into place at the end, so a failure leaves nothing behind. ``progress``: a progress bar over the
    cells."""
    from tqdm import tqdm

    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists already: the merged run needs a new folder")
    manifest, folders = read_shards(folders)
    n, count = manifest["n"], len(folders)
    wanted = [(v, f) for v in manifest["variants"] for f in manifest["families"]]
    shard_rows = [_summary_rows(d, wanted) for d in folders]
    order = list(shard_rows[0])  # the run's order of families (generation.json lists them sorted)
    cells = {
        (v, f): [CellJournal(d / v / f, v, f, shard_indices(n, count, k)) for k, d in enumerate(folders)]
        for v, f in order
    }
    shard_records = {key: [journal.finished() for journal in journals] for key, journals in cells.items()}
    env_args = _exported_env(folders)
    summaries, throughput, records = {}, {}, []
    with atomic_dir(out) as tmp:
        write_manifest(tmp, manifest)
        for (variant, family), journals in tqdm(
            cells.items(), desc=f"merge into {out}", unit="cell", disable=not progress
        ):
            cell = sorted((r for part in shard_records[(variant, family)] for r in part), key=lambda r: r["index"])
            folder = tmp / variant / family
            folder.mkdir(parents=True)
            write_text(folder / JOURNAL, "".join(json.dumps(r, sort_keys=True) + "\n" for r in cell))
            merge_stores(folder / STORE, [j.store_path for j in journals], key="index")
            if CellJournal(folder, variant, family, range(n)).finished() != cell:  # the merged cell reads as a run's
                raise RuntimeError(f"{out / variant / family} did not merge into a finished cell")
            if env_args is not None:
                _export(folder, *env_args)
            records += cell
            summaries[(variant, family)] = success_summary(cell)
            throughput[(variant, family)] = _pooled_throughput([rows[(variant, family)] for rows in shard_rows])
        videos = []
        for video in sorted(p for d in folders for p in d.glob("*.mp4")):
            shutil.copyfile(video, tmp / video.name)
            videos.append(str(out / video.name))
        results = write_results(tmp, manifest, summaries, throughput, records, videos, [str(d) for d in folders])
        if (folders[0] / "config.yaml").is_file():
            _merged_config(folders[0] / "config.yaml", tmp / "config.yaml", out)
    return results


def _summary_rows(folder: Path, cells: list[tuple[str, str]]) -> dict[tuple[str, str], dict]:
    """The summary row of every cell (variant and family) in ``folder``'s ``results.json``, in its order;
    ``ValueError`` unless it summarises exactly ``cells``."""
    path = folder / "results.json"
    try:
        rows = {(r["variant"], r["family"]): r for r in json.loads(path.read_text())["summary"]}
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
        rows = {}
    if set(rows) != set(cells):
        got = ", ".join(f"{v} {f}" for v, f in rows) or "none"
        raise ValueError(f"{path} summarises the cells {got}, not the run's {', '.join(f'{v} {f}' for v, f in cells)}: the "
                         "shard is damaged")  # fmt: skip
    return rows


def _pooled_throughput(rows: list[dict]) -> dict:
    """The throughput of the shards' runs of one cell (``rows``: their summary rows) as one: attempts and wall time
    summed, rates over the sums (the simulated time recovered from each row's ratio)."""
    ran, wall = sum(r["attempts_run"] for r in rows), sum(r["wall_s"] for r in rows)
    sim = sum(r["real_time"] * r["wall_s"] for r in rows if r["attempts_run"])
    pooled = {"attempts_run": ran, "wall_s": wall, "attempts_per_minute": None, "real_time": None}
    if ran and wall > 0:
        pooled.update(attempts_per_minute=60 * ran / wall, real_time=sim / wall)
    return pooled


def _exported_env(folders: list[Path]) -> tuple[str, dict] | None:
    """The robosuite ``env_name`` and ``env_kwargs`` the shards' robomimic exports record (None if they exported
    none); ``ValueError`` naming two files that record different ones."""
    found = None
    for path in sorted(p for d in folders for p in d.glob(f"*/*/{EXPORT}")):
        with h5py.File(path, "r") as f:
            args = json.loads(f["data"].attrs["env_args"])
        if found is None:
            found = (path, args)
        elif args != found[1]:
            raise ValueError(f"{found[0]} and {path} record different robosuite environments: not shards of one run")
    return None if found is None else (found[1]["env_name"], found[1]["env_kwargs"])


def _merged_config(src: Path, dst: Path, out: Path) -> None:
    """``src`` (a shard's resolved config) as the config of the unsharded run in ``out``."""
    cfg = read_yaml(src)
    with open_dict(cfg):
        cfg.shards, cfg.shard, cfg.output_dir = 1, 0, str(out)
    write_text(dst, OmegaConf.to_yaml(cfg))


def _run_cell(folder: Path, generator: Generator, variant: str, family: str, indices: range, workers: int,
              progress: bool) -> tuple[list[dict], dict]:  # fmt: skip
    """One variant and family: its committed attempts continued through ``indices``, each committed as it finishes;
    the records and the throughput of the attempts run here."""
    journal = CellJournal(folder, variant, family, indices)
    records = journal.committed()
    jobs = [(variant, i, family) for i in indices[len(records) :]]
    desc = f"{generator.task.name} {variant} {family}" + (f" (from attempt {len(records)})" if records else "")
    start = time.perf_counter()
    with journal:
        if jobs:
            for record, episode in iter_jobs(_attempt, jobs, workers, _setup, (generator,), desc=desc, unit="attempt",
                                             progress=progress):  # fmt: skip
                journal.commit(record, episode)
                records.append(record)
    wall = time.perf_counter() - start
    sim_seconds = sum(r["steps"] for r in records[len(records) - len(jobs) :]) / CONTROL_FREQ
    run = {"attempts_run": len(jobs), "wall_s": wall, "attempts_per_minute": None, "real_time": None}
    if jobs:
        run.update(attempts_per_minute=60 * len(jobs) / wall, real_time=sim_seconds / wall)
    return records, run


def _export(folder: Path, env_name: str, env_kwargs: dict) -> None:
    """The cell's stored episodes in robomimic's layout, ``demos.hdf5`` (none without a success)."""
    with EpisodeStore(folder / STORE) as store:
        episodes = list(store)
    if episodes:
        export_robomimic(folder / EXPORT, episodes, env_name, env_kwargs)


def generator_env_kwargs(task: SuiteTask) -> dict:
    """The robosuite ``env_kwargs`` recorded in the hdf5 export (what robomimic rebuilds the environment from)."""
    return {"robots": ["Panda"], "controller_configs": controller_config(), "control_freq": CONTROL_FREQ, "seed": MODEL_SEED,
            **task.spec.env_kwargs}  # fmt: skip


def _film(out: Path, generator: Generator, variant: str, family: str, indices: list[int]) -> list[str]:
    """Videos of the attempts ``indices`` of ``variant`` and ``family``, run again with rendering."""
    if not indices:
        return []
    filming = Generator(generator.task, generator.families, generator.n_sources, generator.seed, render=True,
                        candidates=generator.candidates, stop_early=generator.stop_early)  # fmt: skip
    filming.setup()
    paths = []
    for index in indices:
        frames: list = []
        record, _ = filming.attempt(variant, index, family, frames)
        outcome = "success" if record["success"] else str(record["failure"]).replace(" ", "_")
        if frames:
            paths.append(
                str(write_video(frames, out / f"{variant}_{family}_{index:02d}_{outcome}.mp4", fps=CONTROL_FREQ // 2))
            )
    return paths
