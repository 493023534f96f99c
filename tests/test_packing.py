"""Packing with a UR5e in robosuite (real MuJoCo, rendering headless): scenes, perception, the scripted
demonstration, transport and one transported trial end to end."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from kpflow.eval.demo_transport_trial import DemoTransportTrial
from kpflow.eval.reports.packing import PackingReport, box_corner_error
from kpflow.geometry.angles import yaw_of
from kpflow.maps import AffineMap, GPMap, ILWRMap
from kpflow.policies.demo_transport import DemoTransportPolicy
from kpflow.tasks.packing.demonstrator import execute
from kpflow.tasks.packing.env import START_POS
from kpflow.tasks.packing.keypoints import GROUPS, LIFT, N_KEYPOINTS, packing_keypoints
from kpflow.tasks.packing.objects import OBJECT_TYPES
from kpflow.tasks.packing.perception import box_corners, canonical_box, object_box, topdown_frame
from kpflow.tasks.packing.scene import CONTAINER_SIZE, OBJECT_AREA, SOURCE_SCENE, TABLE_TOP, Scene, sample_scene
from kpflow.tasks.packing.task import PackingTask
from kpflow.trajectory import Keypoints
from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]


TASK = PackingTask()


@pytest.fixture(scope="module")
def env():
    torch.set_num_threads(1)
    return TASK.make_env()


@pytest.fixture(scope="module")
def source(env):
    return TASK.demonstrate(env)


# ------------------------------------------------------------------------------------------------ scenes


def test_scenes_are_seeded_and_follow_their_condition():
    relocated = [sample_scene("relocation", i) for i in range(30)]
    full = [sample_scene("full", i) for i in range(30)]
    assert sample_scene("full", 3) == full[3] and sample_scene("full", 3, seed=1) != full[3]
    (x0, x1), (y0, y1) = OBJECT_AREA
    for s in relocated + full:
        x, y, yaw = s.object_pose
        assert x0 <= x <= x1 and y0 <= y <= y1 and -np.pi <= yaw <= np.pi
        gap = np.hypot(x - s.container_pose[0], y - s.container_pose[1])
        assert gap > np.hypot(*CONTAINER_SIZE[:2]) / 2  # never on the container
    assert all(
        s.object_type == SOURCE_SCENE.object_type and s.container_pose == SOURCE_SCENE.container_pose for s in relocated
    )
    assert all(
        s.object_type != SOURCE_SCENE.object_type and s.container_pose != SOURCE_SCENE.container_pose for s in full
    )
    assert len({s.object_type for s in full}) >= 4
    with pytest.raises(ValueError, match="unknown object type"):
        Scene("sphere", (0, 0, 0), (0, 0.3, 0))
    with pytest.raises(ValueError, match="object_pose"):
        Scene("can", (0, float("nan"), 0), (0, 0.3, 0))
    with pytest.raises(ValueError, match="condition"):
        sample_scene("swapped", 0)


# -------------------------------------------------------------------------------------------- perception


def test_backprojection_and_box_geometry():
    k = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    depth = np.full((48, 64), 2.0)
    image = {"rgb": np.zeros((48, 64, 3), np.uint8), "depth": depth, "intrinsics": k, "camera_to_world": pose}
    pts = topdown_frame(image).points().reshape(48, 64, 3)
    np.testing.assert_allclose(pts[24, 32], (1.0 + 0.5 * 2 / 100, 2.0 + 0.5 * 2 / 100, 5.0))  # pixel centre
    assert np.allclose(pts[..., 2], 5.0) and pts[0, 1, 0] - pts[0, 0, 0] == pytest.approx(0.02)
    centre, size, yaw = canonical_box((0.0, 0.0), (0.02, 0.06), 0.1, reference_yaw=0.0)
    assert size[0] > size[1] and yaw == pytest.approx(0.1 + np.pi / 2 - np.pi)  # long axis first, nearest yaw 0
    _, _, yaw = canonical_box((0.0, 0.0), (0.06, 0.02), 3.0, reference_yaw=0.0)
    assert yaw == pytest.approx(3.0 - np.pi)
    corners = box_corners((0.0, 0.0), (0.2, 0.1), 0.0, 0.0, 0.3)
    np.testing.assert_allclose(corners[:4], [[-0.1, -0.05, 0], [0.1, -0.05, 0], [0.1, 0.05, 0], [-0.1, 0.05, 0]])
    np.testing.assert_allclose(corners[4:, :2], corners[:4, :2])
    assert np.all(corners[4:, 2] == 0.3)


@pytest.mark.slow
def test_env_resets_to_a_scene_and_steps(env):
    scene = Scene("box_small", (0.0, -0.3, 0.7), (-0.05, 0.36, 0.3))
    env.reset_to(scene)
    centre, rot, half = env.object_box()
    np.testing.assert_allclose(centre[:2], scene.object_pose[:2], atol=2e-3)
    assert centre[2] - half[2] == pytest.approx(TABLE_TOP, abs=3e-3)  # resting on the table
    assert np.arctan2(rot[1, 0], rot[0, 0]) == pytest.approx(0.7, abs=0.01)
    pos, crot = env.container_frame()
    np.testing.assert_allclose(pos[:2], scene.container_pose[:2], atol=1e-9)
    assert np.arctan2(crot[1, 0], crot[0, 0]) == pytest.approx(0.3, abs=1e-9)
    tip, tip_rot = env.ee_pose()
    assert np.linalg.norm(tip - START_POS) < 0.01 and tip_rot[2, 2] < -0.99  # at the start pose, pointing down
    err = env.move_to(tip + (0.05, 0.05, -0.05), tip_rot, settle=20)
    assert err < 0.01
    assert not env.holding() and not env.object_in_container() and not env.suction_on()  # too far to seal


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(OBJECT_TYPES))
def test_object_box_from_the_camera_matches_the_simulator(env, kind):
    scene = Scene(kind, (-0.05, -0.2, 0.9), SOURCE_SCENE.container_pose)
    env.reset_to(scene)
    box, (centre, _, half) = object_box(env.render_topdown(), TABLE_TOP), env.object_box()
    pos, rot = env.container_frame()
    kp = {"keypoints": packing_keypoints(env.ee_pose(), box, pos, yaw_of(rot))}
    assert kp["keypoints"].shape == (N_KEYPOINTS, 3)
    assert abs(box["top"] - (centre[2] + half[2])) < 3e-3  # mm-level top height
    assert np.linalg.norm(box["centre"] - centre[:2]) < 4e-3
    if kind.startswith("box") or kind == "cereal":  # boxes: every corner within a few mm
        assert 1e3 * box_corner_error(box["corners"], env.object_box()) < 3.0
    np.testing.assert_allclose(
        kp["keypoints"][GROUPS["lifted"]] - kp["keypoints"][GROUPS["object"]], np.tile([0, 0, LIFT], (8, 1))
    )


def test_keypoints_from_the_simulator_or_the_noisy_camera(env):
    """keypoints=sim reads the object's box and the container from the simulator; keypoints=camera perceives both in
    the noisy top-down image, the same for the same scene whichever scenes came before."""
    from kpflow.vision.keypoint_source import KeypointSource

    scene, other = sample_scene("full", 3), sample_scene("full", 4)
    view = TASK._view(env, scene, 0.0)
    assert (
        box_corner_error(view.box["corners"], view.true_box) < 5e-4
    )  # the bottom at the table top, the object 0.1 mm off it
    camera = PackingTask(keypoints=KeypointSource("camera", seed=2))
    assert camera.keypoint_sources == ("camera",)
    seen = camera._view(env, scene, 0.0, view.container_yaw)
    camera._view(env, other, 0.0)
    np.testing.assert_array_equal(seen.keypoints, camera._view(env, scene, 0.0, view.container_yaw).keypoints)
    container = GROUPS["container"]
    assert 0 < np.linalg.norm(seen.keypoints[container] - view.keypoints[container], axis=1).max() < 0.015
    assert abs(seen.container_yaw - view.container_yaw) < np.radians(2)
    assert 1e3 * box_corner_error(seen.box["corners"], seen.true_box) < 20  # mm: the D435's noise and calibration
    with pytest.raises(ValueError, match="reads its keypoints from 'camera', not 'sim'"):
        camera.observe(env, scene, None, "sim")
    with pytest.raises(ValueError, match="packing's camera is its one top-down camera"):
        PackingTask(keypoints=KeypointSource("camera", cameras=("frontview",)))


# ----------------------------------------------------------------------------------- demonstration, transport


@pytest.mark.slow
def test_scripted_demonstration_packs_the_source_object(source):
    assert source.execution.success and source.execution.grasp_step is not None
    phases = list(dict.fromkeys(source.trajectory.phases))
    assert phases == ["approach", "descend", "seal", "lift", "carry", "lower", "release", "retreat"]
    steps = np.linalg.norm(np.diff(source.trajectory.positions, axis=0), axis=-1)
    assert steps.max() <= 0.015 + 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("make_map", [GPMap, ILWRMap, AffineMap])
def test_identical_scenes_reproduce_the_demonstration(source, make_map):
    kp = source.observation.keypoints
    moved, _ = DemoTransportPolicy(make_map).plan(source.trajectory, Keypoints(kp, kp))
    np.testing.assert_allclose(moved.positions, source.trajectory.positions, atol=1e-5)
    np.testing.assert_allclose(moved.rotations, source.trajectory.rotations, atol=1e-5)
    np.testing.assert_array_equal(moved.grasp, source.trajectory.grasp)
    assert moved.std.shape == (len(moved), 3)
    with pytest.raises(ValueError, match="source and target keypoints"):
        Keypoints(kp, kp[:31])


@pytest.mark.slow
def test_a_transported_demonstration_packs_a_moved_object(env, source):
    runner = DemoTransportTrial(TASK, PackingReport(), {"gp": GPMap})
    runner.env, runner.source = env, source  # the module's simulator and recording (what setup() would build)
    trial = runner.run_scene(sample_scene("relocation", 0), "sim", GPMap, variant={"map": "gp"})
    assert trial.success, trial.failure
    assert trial.scores["box_error_mm"] < 3.0 and trial.record()["map"] == "gp"
    tip = trial.artefacts["execution"].tip
    assert np.linalg.norm(tip[0] - source.trajectory.positions[0]) < 0.05  # starts where the source started


@pytest.mark.slow
def test_execute_reports_why_a_trial_failed(env, source):
    env.reset_to(sample_scene("relocation", 1))
    result = execute(env, source.trajectory)  # the source's motion, untransported: the object is elsewhere
    assert not result.success and result.failure == "not grasped"
    with pytest.raises(ValueError, match="NaN"):
        dataclasses.replace(source.trajectory, positions=np.full_like(source.trajectory.positions, np.nan))


@pytest.mark.slow
def test_evaluate_packing_cli_writes_table_plot_video_and_config(tmp_path):
    cmd = [
        "experiment=packing", "experiment.n_trials=1", "workers=1", "logger=none",
        "experiment.conditions=[full]", "~experiment.trial.maps.ilwr", f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    done = run_command("kpflow.cli.evaluate", *cmd)  # in this process: what kpflow-evaluate runs, without re-importing
    assert done.returncode == 0, done.stderr[-3000:]
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["task"]["source"]["object_type"] == SOURCE_SCENE.object_type and cfg["experiment"]["n_trials"] == 1
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["source"]["success"] and {s["map"] for s in results["summary"]} == {"gp", "affine"}
    assert all(t["success"] or t["failure"] for t in results["trials"])
    assert "| full | gp | 1 |" in (tmp_path / "results.md").read_text()
    assert (tmp_path / "trajectories.png").stat().st_size > 0 and list(tmp_path.glob("full_gp_*.mp4"))
