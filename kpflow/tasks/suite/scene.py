"""Scenes of the robosuite benchmark tasks: where every object stands and how far the movable fixtures moved, drawn
by robosuite's own placement initializers.

``d0`` draws with the initializer the environment ships with; ``wide`` with robosuite ``UniformRandomSampler``s
over the wider ranges of :mod:`.specs` (and uniform fixture offsets, redrawn until every object is
``fixture_clearance`` from them). Both are seeded: scene ``index`` of a variant for ``seed`` comes from
``numpy.random.default_rng([seed, variant id, index])``, handed to every sampler, so a scene is the same for every
map family and worker.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from robosuite.utils.placement_samplers import UniformRandomSampler

from .specs import TaskSpec

VARIANTS = ("d0", "wide")
_VARIANT_IDS = {"d0": 0, "wide": 1}
_MAX_DRAWS = 1000


@dataclass(frozen=True)
class Scene:
    """One scene: ``objects`` (name -> (position [3], quaternion (w, x, y, z) [4]) of its free joint) and
    ``fixture_offsets`` (fixture name -> its displacement [3] from where robosuite puts it)."""

    objects: dict[str, tuple[tuple[float, ...], tuple[float, ...]]]
    fixture_offsets: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    def __post_init__(self):
        for name, (pos, quat) in self.objects.items():
            if len(pos) != 3 or len(quat) != 4 or not np.all(np.isfinite([*pos, *quat])):
                raise ValueError(f"object {name!r} needs a finite position [3] and quaternion [4]; got {pos!r}, {quat!r}")
            if not abs(np.linalg.norm(quat) - 1.0) < 1e-6:
                raise ValueError(f"object {name!r}'s quaternion is not a unit quaternion: {quat!r}")

    def as_dict(self) -> dict:
        return {
            "objects": {k: {"pos": list(p), "quat": list(q)} for k, (p, q) in self.objects.items()},
            "fixture_offsets": {k: list(v) for k, v in self.fixture_offsets.items()},
        }

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        objects = {k: (tuple(v["pos"]), tuple(v["quat"])) for k, v in d["objects"].items()}
        return cls(objects, {k: tuple(v) for k, v in d.get("fixture_offsets", {}).items()})


def _seed_samplers(sampler, rng) -> None:
    sampler.rng = rng
    for sub in getattr(sampler, "samplers", {}).values():
        _seed_samplers(sub, rng)


def _mujoco_objects(env) -> dict[str, object]:
    """joint name -> the robosuite object owning it."""
    return {obj.joints[0]: obj for obj in env.model.mujoco_objects if obj.joints}


def _draw(spec: TaskSpec, env, variant: str, rng) -> tuple[dict, dict]:
    """One draw of object poses (joint name -> (pos, quat)) and fixture offsets."""
    offsets = {}
    if variant == "wide":
        offsets = {f: (float(rng.uniform(*xr)), float(rng.uniform(*yr)), 0.0) for f, (xr, yr) in spec.wide_fixtures.items()}
    placed = {}
    shipped = env.placement_initializer
    _seed_samplers(shipped, rng)
    for obj_name, (pos, quat, obj) in shipped.sample().items():
        if obj.joints:  # not the visual markers, which have no joint
            placed[obj.joints[0]] = (np.asarray(pos, float), np.asarray(quat, float))
    if variant == "wide" and spec.wide_objects:
        objects = _mujoco_objects(env)
        for name in spec.wide_objects:
            del placed[spec.object_joints[name]]
        fixtures = None
        for name, wide in spec.wide_objects.items():
            obj = objects[spec.object_joints[name]]
            sampler = UniformRandomSampler(
                f"{name}_wide", mujoco_objects=[obj], x_range=wide.x, y_range=wide.y, rotation=wide.rotation,
                ensure_object_boundary_in_range=False, ensure_valid_placement=True,
                reference_pos=np.array(env.table_offset), z_offset=0.01, rng=rng,
            )  # fmt: skip
            drawn = sampler.sample(fixtures=fixtures)
            fixtures = {**(fixtures or {}), **drawn}
            pos, quat, _ = drawn[obj.name]
            placed[obj.joints[0]] = (np.asarray(pos, float), np.asarray(quat, float))
    return placed, offsets


def _clear(spec: TaskSpec, fixture_home: dict, placed: dict, offsets: dict) -> bool:
    if not spec.fixture_clearance:
        return True
    for fixture, offset in offsets.items():
        xy = fixture_home[fixture][:2] + np.asarray(offset[:2])
        for name in spec.object_joints:
            if np.linalg.norm(placed[spec.object_joints[name]][0][:2] - xy) < spec.fixture_clearance:
                return False
    return True


def sample_scene(spec: TaskSpec, env, variant: str, index: int, seed: int = 0) -> Scene:
    """Scene ``index`` of ``variant`` for ``seed`` (module docstring), drawn with the placement initializers of
    ``env`` (a :class:`~.env.SuiteEnv`); the same whatever scene ``env`` was last reset to (fixtures are measured
    from where robosuite puts them, not from where the last scene moved them)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose one of {VARIANTS}")
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    rng = np.random.default_rng([seed, _VARIANT_IDS[variant], index])
    for _ in range(_MAX_DRAWS):
        placed, offsets = _draw(spec, env.env, variant, rng)
        if _clear(spec, env.fixture_home, placed, offsets):
            break
    else:
        raise RuntimeError(f"{spec.name}/{variant}: no scene with the fixtures {spec.fixture_clearance} m clear in {_MAX_DRAWS} draws")
    objects = {name: (tuple(map(float, placed[j][0])), tuple(map(float, placed[j][1]))) for name, j in spec.object_joints.items()}
    return Scene(objects, offsets)
