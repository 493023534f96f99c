"""What each robosuite benchmark task is: its environment, objects, fixtures, the object each segment acts on, and
the wide variant's placement ranges.

A task is a pick (segment ``"pick"``, acting on ``grasp``) and, except ``lift``, a place (segment ``"place"``,
carrying ``grasp`` to ``target``). ``kinds`` names each object's geometry for :mod:`.keypoints` (``cube``,
``can``, ``nut``, ``peg``, ``bin``).

Variants (:mod:`.scene`): ``d0`` is robosuite's placement initializer as it ships (what MimicGen calls D0);
``wide`` widens it like MimicGen's D1:

| task | d0 (robosuite) | wide |
|---|---|---|
| lift | cube x, y in +-0.03 m, any yaw | x, y in +-0.15 m, any yaw |
| stack | both cubes x, y in +-0.08 m, any yaw | +-0.20 m (MimicGen's Stack D1) |
| can | the can anywhere in bin 1, any yaw | the same, and the target bin moved by x in [-0.15, 0], y in [-0.03, 0.05] m (towards the robot: its far quarter is at the Panda's reach already) |
| square | nut x in [-0.115, -0.11], y in [0.11, 0.225], any yaw | nut x in +-0.115, y in +-0.255 and the square peg anywhere in x in [-0.1, 0.3], y in [-0.2, 0.2] (MimicGen's Square D1), kept 0.13 m from the nut |

Two harder variants where the task allows them: ``far`` puts the objects and fixtures outside every range above
(the ``far_objects`` ranges and the ``far_fixtures``' world positions and yaws, mirrored across the table's long
axis with probability 1/2 where ``far_mirror``: ``y -> -y``); ``resized``
draws the shipped placement and scales each of ``resize_objects`` by a factor drawn uniformly in ``resize``
(:class:`~.scene.Scene` ``scales``):

| task | far | resized |
|---|---|---|
| lift | the cube at x in +-0.2, y in [0.15, 0.25] (or mirrored): beyond the wide square, at the table's side | the cube 0.7-1.4 times its size |
| stack | cube A at x in +-0.15, y in [0.2, 0.28], cube B at y in [-0.28, -0.2] (or mirrored): on opposite sides, 0.4-0.56 m apart (d0: at most 0.23) | both cubes 0.7-1.4 times their size, each its own factor |
| can | the can in bin 1 as shipped; the target bin's centre at x in [-0.22, -0.08], y in [0.26, 0.3] (shipped: (0.1, 0.28); wide: x >= -0.05): nearer the robot than any generated scene | - (a can's size sets its grasp) |
| square | the nut at x in [-0.2, -0.13], y in [0, 0.2] (wide: x >= -0.115), the peg at x in [0, 0.15], y in [-0.28, -0.2] (wide: y in +-0.2) and **turned** by 20-45 degrees (every generated peg stands as built), or all mirrored: nut and peg on swapped sides | - (the nut must fit the peg) |

MimicGen's own scene distributions, ``d1`` and ``d2`` (:class:`MimicGenVariant`), with the ranges of its task
definitions (NVlabs/mimicgen, ``mimicgen/envs/robosuite/stack.py`` and ``nut_assembly.py`` at commit
1d009693e4e3ed068997735d9664063d86112537, each class's ``_get_initial_placement_bounds``, the peg moved in
``_load_model``, the nut redrawn in ``_reset_internal`` until its centre is 0.0226 + 0.11 m from the peg's):

| task | d1 | d2 |
|---|---|---|
| stack | ``Stack_D1``: both cubes x, y in +-0.2 m, any yaw (the ranges of ``wide``, other scenes) | - (MimicGen has none) |
| square | ``Square_D1``: nut x in +-0.115, y in +-0.255, any yaw; the peg at x in [-0.1, 0.3], y in +-0.2 as built | ``Square_D2``: nut x, y in +-0.25, any yaw; the peg at x, y in +-0.25, turned by 0-90 degrees |

The peg is drawn first, then the nut until it is clear of it, as MimicGen does (clear: the centres farther apart in
the plane than the peg's horizontal radius, the norm of its geom's half sides, plus the nut's robosuite
``horizontal_radius``). In both, the round peg (``peg2``) stands at world x = -10 m, out of the scene, as
MimicGen's ``Square_D1._load_model`` puts it (:attr:`MimicGenVariant.removed`); ``d0``, ``wide`` and ``far`` keep it
where robosuite builds it, where it is in the way of 4-13 % of wide scenes. MimicGen's Threading and Coffee are
not built: their objects are MimicGen's own models (a needle, a tripod, a coffee machine with a hinged lid), written
for robosuite 1.4 and under NVIDIA's non-commercial licence.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class WideRange:
    """A wider placement for one object: ``x``, ``y`` (m, about ``reference``: the table's centre) and the yaw
    range (None: any)."""

    x: tuple[float, float]
    y: tuple[float, float]
    rotation: tuple[float, float] | None = None


@dataclass(frozen=True)
class MimicGenVariant:
    """One of MimicGen's scene distributions (module docstring): ``objects`` drawn by robosuite's uniform sampler over
    these ranges (about the table's centre, ``z_offset`` above it), after ``fixtures`` at world x, y and yaw drawn
    uniformly, the objects redrawn until their centres are ``clearance`` (m, in the plane) from every fixture;
    ``removed`` names the MuJoCo bodies moved out of the scene, to world ``(x, y) =`` :data:`REMOVED_AT`."""

    objects: dict[str, WideRange]
    fixtures: dict[str, WideRange] = field(default_factory=dict)
    clearance: float = 0.0
    z_offset: float = 0.01
    removed: tuple[str, ...] = ()


#: where MimicGen moves a body it removes from the scene (world x, y in m; ``Square_D1._load_model``: the round peg)
REMOVED_AT = (-10.0, 0.0)


@dataclass(frozen=True)
class TaskSpec:
    """One benchmark task (module docstring)."""

    name: str
    env_name: str
    object_bodies: dict[str, str]  # name -> MuJoCo body
    object_joints: dict[str, str]  # name -> its free joint
    kinds: dict[str, str]  # object or fixture name -> keypoint geometry
    grasp: str
    target: str | None = None
    fixture_bodies: dict[str, str] = field(default_factory=dict)
    wide_objects: dict[str, WideRange] = field(default_factory=dict)
    #: fixture -> ((x lo, x hi), (y lo, y hi)) offsets of the wide variant
    wide_fixtures: dict[str, tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=dict)
    #: the wide variant keeps fixtures this far (m, in the plane) from the objects
    fixture_clearance: float = 0.0
    #: the keypoints a grasp and a held object's placement depend on, where they are not the object's own
    grasp_kinds: dict[str, str] = field(default_factory=dict)
    hand_kinds: dict[str, str] = field(default_factory=dict)
    env_kwargs: dict = field(default_factory=dict)
    #: after fixtures moved: ``(env, name -> body position)``, to update what robosuite caches about them
    move_fixtures: Callable = lambda env, positions: None
    #: the ``far`` variant's placement (none: the task has no far variant)
    far_objects: dict[str, WideRange] = field(default_factory=dict)
    #: the ``far`` variant's fixtures: fixture -> the world x, y ranges of its position and its yaw range (None: as built)
    far_fixtures: dict[str, WideRange] = field(default_factory=dict)
    #: whether ``far`` mirrors its draw across the table's long axis (``y -> -y``) with probability 1/2
    far_mirror: bool = True
    #: the ``resized`` variant: these objects scaled by a factor in ``resize`` (none: no resized variant)
    resize_objects: tuple[str, ...] = ()
    resize: tuple[float, float] = (0.7, 1.4)
    #: MimicGen's variants of the task (``d1``, ``d2``), where it defines them
    mimicgen: dict[str, MimicGenVariant] = field(default_factory=dict)

    @property
    def grasp_kind(self) -> str:
        return self.grasp_kinds.get(self.grasp, self.kinds[self.grasp])

    @property
    def hand_kind(self) -> str:
        return self.hand_kinds.get(self.grasp, self.kinds[self.grasp])

    @property
    def variants(self) -> tuple[str, ...]:
        """The scene variants this task has (:mod:`.scene`)."""
        far = self.far_objects or self.far_fixtures
        return (
            ("d0", "wide")
            + (("far",) if far else ())
            + (("resized",) if self.resize_objects else ())
            + tuple(self.mimicgen)
        )

    @property
    def removable_bodies(self) -> tuple[str, ...]:
        """The MuJoCo bodies some variant removes from the scene (:attr:`MimicGenVariant.removed`)."""
        return tuple(dict.fromkeys(b for v in self.mimicgen.values() for b in v.removed))

    @property
    def segments(self) -> tuple[str, ...]:
        return ("pick",) if self.target is None else ("pick", "place")


def _move_bin(env, positions: dict) -> None:
    """PickPlace checks success against its cached ``bin2_pos``: keep it where the bin is."""
    env.bin2_pos = np.array(positions["bin"], float)


TASKS: dict[str, TaskSpec] = {
    "lift": TaskSpec(
        "lift", "Lift", {"cube": "cube_main"}, {"cube": "cube_joint0"}, {"cube": "cube"}, grasp="cube",
        wide_objects={"cube": WideRange((-0.15, 0.15), (-0.15, 0.15))},
        far_objects={"cube": WideRange((-0.2, 0.2), (0.15, 0.25))}, resize_objects=("cube",),
    ),
    "stack": TaskSpec(
        "stack", "Stack", {"cubeA": "cubeA_main", "cubeB": "cubeB_main"}, {"cubeA": "cubeA_joint0", "cubeB": "cubeB_joint0"},
        {"cubeA": "cube", "cubeB": "cube"}, grasp="cubeA", target="cubeB",
        wide_objects={"cubeA": WideRange((-0.2, 0.2), (-0.2, 0.2)), "cubeB": WideRange((-0.2, 0.2), (-0.2, 0.2))},
        far_objects={"cubeA": WideRange((-0.15, 0.15), (0.2, 0.28)), "cubeB": WideRange((-0.15, 0.15), (-0.28, -0.2))},
        resize_objects=("cubeA", "cubeB"),
        mimicgen={"d1": MimicGenVariant({"cubeA": WideRange((-0.2, 0.2), (-0.2, 0.2)), "cubeB": WideRange((-0.2, 0.2), (-0.2, 0.2))})},
    ),
    "can": TaskSpec(
        "can", "PickPlaceCan", {"can": "Can_main"}, {"can": "Can_joint0"}, {"can": "can", "bin": "bin"}, grasp="can",
        target="bin", fixture_bodies={"bin": "bin2"}, wide_fixtures={"bin": ((-0.15, 0.0), (-0.03, 0.05))},
        move_fixtures=_move_bin, far_fixtures={"bin": WideRange((-0.22, -0.08), (0.26, 0.3))}, far_mirror=False,
    ),
    "square": TaskSpec(
        "square", "NutAssemblySquare", {"nut": "SquareNut_main"}, {"nut": "SquareNut_joint0"}, {"nut": "nut", "peg": "peg"},
        grasp="nut", target="peg", fixture_bodies={"peg": "peg1"}, grasp_kinds={"nut": "nut_handle"}, hand_kinds={"nut": "nut_ring"},
        wide_objects={"nut": WideRange((-0.115, 0.115), (-0.255, 0.255))},
        wide_fixtures={"peg": ((-0.33, 0.07), (-0.30, 0.10))},  # peg1 ships at (0.23, 0.10): x in [-0.1, 0.3], y in [-0.2, 0.2]
        fixture_clearance=0.13,
        far_objects={"nut": WideRange((-0.2, -0.13), (0.0, 0.2))},
        far_fixtures={"peg": WideRange((0.0, 0.15), (-0.28, -0.2), (np.pi / 9, np.pi / 4))},
        mimicgen={
            "d1": MimicGenVariant({"nut": WideRange((-0.115, 0.115), (-0.255, 0.255))}, {"peg": WideRange((-0.1, 0.3), (-0.2, 0.2))},
                                  clearance=float(np.hypot(0.016, 0.016)) + 0.11, z_offset=0.02, removed=("peg2",)),
            "d2": MimicGenVariant({"nut": WideRange((-0.25, 0.25), (-0.25, 0.25))}, {"peg": WideRange((-0.25, 0.25), (-0.25, 0.25), (0.0, np.pi / 2))},
                                  clearance=float(np.hypot(0.016, 0.016)) + 0.11, z_offset=0.02, removed=("peg2",)),
        },
    ),
}  # fmt: skip


def task_spec(name: str) -> TaskSpec:
    if name not in TASKS:
        raise ValueError(f"unknown robosuite task {name!r}; choose one of {sorted(TASKS)}")
    return TASKS[name]
