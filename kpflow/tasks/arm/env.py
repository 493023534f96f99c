"""A UR5e with a suction cup over a table in robosuite, with a top-down RGB-D camera: the robot shared by the
packing and stacking tasks.

Subclasses say which objects exist (:meth:`SuctionArmEnv._make_objects`, each with a free joint; extra static
bodies via :meth:`SuctionArmEnv._static_objects`) and where a scene puts them (:meth:`SuctionArmEnv._arrange`, with
:meth:`SuctionArmEnv.place_object` / :meth:`SuctionArmEnv.park_object`). Every object is in the model once, so
:meth:`SuctionArmEnv.reset_to` changes scenes without rebuilding the model (robosuite's ``hard_reset=False``: 0.1 s
instead of 2 s).

* The arm is driven by robosuite's operational-space controller on **absolute** poses of the cup's tip in the world
  (``[x, y, z]`` and an axis-angle ``[rx, ry, rz]``; pointing down is ``[pi, 0, 0]``). :meth:`SuctionArmEnv.move_to`
  follows :func:`~.motion.interpolate`'s straight-line waypoints.
* The suction cup (:mod:`~kpflow.tasks.arm.gripper`) grasps with a weld: :meth:`SuctionArmEnv.suction_on` seals on
  the nearest object if it is within ``SUCTION_REACH``, at that object's current pose.
* The top-down camera (:meth:`SuctionArmEnv.render_topdown`) gives RGB, metric depth, a mask per object, the
  intrinsics and the camera-to-world pose (OpenCV axes).

Rendering runs headless on the CPU: unless ``MUJOCO_GL`` is set, it is ``osmesa`` when Debian's libosmesa6 is
installed (``make`` installs it) and Mesa's software ``egl`` otherwise.
"""

from __future__ import annotations

from kpflow.utils.headless import use_headless_gl
from kpflow.utils.offscreen import metric_depth, render

use_headless_gl()  # before MuJoCo is imported

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import robosuite.macros as macros  # noqa: E402

macros.IMAGE_CONVENTION = "opencv"
from robosuite.controllers import load_composite_controller_config  # noqa: E402
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv  # noqa: E402
from robosuite.models.arenas import TableArena  # noqa: E402
from robosuite.models.objects import MujocoObject  # noqa: E402
from robosuite.models.tasks import ManipulationTask  # noqa: E402
from robosuite.utils import camera_utils  # noqa: E402
from robosuite.utils.mjcf_utils import new_element  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from . import gripper  # noqa: E402,F401  (registers SuctionGripper)
from .motion import DOWN, interpolate, rotvec  # noqa: E402

CAMERA = "topdown"
SUCTION_REACH = 0.01  # m: the cup seals when its tip is this close to an object
PARK = np.array([3.0, 3.0])  # where unused objects wait, on the floor


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


