"""Packing in robosuite: the suction arm (:class:`~kpflow.tasks.arm.env.SuctionArmEnv`), an open container and one
object to pack.

The scene (:class:`~kpflow.tasks.packing.scene.Scene`) says which object lies where and where the container stands.
Every object type is in the model once; :meth:`PackingEnv.reset_to` puts the scene's object on the table and parks
the others on the floor far away, and moves the (static) container. The container's pose is read from the simulator
(it stands in for the paper's AprilTag).
"""

from __future__ import annotations

import numpy as np
from robosuite.models.objects import Bin
from scipy.spatial.transform import Rotation

from kpflow.tasks.arm.env import SuctionArmEnv

from .objects import OBJECT_TYPES
from .scene import CONTAINER_SIZE, CONTAINER_WALL, TABLE_SIZE, TABLE_TOP, Scene

#: the cup's tip at the start of every episode (above the robot's side of the table, out of the camera's view of
#: the object area), pointing down
START_POS = np.array(SuctionArmEnv.start_pos)


class _FixedContainer(Bin):
    """robosuite's thin-walled bin without its free joint: a static container moved by editing its body pose."""

    def _get_geom_attrs(self):
        attrs = super()._get_geom_attrs()
        attrs["joints"] = None
        return attrs


class PackingEnv(SuctionArmEnv):
    """The suction arm, a container and the objects of :data:`OBJECT_TYPES` (module docstring).

    Args:
        camera_size: ``(height, width)`` of the top-down images.
        seed: robosuite's seed (the scene itself comes from :meth:`reset_to`).
        **kwargs: passed to robosuite's ``ManipulationEnv`` (e.g. ``control_freq``).
    """

    table_size = TABLE_SIZE
    table_top = TABLE_TOP
    scene: Scene | None

    def _make_objects(self):
        return {kind: make(kind) for kind, make in OBJECT_TYPES.items()}

    def _load_model(self):
        self.container = _FixedContainer(
            name="container", bin_size=CONTAINER_SIZE, wall_thickness=CONTAINER_WALL, transparent_walls=False,
            use_texture=False, rgba=(0.55, 0.4, 0.25, 1),
        )  # fmt: skip
        super()._load_model()

    def _static_objects(self):
        return [self.container]

    def _setup_references(self):
        super()._setup_references()
        m = self.sim.model
        self.container_body = m.body_name2id(self.container.root_body)
        root = m._model.body_rootid
        self.container_geoms = set(np.flatnonzero(root[m.geom_bodyid] == root[self.container_body]).tolist())

    def _arrange(self, scene: Scene) -> None:
        m = self.sim.model
        cx, cy, cyaw = scene.container_pose
        m.body_pos[self.container_body] = (cx, cy, TABLE_TOP + CONTAINER_SIZE[2] / 2)
        m.body_quat[self.container_body] = Rotation.from_euler("z", cyaw).as_quat(scalar_first=True)
        for kind in self.objects:
            if kind == scene.object_type:
                self.place_object(kind, *scene.object_pose)
            else:
                self.park_object(kind)

    @property
    def grasp_object(self) -> str:
        self._scene_required()
        return self.scene.object_type

    def reward(self, action=None) -> float:
        return float(self.scene is not None and self.object_in_container())

    # ------------------------------------------------------------------------------------------ state
    def container_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """Position (centre of its volume) ``[3]`` and rotation ``[3, 3]`` of the container, read from the simulator."""
        d = self.sim.data
        return d.xpos[self.container_body].copy(), d.xmat[self.container_body].reshape(3, 3).copy()

    def object_in_container(self) -> bool:
        """Whether the object's centre lies within the container's inner walls, below its rim, and it is let go."""
        centre, _, half = self.object_box()
        pos, rot = self.container_frame()
        local = rot.T @ (centre - pos)
        inner = np.array(CONTAINER_SIZE[:2]) / 2 - CONTAINER_WALL
        rim = CONTAINER_SIZE[2] / 2
        return bool(np.all(np.abs(local[:2]) < inner) and local[2] - half[2] < rim and not self.holding())

    def render_topdown(self) -> dict:
        """:meth:`SuctionArmEnv.render_topdown` plus ``mask [H, W]`` and ``container_mask [H, W]``: the scene's
        object's pixels and the container's."""
        image = super().render_topdown()
        image["mask"] = image["masks"][self.grasp_object]
        image["container_mask"] = np.isin(image["geom_ids"], sorted(self.container_geoms))
        return image
