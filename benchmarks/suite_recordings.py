"""Scripted robosuite demonstrations recorded scene by scene for the map suite (``benchmarks/map_suite.py``).

Each recording is one successful scripted demonstration (:meth:`kpflow.tasks.suite.task.SuiteTask.demonstrate`) in a
scene of the ``wide`` variant: per segment its commanded grip-site path and orientations, the reference object's pose
at the segment's start (the object picked, or the goal of a place) and the grip site's position then. Scenes whose
scripted demonstration fails are skipped (the next index is drawn). Recordings are written to ``cache`` as ``.npz``
(numbers only, read with ``allow_pickle=False``) and re-read when present.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kpflow.geometry.angles import yaw_of
from kpflow.tasks.suite.keypoints import object_keypoints
from kpflow.tasks.suite.objects import SYMMETRY
from kpflow.tasks.suite.specs import task_spec
from kpflow.utils.formats import read_npz
from kpflow.utils.io import atomic_path

VARIANT = "wide"
FIELDS = ("positions", "rotations", "pos", "rot", "half", "gripper")


@dataclass(frozen=True)
class RecordedSegment:
    """One segment: the grip site's ``positions [T, 3]`` and ``rotations [T, 3, 3]``, the reference object's ``pos``
    and ``rot`` at its start (``half``: a cube's half side, else nan), the grip site ``gripper [3]`` then, the
    keypoint ``kind`` and its symmetry ``turns`` (0: any yaw)."""

    name: str
    kind: str
    positions: np.ndarray
    rotations: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    half: float
    gripper: np.ndarray

    @property
    def turns(self) -> int:
        return SYMMETRY[self.kind]

    def keypoints(self, reference_yaw: float) -> np.ndarray:
        """The reference object's keypoints ordered by the turn nearest ``reference_yaw``, then the grip site: ``[N + 1, 3]``."""
        half = None if math.isnan(self.half) else self.half
        return np.concatenate(
            [object_keypoints(self.kind, self.pos, self.rot, reference_yaw, half), self.gripper[None]]
        )


@dataclass(frozen=True)
class Recording:
    index: int
    segments: list[RecordedSegment]


def keypoint_pair(a: RecordedSegment, b: RecordedSegment) -> tuple[np.ndarray, np.ndarray]:
    """Source and target keypoints of carrying segment ``a`` into ``b``'s scene, both ordered by ``a``'s yaw (as a
    generator orders what it observes by the recorded source's: the least turn that looks the same)."""
    yaw = yaw_of(a.rot)
    return a.keypoints(yaw), b.keypoints(yaw)


def reference(task_name: str, segment: str) -> tuple[str, str]:
    """The object segment ``segment`` of ``task_name`` acts relative to and its keypoint kind (the object picked with the
    grasp's kind, or the goal of a place with its own)."""
    spec = task_spec(task_name)
    if segment == "pick":
        return spec.grasp, spec.grasp_kind
    return spec.target, spec.kinds[spec.target]


def record(task_name: str, n_scenes: int, seed: int) -> list[Recording]:
    """``n_scenes`` successful scripted demonstrations of ``task_name`` (module docstring)."""
    from kpflow.tasks.suite.objects.cube import cube_half
    from kpflow.tasks.suite.task import SuiteTask

    task = SuiteTask(task_name)
    spec = task_spec(task_name)
    env = task.make_sim()
    out, index = [], 0
    while len(out) < n_scenes:
        if index > 4 * n_scenes + 10:
            raise RuntimeError(f"{task_name}: only {len(out)} of {index} scripted demonstrations succeeded")
        scene = task.sample_scene(env, VARIANT, index, seed)
        segments, success, _ = task.demonstrate(env, scene)
        if success:
            recorded = []
            for seg in segments:
                name, kind = reference(task_name, seg.name)
                pos, rot = seg.start.poses[name]
                half = cube_half(env, name) if spec.kinds[name] == "cube" else math.nan
                recorded.append(
                    RecordedSegment(
                        name,
                        kind,
                        seg.trajectory.positions,
                        seg.trajectory.rotations,
                        pos,
                        rot,
                        half,
                        seg.start.gripper[0],
                    )
                )
            out.append(Recording(index, recorded))
        index += 1
    return out


def _path(cache: Path, task: str, n_scenes: int, seed: int) -> Path:
    return cache / f"{task}_{VARIANT}_seed{seed}_{n_scenes}.npz"


def save(path: Path, recordings: list[Recording]) -> None:
    arrays = {
        "index": np.array([r.index for r in recordings]),
        "n_segments": np.array([len(r.segments) for r in recordings]),
    }
    for i, rec in enumerate(recordings):
        for k, seg in enumerate(rec.segments):
            for f in FIELDS:
                arrays[f"{i}/{k}/{f}"] = np.asarray(getattr(seg, f))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def load(path: Path, task_name: str) -> list[Recording]:
    """The recordings of ``task_name`` that :func:`save` wrote, read through :func:`kpflow.utils.formats.read_npz`
    (members checked); segment k of a recording is the task's k-th segment."""
    head = read_npz(path, ("index", "n_segments"))
    members = [(i, k) for i, n in enumerate(head["n_segments"]) for k in range(int(n))]
    data = read_npz(path, [f"{i}/{k}/{f}" for i, k in members for f in FIELDS])
    out = [Recording(int(index), []) for index in head["index"]]
    segments = task_spec(task_name).segments
    for i, k in members:
        v = {f: data[f"{i}/{k}/{f}"] for f in FIELDS}
        name, kind = reference(task_name, segments[k])
        out[i].segments.append(
            RecordedSegment(
                name, kind, v["positions"], v["rotations"], v["pos"], v["rot"], float(v["half"]), v["gripper"]
            )
        )
    return out


def load_or_record(task: str, n_scenes: int, seed: int, cache: Path) -> list[Recording]:
    path = _path(Path(cache), task, n_scenes, seed)
    if path.exists():
        return load(path, task)
    recordings = record(task, n_scenes, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    save(path, recordings)
    return recordings
