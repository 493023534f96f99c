"""Packing in robosuite: a UR5e with a suction cup, a table, an open container and one object to pack.

The scene (:class:`~kpflow.tasks.packing.scene.Scene`) says which object lies where and where the container stands.
Every object type is in the model once; :meth:`PackingEnv.reset_to` puts the scene's object on the table and parks
the others on the floor far away, moves the (static) container, and brings the arm to its start pose, so scenes
change without rebuilding the model (robosuite's ``hard_reset=False``: 0.1 s instead of 2 s).

* The arm is driven by robosuite's operational-space controller on **absolute** poses of the cup's tip in the world
  (``[x, y, z]`` and an axis-angle ``[rx, ry, rz]``; pointing down is ``[pi, 0, 0]``). :meth:`PackingEnv.move_to`
  follows :func:`~.trajectory.interpolate`'s straight-line waypoints (at most 1.5 cm and 0.1 rad per control step
  at 20 Hz): a single large jump can flip the UR5e's elbow, and the controller's orientation error is blind to
  180-degree rotations.
* The suction cup (:mod:`~kpflow.tasks.packing.gripper`) grasps with a weld that :meth:`PackingEnv.suction_on`
  switches on only when the cup is within ``SUCTION_REACH`` of the object, at the object's current pose.
* A top-down camera gives RGB, metric depth and the object's segmentation mask (:meth:`PackingEnv.render_topdown`);
  its intrinsics and camera-to-world pose (OpenCV axes) come with it. The container's pose is read from the
  simulator (it stands in for the paper's AprilTag).

Rendering runs headless on the CPU: unless ``MUJOCO_GL`` is set, it is ``osmesa`` when Debian's libosmesa6 is
installed (``make`` installs it) and Mesa's software ``egl`` otherwise.
"""

from __future__ import annotations

import ctypes.util
import os

if "MUJOCO_GL" not in os.environ:
    os.environ["MUJOCO_GL"] = "osmesa" if ctypes.util.find_library("OSMesa") else "egl"
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import robosuite.macros as macros  # noqa: E402

macros.IMAGE_CONVENTION = "opencv"
from robosuite.controllers import load_composite_controller_config  # noqa: E402
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv  # noqa: E402
from robosuite.models.arenas import TableArena  # noqa: E402
from robosuite.models.objects import Bin  # noqa: E402
from robosuite.models.tasks import ManipulationTask  # noqa: E402
from robosuite.utils import camera_utils  # noqa: E402
from robosuite.utils.mjcf_utils import new_element  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from . import gripper  # noqa: E402,F401  (registers SuctionGripper)
from .objects import OBJECT_TYPES, body_box  # noqa: E402
from .scene import CONTAINER_SIZE, CONTAINER_WALL, TABLE_SIZE, TABLE_TOP, Scene  # noqa: E402
from .trajectory import DOWN, interpolate  # noqa: E402

CAMERA = "topdown"
CAMERA_POS = (-0.08, 0.0, 1.95)
CAMERA_FOVY = 50.0
#: the cup's tip at the start of every episode (above the robot's side of the table, out of the camera's view of
#: the object area), pointing down
START_POS = np.array([-0.32, 0.0, 1.12])
SUCTION_REACH = 0.01  # m: the cup seals when its tip is this close to the object
PARK = np.array([3.0, 3.0])  # where unused objects wait, on the floor


class _FixedContainer(Bin):
    """robosuite's thin-walled bin without its free joint: a static container moved by editing its body pose."""

    def _get_geom_attrs(self):
        attrs = super()._get_geom_attrs()
        attrs["joints"] = None
        return attrs