class SuctionArmEnv(ManipulationEnv):
    """UR5e + suction cup, a table and the subclass's objects (module docstring).

    Class attributes set the geometry: ``table_size`` (full size, m), ``table_top`` (height of its top),
    ``camera_pos`` / ``camera_fovy`` (the top-down camera, looking straight down) and ``start_pos`` (the cup's tip
    at the start of every episode, pointing down).

    Args:
        camera_size: ``(height, width)`` of the top-down images.
        seed: robosuite's seed (the scene itself comes from :meth:`reset_to`).
        **kwargs: passed to robosuite's ``ManipulationEnv`` (e.g. ``control_freq``).
    """

    table_size = (0.8, 1.2, 0.05)
    table_top = 0.8
    camera_pos = (-0.08, 0.0, 1.95)
    camera_fovy = 50.0
    start_pos = (-0.32, 0.0, 1.12)

    def __init__(self, camera_size: tuple[int, int] = (480, 640), seed: int | None = 0, **kwargs):
        self.camera_size = tuple(int(v) for v in camera_size)
        controller = load_composite_controller_config(robot="UR5e")
        controller["body_parts"]["right"].update(input_type="absolute", input_ref_frame="world")
        kwargs.setdefault("control_freq", 20)
        super().__init__(
            robots="UR5e",
            gripper_types="SuctionGripper",
            controller_configs=controller,
            initialization_noise=None,
            use_camera_obs=False,
            has_renderer=False,
            has_offscreen_renderer=True,
            hard_reset=False,
            horizon=100_000,
            ignore_done=True,
            seed=seed,
            **kwargs,
        )
        self.scene = None
        self._start_qpos: np.ndarray | None = None
        self._target: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------------------------------ for subclasses
    def _make_objects(self) -> dict[str, MujocoObject]:
        """The movable objects (name -> robosuite object with a free joint)."""
        raise NotImplementedError

    def _static_objects(self) -> list[MujocoObject]:
        """Objects without a free joint (e.g. a container), moved by editing their body pose."""
        return []

    def _arrange(self, scene) -> None:
        """Put the objects where ``scene`` says (called by :meth:`reset_to`, before the arm moves)."""
        raise NotImplementedError

    @property
    def grasp_object(self) -> str:
        """The object the task is about (the default of :meth:`object_pose` and friends)."""
        raise NotImplementedError

    # ------------------------------------------------------------------------------------------ model
    def _load_model(self):
        super()._load_model()
        robot = self.robots[0].robot_model
        robot.set_base_xpos(robot.base_xpos_offset["table"](self.table_size[0]))
        arena = TableArena(table_full_size=self.table_size, table_offset=(0, 0, self.table_top))
        arena.set_origin([0, 0, 0])
        arena.set_camera(
            CAMERA, pos=list(self.camera_pos), quat=[1, 0, 0, 0], camera_attribs={"fovy": str(self.camera_fovy)}
        )
        self.objects = self._make_objects()
        self.model = ManipulationTask(
            mujoco_arena=arena,
            mujoco_robots=[robot],
            mujoco_objects=[*self._static_objects(), *self.objects.values()],
        )
        eef = self.robots[0].gripper["right"].correct_naming("eef")
        for name, obj in self.objects.items():  # one weld per object, switched on by suction_on
            self.model.equality.append(
                new_element(tag="weld", name=f"suction_{name}", body1=eef, body2=obj.root_body, active="false",
                            solref="0.01 1", solimp="0.99 0.999 0.001")
            )  # fmt: skip

    def _setup_references(self):
        super()._setup_references()
        m = self.sim.model
        self.object_body = {k: m.body_name2id(o.root_body) for k, o in self.objects.items()}
        self.object_geoms = {k: np.flatnonzero(m.geom_bodyid == b) for k, b in self.object_body.items()}
        self.weld = {k: m._model.equality(f"suction_{k}").id for k in self.objects}
        self.eef_body = m.body_name2id(self.robots[0].gripper["right"].correct_naming("eef"))
        self.grip_site = m.site_name2id(self.robots[0].gripper["right"].correct_naming("grip_site"))
        self.cup_geom = m.geom_name2id(self.robots[0].gripper["right"].correct_naming("cup_collision"))
        self.object_extent = {k: body_box(m._model, b) for k, b in self.object_body.items()}
        root = m._model.body_rootid
        self._arm_geoms = set(np.flatnonzero(root[m.geom_bodyid] == root[self.eef_body]).tolist())

    # ------------------------------------------------------------------------------------------ scenes
    def place_object(self, name: str, x: float, y: float, yaw: float) -> None:
        """Stand object ``name`` on the table with the centre of its box at ``(x, y)`` turned by ``yaw``, its bottom
        1 mm above the table top."""
        centre, half = self.object_extent[name]
        rot = Rotation.from_euler("z", yaw)
        offset = rot.apply([centre[0], centre[1], 0.0])  # the body origin is not the box's centre
        pos = (x - offset[0], y - offset[1], self.table_top + half[2] - centre[2] + 1e-3)
        self.sim.data.set_joint_qpos(
            self.objects[name].joints[0], np.concatenate([pos, rot.as_quat(scalar_first=True)])
        )

    def park_object(self, name: str) -> None:
        """Put object ``name`` on the floor far from the table (each object has its own spot)."""
        centre, half = self.object_extent[name]
        i = list(self.objects).index(name)
        pos = (PARK[0] + 0.3 * i, PARK[1], half[2] - centre[2] + 1e-3)
        self.sim.data.set_joint_qpos(self.objects[name].joints[0], np.concatenate([pos, [1.0, 0, 0, 0]]))

    def reset_to(self, scene) -> None:
        """Set up ``scene``: the objects in place (:meth:`_arrange`), the arm at its start pose, everything at rest."""
        self.reset()
        self._target = None
        d = self.sim.data
        d.eq_active[:] = 0
        self._arrange(scene)
        self.sim.forward()
        self.scene = scene
        if self._start_qpos is None:  # first episode: drive to the start pose once and remember the joints
            self.move_to(np.array(self.start_pos), DOWN, settle=60)
            self._start_qpos = np.array(d.qpos[self.robots[0]._ref_joint_pos_indexes])
        d.qpos[self.robots[0]._ref_joint_pos_indexes] = self._start_qpos
        d.qvel[:] = 0.0
        self.sim.forward()
        self.hold(10, np.array(self.start_pos), DOWN)  # let the objects settle and the controller take its start pose

    def _scene_required(self) -> None:
        if self.scene is None:
            raise RuntimeError("no scene: call reset_to(scene) first")

    # ------------------------------------------------------------------------------------------ state
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of the cup's tip (the controlled site) in the world."""
        d = self.sim.data
        return d.site_xpos[self.grip_site].copy(), d.site_xmat[self.grip_site].reshape(3, 3).copy()

    def object_pose(self, name: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of an object's body (default: :attr:`grasp_object`)."""
        b = self.object_body[name or self.grasp_object]
        d = self.sim.data
        return d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy()

    def object_box(self, name: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground truth of an object's bounding box: centre ``[3]``, rotation ``[3, 3]`` and half extents ``[3]``."""
        name = name or self.grasp_object
        pos, rot = self.object_pose(name)
        centre, half = self.object_extent[name]
        return pos + rot @ centre, rot, half.copy()

    def held_object(self) -> str | None:
        """The object the cup holds, if any."""
        active = self.sim.data.eq_active
        return next((k for k, e in self.weld.items() if active[e]), None)

    def holding(self) -> bool:
        return self.held_object() is not None

    def cup_distance(self, name: str | None = None) -> float:
        """Distance (m) from the cup to an object (default: :attr:`grasp_object`; negative: penetration)."""
        m, d = self.sim.model._model, self.sim.data._data
        fromto = np.zeros(6)
        geoms = self.object_geoms[name or self.grasp_object]
        return min(mujoco.mj_geomDistance(m, d, self.cup_geom, int(g), 0.5, fromto) for g in geoms)

    # ------------------------------------------------------------------------------------------ acting
    def command(self, pos: np.ndarray, rot: np.ndarray) -> None:
        """One control step towards the absolute pose ``(pos [3], rot [3, 3])`` of the cup's tip."""
        self.step(np.concatenate([np.asarray(pos, float), rotvec(np.asarray(rot, float))]))

    def hold(self, steps: int, pos: np.ndarray | None = None, rot: np.ndarray | None = None) -> None:
        """Command ``(pos, rot)`` (which becomes the target; default: the current target, else the current pose)
        for ``steps`` control steps."""
        if pos is not None:
            self._target = (np.asarray(pos, float), np.asarray(rot, float))
        pos, rot = self._target if self._target is not None else self.ee_pose()
        for _ in range(steps):
            self.command(pos, rot)

    def move_to(self, pos: np.ndarray, rot: np.ndarray, settle: int = 0) -> float:
        """Move the tip along :func:`~.motion.interpolate`'s waypoints to ``(pos, rot)``, hold it ``settle``
        steps; returns the final position error (m)."""
        start_pos, start_rot = self.ee_pose()
        for p, r in zip(*interpolate(start_pos, start_rot, pos, rot)):
            self.command(p, r)
        self.hold(settle, pos, rot)
        return float(np.linalg.norm(self.ee_pose()[0] - pos))

    def arm_touches(self, geoms: set[int]) -> bool:
        """Whether any geom of the arm or its cup is in contact with one of ``geoms``."""
        d = self.sim.data
        for c in d.contact[: d.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if pair & geoms and pair & self._arm_geoms:
                return True
        return False

    def arm_singular_value(self) -> float:
        """Smallest singular value of the cup tip's 6 x 6 Jacobian over the arm's joints (small: near-singular)."""
        m, d = self.sim.model._model, self.sim.data._data
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jacp, jacr, self.grip_site)
        cols = self.robots[0]._ref_joint_vel_indexes
        return float(np.linalg.svd(np.vstack([jacp[:, cols], jacr[:, cols]]), compute_uv=False).min())

    def suction_on(self) -> bool:
        """Seal the cup on the nearest object if it is within ``SUCTION_REACH``; returns whether it sealed."""
        self._scene_required()
        distance = {k: self.cup_distance(k) for k in self.objects}
        name = min(distance, key=distance.get)
        if distance[name] > SUCTION_REACH:
            return False
        m, d = self.sim.model._model, self.sim.data._data
        b1, b2 = self.eef_body, self.object_body[name]
        inv = np.zeros(4)
        mujoco.mju_negQuat(inv, d.xquat[b1])
        rel_pos, rel_quat = np.zeros(3), np.zeros(4)
        mujoco.mju_rotVecQuat(rel_pos, d.xpos[b2] - d.xpos[b1], inv)
        mujoco.mju_mulQuat(rel_quat, inv, d.xquat[b2])
        e = self.weld[name]
        m.eq_data[e, 0:3] = 0.0
        m.eq_data[e, 3:6] = rel_pos  # the object's pose in the cup's frame, now
        m.eq_data[e, 6:10] = rel_quat
        m.eq_data[e, 10] = 1.0
        d.eq_active[e] = 1
        return True

    def suction_off(self) -> None:
        self.sim.data.eq_active[:] = 0

    # ------------------------------------------------------------------------------------------ camera
    def render_view(self, camera: str = "sideview", size: tuple[int, int] = (240, 320)) -> np.ndarray:
        """An RGB frame ``[H, W, 3]`` from one of the arena's cameras (for videos)."""
        rgb = render(self, camera, *size)
        return np.ascontiguousarray(rgb[::-1])

    def render_topdown(self) -> dict:
        """The top-down camera now: ``rgb [H, W, 3]`` uint8, ``depth [H, W]`` (m), ``geom_ids [H, W]`` (the MuJoCo
        geom seen at each pixel, -1: none), ``masks`` (object name -> the object's pixels ``[H, W]`` bool),
        ``intrinsics [3, 3]`` and ``camera_to_world [4, 4]`` (OpenCV axes); row 0 is the image's top."""
        h, w = self.camera_size
        rgb, depth = render(self, CAMERA, h, w, depth=True)
        seg = render(self, CAMERA, h, w, segmentation=True)
        rgb, depth, seg = rgb[::-1], depth[::-1], seg[::-1]  # OpenGL rows are bottom-up
        is_geom = seg[..., 0] == int(mujoco.mjtObj.mjOBJ_GEOM)
        masks = {k: is_geom & np.isin(seg[..., 1], g) for k, g in self.object_geoms.items()}
        return {
            "geom_ids": np.ascontiguousarray(np.where(is_geom, seg[..., 1], -1)),
            "rgb": np.ascontiguousarray(rgb),
            "depth": metric_depth(self.sim, np.ascontiguousarray(depth), CAMERA),
            "masks": masks,
            "intrinsics": camera_utils.get_camera_intrinsic_matrix(self.sim, CAMERA, h, w),
            "camera_to_world": camera_utils.get_camera_extrinsic_matrix(self.sim, CAMERA),
        }
