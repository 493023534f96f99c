"""The objects to pack: four primitive shapes and two of robosuite's scanned objects.

Each type builds a robosuite ``MujocoObject`` with a free joint. Their true extents come from the compiled model
(:func:`body_box`), not from robosuite's ``bottom_offset``/``top_offset`` sites, which are off by up to 4.5 cm for the
can and the cereal box.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation
from robosuite.models.objects import BoxObject, CanObject, CerealObject, CylinderObject, MujocoObject

#: name -> factory(name) of the object; box and cylinder sizes are half extents (m)
OBJECT_TYPES: dict[str, Callable[[str], MujocoObject]] = {
    "box_small": lambda name: BoxObject(name=name, size=[0.025, 0.025, 0.025], rgba=[0.85, 0.2, 0.2, 1], density=400),
    "box_large": lambda name: BoxObject(name=name, size=[0.05, 0.035, 0.03], rgba=[0.2, 0.7, 0.3, 1], density=400),
    "box_flat": lambda name: BoxObject(name=name, size=[0.06, 0.045, 0.015], rgba=[0.9, 0.6, 0.1, 1], density=400),
    "cylinder": lambda name: CylinderObject(name=name, size=[0.03, 0.035], rgba=[0.9, 0.85, 0.2, 1], density=400),
    "can": lambda name: CanObject(name=name),
    "cereal": lambda name: CerealObject(name=name),
}


def body_box(model, body_id: int) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box ``(centre [3], half extents [3])``, in the body's frame, of the body's collision geoms.

    Unions the corners of each geom's own bounding box (``geom_aabb``, in the geom frame) moved into the body frame.
    """
    corners = []
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    for g in np.flatnonzero(model.geom_bodyid == body_id):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        rot = Rotation.from_quat(model.geom_quat[g], scalar_first=True).as_matrix()
        corners.append((centre + signs * half) @ rot.T + model.geom_pos[g])
    if not corners:
        raise ValueError(f"body {body_id} has no collision geoms")
    pts = np.concatenate(corners)
    lo, hi = pts.min(0), pts.max(0)
    return (lo + hi) / 2, (hi - lo) / 2