def rotvec(rot: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (the controller's orientation input)."""
    return Rotation.from_matrix(rot).as_rotvec()


class PackingEnv(ManipulationEnv):
    """UR5e + suction cup, a table, a container and the objects of :data:`OBJECT_TYPES` (module docstring).

    Args:
        camera_size: ``(height, width)`` of the top-down images.
        seed: robosuite's seed (the scene itself comes from :meth:`reset_to`).
        **kwargs: passed to robosuite's ``ManipulationEnv`` (e.g. ``control_freq``).
    """

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
        self.scene: Scene | None = None
        self._start_qpos: np.ndarray | None = None
        self._target: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------------------------------ model
    def _load_model(self):
        super()._load_model()
        robot = self.robots[0].robot_model
        robot.set_base_xpos(robot.base_xpos_offset["table"](TABLE_SIZE[0]))
        arena = TableArena(table_full_size=TABLE_SIZE, table_offset=(0, 0, TABLE_TOP))
        arena.set_origin([0, 0, 0])
        arena.set_camera(CAMERA, pos=list(CAMERA_POS), quat=[1, 0, 0, 0], camera_attribs={"fovy": str(CAMERA_FOVY)})
        self.container = _FixedContainer(
            name="container", bin_size=CONTAINER_SIZE, wall_thickness=CONTAINER_WALL, transparent_walls=False,
            use_texture=False, rgba=(0.55, 0.4, 0.25, 1),
        )
        self.objects = {kind: make(kind) for kind, make in OBJECT_TYPES.items()}
        self.model = ManipulationTask(
            mujoco_arena=arena,
            mujoco_robots=[robot],
            mujoco_objects=[self.container, *self.objects.values()],
        )
        eef = self.robots[0].gripper["right"].correct_naming("eef")
        for kind, obj in self.objects.items():  # one weld per object, switched on by suction_on
            self.model.equality.append(
                new_element(tag="weld", name=f"suction_{kind}", body1=eef, body2=obj.root_body, active="false",
                            solref="0.01 1", solimp="0.99 0.999 0.001")
            )  # fmt: skip

    def _setup_references(self):
        super()._setup_references()
        m = self.sim.model
        self.object_body = {k: m.body_name2id(o.root_body) for k, o in self.objects.items()}
        self.object_geoms = {k: np.flatnonzero(m.geom_bodyid == b) for k, b in self.object_body.items()}
        self.weld = {k: m._model.equality(f"suction_{k}").id for k in self.objects}
        self.container_body = m.body_name2id(self.container.root_body)
        self.eef_body = m.body_name2id(self.robots[0].gripper["right"].correct_naming("eef"))
        self.grip_site = m.site_name2id(self.robots[0].gripper["right"].correct_naming("grip_site"))
        self.cup_geom = m.geom_name2id(self.robots[0].gripper["right"].correct_naming("cup_collision"))
        self.object_extent = {k: body_box(m._model, b) for k, b in self.object_body.items()}
        root = m._model.body_rootid
        self._container_geoms = set(np.flatnonzero(root[m.geom_bodyid] == root[self.container_body]).tolist())
        self._arm_geoms = set(np.flatnonzero(root[m.geom_bodyid] == root[self.eef_body]).tolist())

    def reward(self, action=None) -> float:
        return float(self.scene is not None and self.object_in_container())

    # ------------------------------------------------------------------------------------------ scenes
    def reset_to(self, scene: Scene) -> None:
        """Set up ``scene``: the object on the table, the container in place, the arm at its start pose, at rest."""
        self.reset()
        self._target = None
        m, d = self.sim.model, self.sim.data
        d.eq_active[:] = 0
        cx, cy, cyaw = scene.container_pose
        m.body_pos[self.container_body] = (cx, cy, TABLE_TOP + CONTAINER_SIZE[2] / 2)
        m.body_quat[self.container_body] = Rotation.from_euler("z", cyaw).as_quat(scalar_first=True)
        for i, (kind, obj) in enumerate(self.objects.items()):
            centre, half = self.object_extent[kind]
            if kind == scene.object_type:
                x, y, yaw = scene.object_pose
                quat = Rotation.from_euler("z", yaw).as_quat(scalar_first=True)
                # the body origin sits centre[2] above the box's middle: put the box's bottom 1 mm above the table
                offset = Rotation.from_euler("z", yaw).apply([centre[0], centre[1], 0.0])
                pos = (x - offset[0], y - offset[1], TABLE_TOP + half[2] - centre[2] + 1e-3)
            else:
                quat = np.array([1.0, 0, 0, 0])
                pos = (PARK[0] + 0.3 * i, PARK[1], half[2] - centre[2] + 1e-3)
            d.set_joint_qpos(obj.joints[0], np.concatenate([pos, quat]))
        self.sim.forward()
        self.scene = scene
        if self._start_qpos is None:  # first episode: drive to the start pose once and remember the joints
            self.move_to(START_POS, DOWN, settle=60)
            self._start_qpos = np.array(d.qpos[self.robots[0]._ref_joint_pos_indexes])
        d.qpos[self.robots[0]._ref_joint_pos_indexes] = self._start_qpos
        d.qvel[:] = 0.0
        self.sim.forward()
        self.hold(10, START_POS, DOWN)  # let the object settle and the controller take its start pose

    # ------------------------------------------------------------------------------------------ state
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of the cup's tip (the controlled site) in the world."""
        d = self.sim.data
        return d.site_xpos[self.grip_site].copy(), d.site_xmat[self.grip_site].reshape(3, 3).copy()

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of the scene's object body."""
        b = self.object_body[self._kind()]
        d = self.sim.data
        return d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy()

    def object_box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground truth of the object's bounding box: centre ``[3]``, rotation ``[3, 3]`` and half extents ``[3]``."""
        pos, rot = self.object_pose()
        centre, half = self.object_extent[self._kind()]
        return pos + rot @ centre, rot, half.copy()

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

    def holding(self) -> bool:
        return bool(self.sim.data.eq_active[self.weld[self._kind()]])

    def cup_distance(self) -> float:
        """Distance (m) from the cup to the scene's object (negative: penetration)."""
        m, d = self.sim.model._model, self.sim.data._data
        fromto = np.zeros(6)
        return min(
            mujoco.mj_geomDistance(m, d, self.cup_geom, int(g), 0.5, fromto) for g in self.object_geoms[self._kind()]
        )

    def _kind(self) -> str:
        if self.scene is None:
            raise RuntimeError("no scene: call reset_to(scene) first")
        return self.scene.object_type

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
        """Move the tip along :func:`~.trajectory.interpolate`'s waypoints to ``(pos, rot)``, hold it ``settle``
        steps; returns the final position error (m)."""
        start_pos, start_rot = self.ee_pose()
        for p, r in zip(*interpolate(start_pos, start_rot, pos, rot)):
            self.command(p, r)
        self.hold(settle, pos, rot)
        return float(np.linalg.norm(self.ee_pose()[0] - pos))

    def arm_touches_container(self) -> bool:
        """Whether any geom of the arm or its cup is in contact with the container."""
        d = self.sim.data
        for c in d.contact[: d.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if pair & self._container_geoms and pair & self._arm_geoms:
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
        """Seal the cup on the scene's object if it is within ``SUCTION_REACH``; returns whether it sealed."""
        if self.cup_distance() > SUCTION_REACH:
            return False
        kind = self._kind()
        m, d = self.sim.model._model, self.sim.data._data
        b1, b2 = self.eef_body, self.object_body[kind]
        inv = np.zeros(4)
        mujoco.mju_negQuat(inv, d.xquat[b1])
        rel_pos, rel_quat = np.zeros(3), np.zeros(4)
        mujoco.mju_rotVecQuat(rel_pos, d.xpos[b2] - d.xpos[b1], inv)
        mujoco.mju_mulQuat(rel_quat, inv, d.xquat[b2])
        e = self.weld[kind]
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
        rgb = self.sim.render(camera_name=camera, width=size[1], height=size[0])
        return np.ascontiguousarray(rgb[::-1])

    def render_topdown(self) -> dict:
        """The top-down camera now: ``rgb [H, W, 3]`` uint8, ``depth [H, W]`` (m), ``mask [H, W]`` (the object's
        pixels), ``intrinsics [3, 3]`` and ``camera_to_world [4, 4]`` (OpenCV axes); row 0 is the image's top."""
        h, w = self.camera_size
        rgb, depth = self.sim.render(camera_name=CAMERA, width=w, height=h, depth=True)
        seg = self.sim.render(camera_name=CAMERA, width=w, height=h, segmentation=True)
        rgb, depth, seg = rgb[::-1], depth[::-1], seg[::-1]  # OpenGL rows are bottom-up
        is_geom = seg[..., 0] == int(mujoco.mjtObj.mjOBJ_GEOM)
        mask = is_geom & np.isin(seg[..., 1], self.object_geoms[self._kind()])
        return {
            "rgb": np.ascontiguousarray(rgb),
            "depth": camera_utils.get_real_depth_map(self.sim, np.ascontiguousarray(depth)),
            "mask": mask,
            "intrinsics": camera_utils.get_camera_intrinsic_matrix(self.sim, CAMERA, h, w),
            "camera_to_world": camera_utils.get_camera_extrinsic_matrix(self.sim, CAMERA),
        }
