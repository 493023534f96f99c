"""robosuite's own benchmark tasks as they ship, driven on absolute end-effector poses.

:class:`SuiteEnv` builds one of robosuite 1.5's environments (``Lift``, ``Stack``, ``PickPlaceCan``,
``NutAssemblySquare``) with the Panda and its standard parallel-jaw gripper, under robosuite's operational-space
controller (``OSC_POSE``) on **absolute** poses of the grip site in the world frame (``[x, y, z]``, an axis-angle
``[rx, ry, rz]``, and the gripper: -1 open, +1 closed). Success is robosuite's own ``_check_success()``.

Scenes are set, not sampled here: :meth:`SuiteEnv.reset_to` puts every object at the pose the scene gives (the
draw of robosuite's placement initializer, :mod:`.scene`) and moves the fixtures the wide variants move (the peg of
``NutAssemblySquare``, the target bin of ``PickPlaceCan``) by changing the static body's position in the compiled
model, so nothing is rebuilt between scenes; a body the scene removes (MimicGen's d1 and d2 of Square take the
round peg away) is moved the same way, to where MimicGen puts it. The arm starts from robosuite's home configuration every time
(``initialization_noise=None``). robosuite draws parts of some models when it builds them (Lift's cube side) from
its own generator, seeded here (:data:`MODEL_SEED`), so every environment of a task is the same model.

Rendering is headless on the CPU (``MUJOCO_GL=osmesa`` when Debian's libosmesa6 is installed, ``egl`` otherwise).
"""

from __future__ import annotations

from kpflow.utils.headless import use_headless_gl
from kpflow.utils.offscreen import own_renderer, render

use_headless_gl()  # before MuJoCo is imported

import numpy as np  # noqa: E402
import robosuite  # noqa: E402
from robosuite.controllers import load_composite_controller_config  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from .specs import REMOVED_AT, TaskSpec  # noqa: E402

OPEN, CLOSED = -1.0, 1.0  # the gripper's action
SETTLE_STEPS = 5  # control steps after a reset, holding the home pose, for the objects to come to rest
#: the seed of robosuite's own generator, which draws parts of the model when it is built (Lift's cube side, 4.0 to
#: 4.4 cm); unseeded, robosuite seeds it from the operating system, so every environment was another model
MODEL_SEED = 0


def controller_config() -> dict:
    """robosuite's BASIC composite controller for the Panda with its arm's OSC_POSE on absolute world poses; only
    the arm's part is kept (robosuite skips the others, the Panda has no base, torso, head, legs or left arm, with a
    warning at every reset)."""
    controller = load_composite_controller_config(controller="BASIC", robot="Panda")
    controller["body_parts"] = {"right": controller["body_parts"]["right"]}
    controller["body_parts"]["right"].update(input_type="absolute", input_ref_frame="world")
    return controller


