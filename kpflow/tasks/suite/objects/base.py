"""What every object kind of the robosuite tasks declares (one kind per file of this folder, :mod:`kpflow.tasks.suite.objects`).

An :class:`ObjectKind` has its ``name``, its ``symmetry`` (the number of turns about the vertical that leave it
unchanged; 0: any, a cylinder) and says, from its body pose ``(pos [3], rot [3, 3])``:

* :meth:`~ObjectKind.keypoints`: its keypoints ``[N, 3]`` (world, m), the yaw already reduced by its symmetry to the
  turn nearest a reference (:func:`reduced_yaw`; :func:`~kpflow.tasks.suite.keypoints.object_keypoints` does that);
* :meth:`~ObjectKind.pose_from_box`: its body pose from the footprint box a camera sees of it
  (:mod:`kpflow.tasks.suite.perception`);
* :meth:`~ObjectKind.grasp`: where the scripted jaws close on it (the kinds a task picks);
* :meth:`~ObjectKind.place_goal`: where an object placed on it goes (the kinds a task places on).

A new kind is a file here and an entry in the registry (:data:`kpflow.tasks.suite.objects.KINDS`).
"""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_rotation
from kpflow.vision.boxes import FootprintBox


def reduced_yaw(yaw: float, order: int, reference: float) -> float:
    """``yaw`` plus the multiple of ``2 pi / order`` that brings it nearest ``reference`` (``order`` 1: as it is)."""
    period = 2 * np.pi / order
    return float(reference + (yaw - reference + period / 2) % period - period / 2)


def square(centre, yaw: float, half_x: float, half_y: float, height: float = 0.0) -> list[np.ndarray]:
    """The 4 corners ``(+,+), (-,+), (-,-), (+,-)`` of a horizontal rectangle turned by ``yaw``, ``height`` above
    ``centre``."""
    r = yaw_rotation(yaw)
    return [
        np.asarray(centre) + r @ np.array([sx * half_x, sy * half_y, height])
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ]


def box(centre, yaw, half) -> np.ndarray:
    """The 8 corners ``[8, 3]`` of a box of half extents ``half`` at ``centre``, turned by ``yaw``."""
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return np.asarray(centre) + (signs * np.asarray(half)) @ yaw_rotation(yaw).T


class ObjectKind:
    """An object kind (module docstring); the methods a kind has no use for refuse, naming it."""

    name: str = ""
    symmetry: int = 1

    def keypoints(
        self, pos: np.ndarray, rot: np.ndarray, yaw: float, reference_yaw: float, half: float | None
    ) -> np.ndarray:
        """Its keypoints ``[N, 3]`` at body pose ``(pos, rot)``, ``yaw`` its yaw reduced by its symmetry (a
        cylinder's: ``reference_yaw``), ``half`` a cube's half side."""
        raise NotImplementedError

    def pose_from_box(self, box: FootprintBox, support: float | None) -> tuple[np.ndarray, np.ndarray, float | None]:
        """``(pos [3], rot [3, 3], half)`` of the object whose footprint box is ``box``, on a surface at ``support``."""
        raise NotImplementedError

    def grasp(self, env, pos: np.ndarray, rot: np.ndarray, home_yaw: float) -> tuple[np.ndarray, float]:
        """Where the jaws close on it at body pose ``(pos, rot)``: the grip site's position and the jaws' yaw."""
        raise ValueError(f"no grasp for a {self.name!r}")

    def place_goal(
        self, env, spec, held: tuple[np.ndarray, np.ndarray], goal: tuple[np.ndarray, np.ndarray]
    ) -> tuple[np.ndarray, float]:
        """Where the object ``held`` (its body pose) goes on this one at pose ``goal``: the held body's position and
        the yaw change that gets it there."""
        raise ValueError(f"no placement on a {self.name!r}")
