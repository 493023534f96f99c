"""Scenes of the robosuite benchmark tasks: where every object stands and how far the movable fixtures moved, drawn
by robosuite's own placement initializers.

``d0`` draws with the initializer the environment ships with; ``d1``, ``d2`` (MimicGen's,
:class:`~.specs.MimicGenVariant`) place the fixtures first, then the objects until they are clear of them, and
remove what MimicGen removes (Square's round peg); ``wide`` with robosuite ``UniformRandomSampler``s
over the wider ranges of :mod:`.specs` (and uniform fixture offsets, redrawn until every object is
``fixture_clearance`` from them); ``far`` likewise over the far ranges, mirrored across the table's long axis
(``y -> -y``) with probability 1/2 where the task allows, its fixtures at drawn world positions and yaws; ``resized`` as ``d0``, with each resized object scaled by a factor drawn
uniformly in the task's range and raised so that it stands on the table. All are seeded: scene ``index`` of a variant for ``seed`` comes from
``numpy.random.default_rng([seed, variant id, index])``, handed to every sampler, so a scene is the same for every
map family and worker.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from robosuite.utils.placement_samplers import UniformRandomSampler

from .specs import TaskSpec

_VARIANT_IDS = {"d0": 0, "wide": 1, "far": 2, "resized": 3, "d1": 4, "d2": 5}
_MAX_DRAWS = 1000


@dataclass(frozen=True)
class Scene:
    """One scene: ``objects`` (name -> (position [3], quaternion (w, x, y, z) [4]) of its free joint),
    ``fixture_offsets`` (fixture name -> its displacement [3] from where robosuite puts it), ``fixture_yaws``
    (fixture name -> its turn about the vertical (rad) from how robosuite builds it; 0 when absent), ``scales``
    (object name -> the factor its geometry is scaled by; 1 when absent) and ``removed`` (the MuJoCo bodies moved out
    of the scene, :attr:`~.specs.MimicGenVariant.removed`)."""

    objects: dict[str, tuple[tuple[float, ...], tuple[float, ...]]]
    fixture_offsets: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    scales: dict[str, float] = field(default_factory=dict)
    fixture_yaws: dict[str, float] = field(default_factory=dict)
    removed: tuple[str, ...] = ()

    def __post_init__(self):
        for name, (pos, quat) in self.objects.items():
            if len(pos) != 3 or len(quat) != 4 or not np.all(np.isfinite([*pos, *quat])):
                raise ValueError(
                    f"object {name!r} needs a finite position [3] and quaternion [4]; got {pos!r}, {quat!r}"
                )
            if not abs(np.linalg.norm(quat) - 1.0) < 1e-6:
                raise ValueError(f"object {name!r}'s quaternion is not a unit quaternion: {quat!r}")
        for name, scale in self.scales.items():
            if name not in self.objects or not (np.isfinite(scale) and 0.1 <= scale <= 10):
                raise ValueError(
                    f"scale {scale!r} of {name!r}: scales are factors in 0.1..10 of the scene's objects {sorted(self.objects)}"
                )
        for name, yaw in self.fixture_yaws.items():
            if not np.isfinite(yaw):
                raise ValueError(f"fixture {name!r}'s yaw must be finite, got {yaw!r}")

    def as_dict(self) -> dict:
        return {
            "objects": {k: {"pos": list(p), "quat": list(q)} for k, (p, q) in self.objects.items()},
            "fixture_offsets": {k: list(v) for k, v in self.fixture_offsets.items()},
            **({"scales": dict(self.scales)} if self.scales else {}),
            **({"fixture_yaws": dict(self.fixture_yaws)} if self.fixture_yaws else {}),
            **({"removed": list(self.removed)} if self.removed else {}),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        objects = {k: (tuple(v["pos"]), tuple(v["quat"])) for k, v in d["objects"].items()}
        offsets = {k: tuple(v) for k, v in d.get("fixture_offsets", {}).items()}
        return cls(
            objects, offsets, dict(d.get("scales", {})), dict(d.get("fixture_yaws", {})), tuple(d.get("removed", ()))
        )


def _seed_samplers(sampler, rng) -> None:
    sampler.rng = rng
    for sub in getattr(sampler, "samplers", {}).values():
        _seed_samplers(sub, rng)


def _mujoco_objects(env) -> dict[str, object]:
    """joint name -> the robosuite object owning it."""
    return {obj.joints[0]: obj for obj in env.model.mujoco_objects if obj.joints}


def _place(spec: TaskSpec, env, ranges: dict, placed: dict, rng, mirror: bool = False, z_offset: float = 0.01) -> None:
    """Redraw the objects of ``ranges`` (name -> :class:`~.specs.WideRange`) in ``placed``, each clear of those drawn
    before it, ``z_offset`` above the table; ``mirror``: with ``y -> -y``."""
    objects = _mujoco_objects(env)
    for name in ranges:
        del placed[spec.object_joints[name]]
    fixtures = None
    for name, wide in ranges.items():
        obj = objects[spec.object_joints[name]]
        y = (-wide.y[1], -wide.y[0]) if mirror else wide.y
        sampler = UniformRandomSampler(
            f"{name}_placed", mujoco_objects=[obj], x_range=wide.x, y_range=y, rotation=wide.rotation,
            ensure_object_boundary_in_range=False, ensure_valid_placement=True,
            reference_pos=np.array(env.table_offset), z_offset=z_offset, rng=rng,
        )  # fmt: skip
        drawn = sampler.sample(fixtures=fixtures)
        fixtures = {**(fixtures or {}), **drawn}
        pos, quat, _ = drawn[obj.name]
        placed[obj.joints[0]] = (np.asarray(pos, float), np.asarray(quat, float))


def _world_fixtures(ranges: dict, fixture_home: dict, rng, mirror: bool = False) -> tuple[dict, dict]:
    """Fixture offsets (from ``fixture_home``) and yaws for fixtures drawn at world positions and yaws in ``ranges``
    (name -> :class:`~.specs.WideRange`), ``mirror``: ``y -> -y``."""
    offsets, yaws = {}, {}
    for name, far in ranges.items():
        x, y = float(rng.uniform(*far.x)), float(rng.uniform(*far.y))
        y = -y if mirror else y
        offsets[name] = (x - float(fixture_home[name][0]), y - float(fixture_home[name][1]), 0.0)
        if far.rotation is not None:
            yaws[name] = float(rng.uniform(*far.rotation)) * (-1.0 if mirror else 1.0)
    return offsets, yaws


def _draw(spec: TaskSpec, env, fixture_home: dict, variant: str, rng) -> tuple[dict, dict, dict, dict]:
    """One draw of object poses (joint name -> (pos, quat)), fixture offsets and yaws, and object scales."""
    offsets, yaws = {}, {}
    if variant == "wide":
        offsets = {
            f: (float(rng.uniform(*xr)), float(rng.uniform(*yr)), 0.0) for f, (xr, yr) in spec.wide_fixtures.items()
        }
    placed = {}
    shipped = env.placement_initializer
    _seed_samplers(shipped, rng)
    for obj_name, (pos, quat, obj) in shipped.sample().items():
        if obj.joints:  # not the visual markers, which have no joint
            placed[obj.joints[0]] = (np.asarray(pos, float), np.asarray(quat, float))
    if variant == "wide" and spec.wide_objects:
        _place(spec, env, spec.wide_objects, placed, rng)
    if variant == "far":
        mirror = spec.far_mirror and bool(rng.random() < 0.5)
        if spec.far_objects:
            _place(spec, env, spec.far_objects, placed, rng, mirror=mirror)
        offsets, yaws = _world_fixtures(spec.far_fixtures, fixture_home, rng, mirror)
    if variant in spec.mimicgen:
        mimicgen = spec.mimicgen[variant]
        offsets, yaws = _world_fixtures(mimicgen.fixtures, fixture_home, rng)
        for _ in range(_MAX_DRAWS):
            _place(spec, env, mimicgen.objects, placed, rng, z_offset=mimicgen.z_offset)
            if _clear(spec, fixture_home, placed, offsets, mimicgen.clearance):
                break
    scales = {}
    if variant == "resized":
        scales = {name: float(rng.uniform(*spec.resize)) for name in spec.resize_objects}
    return placed, offsets, yaws, scales


def _clear(spec: TaskSpec, fixture_home: dict, placed: dict, offsets: dict, clearance: float) -> bool:
    """Whether every object's centre is ``clearance`` (m, in the plane) from every moved fixture."""
    if not clearance:
        return True
    for fixture, offset in offsets.items():
        xy = fixture_home[fixture][:2] + np.asarray(offset[:2])
        for name in spec.object_joints:
            if np.linalg.norm(placed[spec.object_joints[name]][0][:2] - xy) < clearance:
                return False
    return True


