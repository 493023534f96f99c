"""Cameras in the robosuite tasks (issue 44): robosuite's renderer and calibration give frames whose points land on
the objects, and a rendered cube's box keypoints match the simulator's within what the pixels resolve."""

from __future__ import annotations

import numpy as np
import pytest

from kpflow.geometry.angles import yaw_of
from kpflow.tasks.suite.cameras import DEFAULT_CAMERAS, SuiteCameras, object_geoms
from kpflow.tasks.suite.env import SuiteEnv
from kpflow.tasks.suite.keypoints import scene_keypoints
from kpflow.tasks.suite.objects.cube import cube_half
from kpflow.tasks.suite.objects.nut import NUT_TOP
from kpflow.tasks.suite.perception import CameraKeypoints, object_points, pose_from_box
from kpflow.tasks.suite.scene import sample_scene
from kpflow.tasks.suite.specs import task_spec
from kpflow.vision.boxes import fit_footprint_box
from kpflow.vision.noise import CameraNoise
from tests.helpers import bare_kcfm

SPEC = task_spec("lift")


@pytest.fixture(scope="module")
def env():
    return SuiteEnv(SPEC, render=True)


def pixel_size(frame, point) -> float:
    """The side (m) of one pixel of ``frame`` at ``point``'s distance from its camera."""
    return float(np.linalg.norm(point - frame.cam_to_world[:3, 3]) / frame.intrinsics[0, 0])


def test_frames_lift_onto_the_cube(env):
    """Every camera's cube pixels lift to points on the cube's surface (within 1.5 pixels of its box), and its top
    pixels to its top face's height."""
    env.reset_to(sample_scene(SPEC, env, "wide", 1))
    frames = SuiteCameras(height=240, width=320).capture(env)
    assert [f.name for f in frames] == list(DEFAULT_CAMERAS) and frames[0].rgb.shape == (240, 320, 3)
    pos, rot = env.object_pose("cube")
    half = cube_half(env, "cube")
    ids = object_geoms(env, "cube")
    for f in frames:
        mask = f.mask_of(ids)
        assert mask.sum() > 10, f.name
        local = (f.points(mask) - pos) @ rot  # in the cube's frame
        outside = np.clip(np.abs(local) - half, 0, None).max(1)
        assert np.percentile(outside, 95) < 1.5 * pixel_size(f, pos), f.name


@pytest.mark.parametrize("variant, index", [("d0", 0), ("wide", 2)])
def test_box_keypoints_of_a_rendered_cube_match_the_simulator(env, variant, index):
    """Clean frames (no sensor noise): every corner within 3 pixels of the coarsest camera at the cube, the
    keypoints' order and symmetry resolved as the simulator's extractor resolves them."""
    env.reset_to(sample_scene(SPEC, env, variant, index))
    perception = CameraKeypoints(noise=CameraNoise.off())
    frames = perception.frames(env)
    true = scene_keypoints(env, SPEC, "cube", 0.3)
    seen = perception.scene_keypoints(env, SPEC, frames, "cube", 0.3)
    pos = env.object_pose("cube")[0]
    tolerance = 3 * max(pixel_size(f, pos) for f in frames)
    assert np.linalg.norm(seen - true, axis=1).max() < tolerance
    keypoints = perception.policy_keypoints(env, SPEC)
    assert keypoints.shape == (11, 3)
    np.testing.assert_array_equal(keypoints[8:9], env.ee_pose()[0][None])  # the gripper from the robot itself


def test_noisy_keypoints_are_seeded_and_unseen_objects_named(env):
    env.reset_to(sample_scene(SPEC, env, "d0", 3))
    a = CameraKeypoints(SuiteCameras(("frontview",), 240, 320), seed=5).policy_keypoints(env, SPEC)
    b = CameraKeypoints(SuiteCameras(("frontview",), 240, 320), seed=5).policy_keypoints(env, SPEC)
    c = CameraKeypoints(SuiteCameras(("frontview",), 240, 320), seed=6).policy_keypoints(env, SPEC)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    frames = CameraKeypoints(noise=CameraNoise.off()).frames(env)
    points, support = object_points(frames, [np.zeros(f.shape, bool) for f in frames])
    assert points.shape == (0, 3)
    with pytest.raises(ValueError, match="lift: cannot place 'cube' from the cameras"):
        CameraKeypoints(segmenter=_Nothing()).scene_keypoints(env, SPEC, frames, "cube")
    with pytest.raises(ValueError, match="has no camera \\['ceiling'\\]"):
        SuiteCameras(("ceiling",)).capture(env)


