"""The objects to pack: four primitive shapes and two of robosuite's scanned objects.

Each type builds a robosuite ``MujocoObject`` with a free joint. Their true extents come from the compiled model
(:func:`kpflow.tasks.arm.env.body_box`), not from robosuite's ``bottom_offset``/``top_offset`` sites, which are off by up to 4.5 cm for the
can and the cereal box.
"""

from __future__ import annotations

from typing import Callable

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