def sample_scene(spec: TaskSpec, env, variant: str, index: int, seed: int = 0) -> Scene:
    """Scene ``index`` of ``variant`` for ``seed`` (module docstring), drawn with the placement initializers of
    ``env`` (a :class:`~.env.SuiteEnv`); the same whatever scene ``env`` was last reset to (fixtures are measured
    from where robosuite puts them, not from where the last scene moved them)."""
    if variant not in spec.variants:
        raise ValueError(f"unknown variant {variant!r} of {spec.name}; choose one of {spec.variants}")
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    rng = np.random.default_rng([seed, _VARIANT_IDS[variant], index])
    for _ in range(_MAX_DRAWS):
        placed, offsets, yaws, scales = _draw(spec, env.env, env.fixture_home, variant, rng)
        clearance = spec.mimicgen[variant].clearance if variant in spec.mimicgen else spec.fixture_clearance
        if _clear(spec, env.fixture_home, placed, offsets, clearance):
            break
    else:
        raise RuntimeError(
            f"{spec.name}/{variant}: no scene with the fixtures {clearance} m clear in {_MAX_DRAWS} draws"
        )
    for name, scale in scales.items():  # stand a resized object on the table: its centre moves with its half height
        pos = placed[spec.object_joints[name]][0]
        pos[2] += (scale - 1.0) * env.home_half_height(name)
    objects = {
        name: (tuple(map(float, placed[j][0])), tuple(map(float, placed[j][1])))
        for name, j in spec.object_joints.items()
    }
    removed = spec.mimicgen[variant].removed if variant in spec.mimicgen else ()
    return Scene(objects, offsets, scales, yaws, removed)