def test_a_pose_filter_steadies_the_reads_of_a_still_cube(env):
    """One noisy camera (240 x 320), eight reads of a still cube: filtered (the median of the reads that agree),
    the reads move less from one read to the next than as they come (the calibration's fixed error stays: no filter
    over reads removes it); a release forgets the cube's reads."""
    from kpflow.vision.pose_filter import PoseFilter

    env.reset_to(sample_scene(SPEC, env, "d0", 4))
    jumps = {}
    for name, pose_filter in (("raw", None), ("filtered", PoseFilter(window=5))):
        perception = CameraKeypoints(SuiteCameras(("agentview",), 240, 320), seed=3, pose_filter=pose_filter)
        reads = np.stack([perception.poses(env, SPEC, ["cube"])["cube"].pos for _ in range(10)])
        jumps[name] = np.linalg.norm(np.diff(reads[3:], axis=0), axis=1).mean()
    assert jumps["filtered"] < 0.6 * jumps["raw"]
    perception.missed("cube")
    assert "cube" not in perception.pose_filter.estimate


class _Nothing:
    """A segmenter that finds nothing."""

    def masks(self, frame, names):
        return [np.zeros(frame.shape, bool) for _ in names]


def _slab(x, y, half, z_top, n, rng) -> np.ndarray:
    """Points on the top of an axis-aligned slab centred at (x, y) with half sides ``half``, up to height ``z_top``."""
    local = rng.uniform(-1, 1, (n, 2)) * half
    return np.c_[local + [x, y], np.full(n, z_top)]


@pytest.mark.parametrize("yaw", [0.4, 2.5, -2.0])
def test_a_nuts_ring_end_and_yaw_come_from_its_footprint(yaw):
    """A square nut's top (a ring of outer half side 4.2 cm and a handle bar along its +x) turned by ``yaw``: the pose
    puts the body at the ring's centre and its x axis along the handle, whichever way the rectangle's axis points."""
    rng = np.random.default_rng(0)
    ring = _slab(0.0, 0.0, np.array([0.042, 0.042]), 0.9, 3000, rng)
    ring = ring[np.abs(ring[:, :2]).max(1) > 0.02]  # the hole
    handle = _slab(0.06, 0.0, np.array([0.019, 0.016]), 0.9, 800, rng)
    turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    points = np.concatenate([ring, handle]) @ turn.T + [0.1, -0.05, 0.0]
    pos, rot, half = pose_from_box("nut", fit_footprint_box(points))
    np.testing.assert_allclose(pos, [0.1, -0.05, 0.9 - NUT_TOP], atol=3e-3)
    assert abs((yaw_of(rot) - yaw + np.pi) % (2 * np.pi) - np.pi) < np.radians(2) and half is None


# ------------------------------------------------------------------------------- GL contexts and broken renders
def test_another_environment_freed_leaves_this_ones_frames_as_they_were(env):
    """Issue 63.9: robosuite frees a renderer in whichever GL context is current, and freeing one environment's while
    another's was current turned the other's frames to noise; kpflow frees each in its own (kpflow/utils/offscreen.py),
    so the frames of an environment do not depend on what other environments were built and collected before."""
    import gc

    cameras = SuiteCameras(("frontview",), 120, 160)
    env.reset_to(sample_scene(SPEC, env, "d0", 0))
    before = cameras.capture(env)[0]
    other = SuiteEnv(SPEC, render=True)
    other.reset_to(sample_scene(SPEC, other, "wide", 3))
    cameras.capture(other)
    env.sim._render_context_offscreen.gl_ctx.make_current()  # this one's context current as the other is collected
    del other
    gc.collect()
    after = cameras.capture(env)[0]
    np.testing.assert_array_equal(after.rgb, before.rgb)
    np.testing.assert_array_equal(after.depth, before.depth)


