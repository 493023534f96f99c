"""Packing with a UR5e in robosuite (the paper's Section 3.3): one demonstration, transported to new objects and
containers.

* :mod:`.objects` -- the object types (boxes, a cylinder, robosuite's can and cereal box) and their true extents.
* :mod:`.scene` -- a scene (object type and pose, container pose) and the seeded relocation / full-variation samplers.
* :mod:`.env` -- :class:`PackingEnv`: the suction arm of :mod:`kpflow.tasks.arm`, a container and the objects.
* :mod:`.perception` -- the object's box from RGB-D and a segmentation mask (minimum-area rectangle, top voxel).
* :mod:`.keypoints` -- the 32 keypoints: start, object, lifted object, container.
* :mod:`.trajectory` -- the scripted demonstration and running a trajectory with its failure reason.
* :mod:`.trial` -- recording the source demonstration and running a transported trial.
"""

from .env import PackingEnv
from .scene import CONDITIONS, SOURCE_SCENE, Scene, sample_scene

__all__ = ["PackingEnv", "Scene", "SOURCE_SCENE", "CONDITIONS", "sample_scene"]