class SuiteEnv:
    """One robosuite benchmark environment (module docstring) for the task ``spec``.

    Args:
        spec: the task (:data:`~.specs.TASKS`).
        render: whether frames can be rendered (an offscreen renderer; slower to build).
        control_freq: control steps per second (robosuite's default, 20).
    """

    def __init__(self, spec: TaskSpec, render: bool = False, control_freq: int = 20):
        self.spec = spec
        self.env = robosuite.make(
            spec.env_name,
            robots="Panda",
            gripper_types="default",
            controller_configs=controller_config(),
            initialization_noise=None,
            has_renderer=False,
            has_offscreen_renderer=render,
            use_camera_obs=False,
            control_freq=control_freq,
            horizon=100_000,
            ignore_done=True,
            hard_reset=False,
            seed=MODEL_SEED,
            **spec.env_kwargs,
        )
        self.env.reset()
        self.sim = self.env.sim
        own_renderer(self)  # freed in its own GL context, never in another environment's
        robot = self.env.robots[0]
        self.grip_site = robot.eef_site_id["right"]
        self._arm_qpos = robot._ref_joint_pos_indexes
        self._home_qpos = np.array(self.sim.data.qpos[self._arm_qpos])
        model = self.sim.model
        self.object_body = {name: model.body_name2id(body) for name, body in spec.object_bodies.items()}
        self.object_joint = dict(spec.object_joints)
        self.fixture_body = {name: model.body_name2id(body) for name, body in spec.fixture_bodies.items()}
        #: where robosuite puts each fixture (a scene's offsets are from here; the model's copy moves with the scene)
        self.fixture_home = {name: model.body_pos[b].copy() for name, b in self.fixture_body.items()}
        self._fixture_home_quat = {name: model.body_quat[b].copy() for name, b in self.fixture_body.items()}
        #: the bodies a scene may remove (Square's round peg in MimicGen's d1, d2): their ids and where robosuite puts them
        self._removable = {
            b: (model.body_name2id(b), model.body_pos[model.body_name2id(b)].copy()) for b in spec.removable_bodies
        }
        self.joint_limits = np.array(model.jnt_range[robot._ref_joint_indexes])
        pads = robot.gripper["right"].important_geoms
        self._pads = [model.geom_name2id(pads[side][0]) for side in ("left_fingerpad", "right_fingerpad")]
        self.home_pose = self.ee_pose()
        #: every geom of each object, with its size and bounds as built (a scene's scales are applied to these)
        self._object_geoms = {name: np.flatnonzero(model.geom_bodyid == b) for name, b in self.object_body.items()}
        self.geom_home = (model.geom_size.copy(), model.geom_rbound.copy(), model.geom_aabb.copy())
        self._gripper = OPEN
        self.last_action = np.zeros(7)  # the last action sent to robosuite

    # ------------------------------------------------------------------------------------------ scenes
    def reset_to(self, scene) -> None:
        """Set up ``scene`` (a :class:`~.scene.Scene`): fixtures moved, objects placed, the arm at home, at rest.
        What follows depends on the scene only, not on what this environment ran before: robosuite's reset clears
        MuJoCo's data (``mj_resetData``: velocities, warm-start accelerations, actuator state), builds the arm's
        controller afresh and clears the gripper's command state, and the model is the same in every environment of a task
        (:data:`MODEL_SEED`)."""
        env, data, model = self.env, self.sim.data, self.sim.model
        removed = tuple(getattr(scene, "removed", ()))
        if unknown := sorted(set(removed) - set(self._removable)):
            raise ValueError(
                f"the scene removes {unknown}, which no variant of {self.spec.name} removes (removable: {sorted(self._removable)})"
            )
        env.reset()
        for name, (body, home) in self._removable.items():  # out of the scene (MimicGen's x = -10 m), or where built
            model.body_pos[body] = (*REMOVED_AT, home[2]) if name in removed else home
        for name, body in self.fixture_body.items():
            model.body_pos[body] = self.fixture_home[name] + np.asarray(
                scene.fixture_offsets.get(name, (0.0, 0.0, 0.0))
            )
            yaw = getattr(scene, "fixture_yaws", {}).get(name, 0.0)
            built = Rotation.from_quat(self._fixture_home_quat[name], scalar_first=True)
            model.body_quat[body] = (Rotation.from_euler("z", yaw) * built).as_quat(scalar_first=True)
        self.spec.move_fixtures(env, {name: model.body_pos[b].copy() for name, b in self.fixture_body.items()})
        self._scale_objects(getattr(scene, "scales", {}))
        for name, (pos, quat) in scene.objects.items():
            data.set_joint_qpos(self.object_joint[name], np.concatenate([pos, quat]))
        data.qpos[self._arm_qpos] = self._home_qpos
        data.qvel[:] = 0.0
        self.sim.forward()
        self._gripper = OPEN
        home_pos, home_rot = self.home_pose
        for _ in range(SETTLE_STEPS):
            self.command(home_pos, home_rot, OPEN)

    def _scale_objects(self, scales: dict) -> None:
        """Every object's geometry as built, scaled by ``scales`` (name -> factor; 1 when absent): sizes, bounding
        spheres and boxes of all its geoms (collision and visual), so contacts and renders see the new size."""
        model = self.sim.model
        size, rbound, aabb = self.geom_home
        for name, geoms in self._object_geoms.items():
            scale = float(scales.get(name, 1.0))
            model.geom_size[geoms] = size[geoms] * scale
            model.geom_rbound[geoms] = rbound[geoms] * scale
            model.geom_aabb[geoms] = aabb[geoms] * scale

    def home_half_height(self, name: str) -> float:
        """Half the height of object ``name`` as built: how far its centre stands above the table."""
        from .objects.can import CAN_HALF_HEIGHT
        from .objects.cube import cube_half

        return cube_half(self, name, home=True) if self.spec.kinds[name] == "cube" else CAN_HALF_HEIGHT

    # ------------------------------------------------------------------------------------------ state
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of the grip site (between the finger pads) in the world."""
        d = self.sim.data
        return d.site_xpos[self.grip_site].copy(), d.site_xmat[self.grip_site].reshape(3, 3).copy()

    def object_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Position ``[3]`` and rotation ``[3, 3]`` of an object's (or a fixture's) body in the world."""
        b = self.object_body[name] if name in self.object_body else self.fixture_body[name]
        d = self.sim.data
        return d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy()

    def base_position(self) -> np.ndarray:
        """The robot base's position ``[3]`` in the world."""
        return self.sim.data.xpos[self.sim.model.body_name2id("robot0_base")].copy()

    def finger_pads(self) -> np.ndarray:
        """The two finger pads' centres ``[2, 3]``."""
        d = self.sim.data
        return np.stack([d.geom_xpos[g] for g in self._pads])

    def gripper_closed(self) -> bool:
        return self._gripper == CLOSED

    def grasping(self, name: str) -> bool:
        """robosuite's own grasp test: both finger pads touch object ``name``."""
        robot = self.env.robots[0]
        obj = next(o for o in self.env.model.mujoco_objects if o.joints and o.joints[0] == self.object_joint[name])
        return bool(self.env._check_grasp(gripper=robot.gripper["right"], object_geoms=obj))

    def success(self) -> bool:
        """robosuite's own success test for this task."""
        return bool(self.env._check_success())

    def arm_joints(self) -> np.ndarray:
        return np.array(self.sim.data.qpos[self._arm_qpos])

    # ------------------------------------------------------------------------------------------ acting
    def command(self, pos: np.ndarray, rot: np.ndarray, gripper: float) -> None:
        """One control step towards the absolute grip-site pose ``(pos [3], rot [3, 3])`` with the gripper command
        (``OPEN`` or ``CLOSED``)."""
        self._gripper = CLOSED if gripper > 0 else OPEN
        rotvec = Rotation.from_matrix(np.asarray(rot, float)).as_rotvec()
        self.last_action = np.concatenate([np.asarray(pos, float), rotvec, [self._gripper]])
        self.env.step(self.last_action)

    def render_view(self, camera: str = "frontview", size: tuple[int, int] = (240, 320)) -> np.ndarray:
        """An RGB frame ``[H, W, 3]`` from one of the task's cameras (for videos; needs ``render=True``)."""
        rgb = render(self, camera, *size)
        return np.ascontiguousarray(rgb[::-1])