def test_a_broken_render_is_refused_by_name_not_clipped_into_depths(env):
    """Issue 63.9: a z-buffer with NaN (or values outside [0, 1]) is refused naming the camera, in the perception
    path too: a broken sensor is not an object unseen this time (a ValueError there would be read as that)."""
    from kpflow.tasks.suite.gym_env import SuiteGymEnv
    from kpflow.tasks.suite.task import SuiteTask
    from kpflow.utils.offscreen import BrokenRender, metric_depth

    zbuffer = np.full((4, 6), 0.99)
    assert np.isfinite(metric_depth(env.sim, zbuffer, "frontview")).all()
    for bad in (np.nan, 1.5e38, -0.2):
        zbuffer[1, 2] = bad
        with pytest.raises(
            BrokenRender,
            match=r"camera 'frontview' rendered a broken depth image \(1 of 24 pixels not a z-buffer value in \[0, 1\]\)",
        ):
            metric_depth(env.sim, zbuffer, "frontview")
    broken = SuiteEnv(SPEC, render=True)
    real_render = broken.sim.render

    def noisy(*args, **kwargs):  # what the damaged context gave on one worker: its real frame with NaN depth pixels
        out = real_render(*args, **kwargs)
        if kwargs.get("depth"):
            rgb, depth = out
            depth = depth.copy()
            depth[::7, ::5] = np.nan
            out = rgb, depth
        return out

    broken.sim.render = noisy  # a context damaged for real does not break every frame the same way: planted here
    with pytest.raises(BrokenRender, match="rendered a broken depth image"):
        SuiteCameras(("frontview",), 120, 160).capture(broken)
    gym = SuiteGymEnv(
        broken,
        "d0",
        SuiteTask("lift").policy_layout.n_keypoints,
        CameraKeypoints(SuiteCameras(("frontview",), 120, 160)),
    )
    with pytest.raises(BrokenRender):
        gym.reset(seed=0)


# ---------------------------------------------------------------------------------------- keypoints=camera in use


class CountingCameras(CameraKeypoints):
    """The real camera perception, counting its captures."""

    captures = 0

    def frames(self, env):
        self.captures += 1
        return super().frames(env)


def test_a_policy_reads_the_cameras_only_where_it_decides(env):
    """The released Lift K-CFM in closed loop on camera keypoints: the cameras are read at the steps whose
    observations a decision takes (the last n_obs = 2 before each chunk), not at every control step, and the episode
    is the same for the same seed."""
    from kpflow.core.rollout import rollout
    from kpflow.tasks.suite.gym_env import SuiteGymEnv
    from kpflow.tasks.suite.task import SuiteTask

    policy = bare_kcfm("release/suite_lift_kcfm.ckpt", steps=2, execute=8)
    n_keypoints = SuiteTask("lift").policy_layout.n_keypoints
    scene = {"seed": 0, "options": {"stream": 20_000}}
    runs = []
    for _ in range(2):
        perception = CountingCameras(SuiteCameras(("frontview", "agentview")), seed=3)
        episode = rollout(
            SuiteGymEnv(env, "d0", n_keypoints, perception, "rgb_array"), policy, 20, 0, scene, render=True
        )
        runs.append((episode, perception.captures, env.ee_pose()[0].copy()))
    (episode, captures, tip), (again, captures_again, tip_again) = runs
    assert episode.steps == 20 and episode.decisions == 3 and len(episode.frames) == 21  # decisions at steps 0, 8, 16
    assert captures == 1 + 2 + 2 == captures_again  # step 0, then steps 6-7 and 14-15 before the next two chunks
    assert not episode.success and episode.info["unseen_reads"] == 0 and "failure" not in episode.first_info
    assert (again.steps, again.decisions, again.info["unseen_reads"]) == (episode.steps, episode.decisions, 0)
    np.testing.assert_array_equal(tip, tip_again)
    np.testing.assert_array_equal(episode.records["action"], again.records["action"])
    blind = CameraKeypoints(SuiteCameras(("agentview",)), segmenter=_Nothing())  # never sees the cube: no pose to keep
    unseen = rollout(SuiteGymEnv(env, "d0", n_keypoints, blind), policy, 20, 0, scene)
    assert (unseen.steps, unseen.decisions, unseen.first_info["failure"], unseen.first_info["unseen_reads"]) == (
        0,
        0,
        "not perceived",
        1,
    )


def test_generation_on_camera_keypoints_is_the_same_whatever_ran_before():
    """keypoints=camera in generation: a Lift attempt succeeds on perceived keypoints, and the noise is drawn per
    attempt (an attempt's record and episode do not depend on which attempts the worker ran before)."""
    from kpflow.generation.generate import Generator
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap
    from kpflow.tasks.suite.task import SuiteTask
    from kpflow.vision.keypoint_source import KeypointSource

    task = SuiteTask("lift", KeypointSource("camera", cameras=("frontview", "agentview")))
    generator = Generator(task, {"rigid": SegmentTransport(lambda: AffineMap("rigid"))})
    generator.setup()
    first, episode = generator.attempt("wide", 1, "rigid")
    generator.attempt("d0", 0, "rigid")
    again, episode_again = generator.attempt("wide", 1, "rigid")
    assert first["success"] and first == again
    np.testing.assert_array_equal(episode["action"], episode_again["action"])
    assert isinstance(task.perception, CameraKeypoints)


def test_a_picked_cube_is_carried_by_the_jaws(env):
    """The ring around a held cube's mask is fingers and floor, not what it stands on: the support is not trusted.
    The task's run signals the grasp to its camera perception, which then carries the cube from where it stood: the
    in-hand keypoints within a centimetre of the simulator's, with no capture needed."""
    from kpflow.geometry.angles import yaw_of as yaw
    from kpflow.tasks.suite.demonstrator import plan_segment
    from kpflow.tasks.suite.keypoints import in_hand_keypoints
    from kpflow.tasks.suite.task import SuiteTask
    from kpflow.vision.keypoint_source import KeypointSource

    task = SuiteTask("lift", KeypointSource("camera", noise=CameraNoise.off()))
    env.reset_to(sample_scene(SPEC, env, "d0", 2))
    perception = task.perception
    standing = perception.poses(env, SPEC, ["cube"])["cube"]
    assert abs(standing.half - cube_half(env, "cube")) < 0.002 and perception.last == {"cube": standing}
    task.run_segment(env, plan_segment(env, SPEC, "pick", yaw(env.home_pose[1])))
    assert env.grasping("cube") and set(perception.held) == {"cube"}
    frames = perception.frames(env)
    masks = [perception._segmenter(env).masks(f, ["cube"])[0] for f in frames]
    assert object_points(frames, masks)[1] is None  # lifted: what surrounds it in the images is not its support
    seen = in_hand_keypoints(env, SPEC, 0.0, perception.poses(env, SPEC, ["cube"])["cube"])
    assert np.linalg.norm(seen - in_hand_keypoints(env, SPEC, 0.0), axis=1).max() < 0.01


def test_a_grasped_object_is_carried_from_where_it_was_last_seen():
    """After grasped() the object's pose moves with the grip site from where the cameras last saw it, relative to
    the commanded grasp pose; released() gives it back to the cameras, lying where the jaws carried it; reseed() forgets both."""
    from kpflow.tasks.suite.keypoints import ObjectPose

    class Hand:  # the grip site's pose, as a SuiteEnv reports it
        def __init__(self, pos, rot):
            self.pose = (np.asarray(pos, float), np.asarray(rot, float))

        def ee_pose(self):
            return self.pose

    perception = CameraKeypoints(noise=CameraNoise.off())
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    perception.last["cube"] = ObjectPose(np.array([0.1, 0.0, 0.82]), np.eye(3), 0.02)
    perception.grasped(Hand([9, 9, 9], np.eye(3)), "cube", at=(np.array([0.1, 0.0, 0.83]), np.eye(3)))
    now = Hand([0.0, 0.2, 1.0], turn)  # moved and turned a quarter
    carried = perception.poses(now, SPEC, ["cube"])["cube"]  # no capture: the held object is not looked for
    np.testing.assert_allclose(carried.pos, [0.0, 0.2, 0.99])
    np.testing.assert_allclose(carried.rot, turn)
    assert carried.half == 0.02
    perception.released(now, "cube")  # set down where the jaws carried it, until a whole read says otherwise
    assert perception.held == {}
    np.testing.assert_allclose(perception.last["cube"].pos, [0.0, 0.2, 0.99])
    perception.grasped(now, "cube", at=now.pose)
    perception.missed("cube")  # the jaws closed on nothing: it lies where the cameras last saw it
    assert perception.held == {}
    np.testing.assert_allclose(perception.last["cube"].pos, [0.0, 0.2, 0.99])
    perception.grasped(now, "cube", at=now.pose)
    perception.reseed(4)
    assert perception.held == perception.last == {}
