"""robosuite's own benchmark tasks (kpflow/tasks/suite) and generation by segment transport (kpflow/eval/generation):
real robosuite 1.5 environments with the Panda's parallel-jaw gripper, headless on the CPU."""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kpflow.data.episode_store import EpisodeStore
from kpflow.generation.robomimic_export import export_robomimic
from kpflow.maps import GPMap, ILWRMap
from kpflow.tasks.suite.keypoints import object_keypoints
from kpflow.tasks.suite.objects import reduced_yaw
from kpflow.tasks.suite.scene import Scene
from kpflow.tasks.suite.specs import TASKS, task_spec
from kpflow.tasks.suite.task import SuiteTask
from kpflow.trajectory import Trajectory
from tests.helpers import bare_kcfm

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def worlds():
    """One environment per task and its scripted demonstration in the first d0 scene."""
    out = {}
    for name in TASKS:
        task = SuiteTask(name)
        env = task.make_sim()
        segments, success, failure = task.demonstrate(env, task.sample_scene(env, "d0", 0))
        out[name] = (task, env, segments, success, failure)
    return out


@pytest.mark.parametrize("name", sorted(TASKS))
def test_the_scripted_source_succeeds_by_robosuites_own_check(worlds, name):
    task, env, segments, success, failure = worlds[name]
    assert success and failure is None and env.success()
    assert [s.name for s in segments] == list(task.spec.segments)
    closed = np.concatenate([s.trajectory.grasp for s in segments])
    assert closed.any() and not closed.all()  # the jaws close on the object (and open again to place it)


@pytest.mark.parametrize("name", sorted(TASKS))
def test_each_task_resets_to_its_scene_and_the_jaws_close(worlds, name):
    task, env, *_ = worlds[name]
    scene = task.sample_scene(env, "wide", 3)
    env.reset_to(scene)
    for obj, (pos, quat) in scene.objects.items():
        assert np.linalg.norm(env.object_pose(obj)[0][:2] - np.asarray(pos)[:2]) < 0.01
    pos, rot = env.ee_pose()
    fingers = env.env.robots[0]._ref_gripper_joint_pos_indexes["right"]
    opened = np.abs(env.sim.data.qpos[fingers]).sum()
    for _ in range(10):
        env.command(pos, rot, 1.0)
    assert np.abs(env.sim.data.qpos[fingers]).sum() < opened - 0.01 and env.gripper_closed()


def test_scenes_are_seeded_and_the_wide_variant_is_wider(worlds):
    task, env, *_ = worlds["stack"]
    a, b = task.sample_scene(env, "d0", 5), task.sample_scene(env, "d0", 5)
    assert a.as_dict() == b.as_dict() and a.as_dict() != task.sample_scene(env, "d0", 6).as_dict()
    spread = {
        v: np.ptp([task.sample_scene(env, v, i).objects["cubeA"][0][0] for i in range(30)]) for v in ("d0", "wide")
    }
    assert spread["d0"] <= 0.16 + 1e-9 and spread["wide"] > 0.2
    square, senv, *_ = worlds["square"]
    offsets = [square.sample_scene(senv, "wide", i).fixture_offsets["peg"] for i in range(10)]
    assert len({tuple(o) for o in offsets}) == 10
    first = square.sample_scene(senv, "wide", 0).as_dict()
    senv.reset_to(square.sample_scene(senv, "wide", 1))  # the peg moves in the model: the draw must not follow it
    assert square.sample_scene(senv, "wide", 0).as_dict() == first
    senv.reset_to(square.sample_scene(senv, "wide", 0))
    peg, nut = senv.object_pose("peg")[0], senv.object_pose("nut")[0]
    assert np.linalg.norm((peg - nut)[:2]) >= square.spec.fixture_clearance - 0.01
    assert Scene.from_dict(a.as_dict()).as_dict() == a.as_dict()


def _outside(value: float, lo: float, hi: float) -> bool:
    return value < lo - 1e-9 or value > hi + 1e-9


def test_far_scenes_leave_every_generated_range_and_resized_ones_scale_the_objects(worlds):
    """``far``: each task's object or fixture outside the d0 and wide ranges (the peg also turned, in the model and
    in its keypoints); ``resized``: the cubes scaled within the range, standing on the table."""
    lift, lenv, *_ = worlds["lift"]
    for i in range(10):
        x, y, _ = lift.sample_scene(lenv, "far", i).objects["cube"][0]
        assert _outside(y, -0.15, 0.15)  # the wide square's side
    can, cenv, *_ = worlds["can"]
    wide_x = cenv.fixture_home["bin"][0] + np.array(can.spec.wide_fixtures["bin"][0])
    for i in range(10):
        scene = can.sample_scene(cenv, "far", i)
        assert _outside(cenv.fixture_home["bin"][0] + scene.fixture_offsets["bin"][0], *wide_x)
    square, senv, *_ = worlds["square"]
    for i in range(10):
        scene = square.sample_scene(senv, "far", i)
        nut_x = scene.objects["nut"][0][0]
        assert _outside(nut_x, -0.115, 0.115)
        senv.reset_to(scene)
        peg_pos, peg_rot = senv.object_pose("peg")
        assert abs(peg_pos[1]) >= 0.2 - 1e-6 and np.sign(peg_pos[1]) != np.sign(senv.object_pose("nut")[0][1])
        turn = scene.fixture_yaws["peg"]
        assert np.radians(20) - 1e-6 <= abs(turn) <= np.radians(45) + 1e-6
        np.testing.assert_allclose(peg_rot, Rotation.from_euler("z", turn).as_matrix(), atol=1e-9)
        keypoints = object_keypoints("peg", peg_pos, peg_rot)
        edge = keypoints[3] - keypoints[2]  # two top corners: the edge turns with the peg, modulo the square's symmetry
        angle = np.arctan2(edge[1], edge[0])
        assert abs(((angle - turn + np.pi / 4) % (np.pi / 2)) - np.pi / 4) < 1e-6
    stack, kenv, *_ = worlds["stack"]
    scene = stack.sample_scene(kenv, "resized", 0)
    assert set(scene.scales) == {"cubeA", "cubeB"} and all(0.7 <= s <= 1.4 for s in scene.scales.values())
    kenv.reset_to(scene)
    for name, scale in scene.scales.items():
        half = kenv.home_half_height(name) * scale
        assert abs(kenv.object_pose(name)[0][2] - (kenv.env.table_offset[2] + half)) < 2e-3
    assert (
        Scene.from_dict(square.sample_scene(senv, "far", 0).as_dict()).fixture_yaws
        == square.sample_scene(senv, "far", 0).fixture_yaws
    )
    assert stack.spec.variants == ("d0", "wide", "far", "resized", "d1") and square.spec.variants == (
        "d0",
        "wide",
        "far",
        "d1",
        "d2",
    )


def test_mimicgens_d1_and_d2_draw_within_its_ranges_the_nut_clear_of_the_peg(worlds):
    """MimicGen's Square_D1 / D2 and Stack_D1 (kpflow/tasks/suite/specs.py cites its task definitions): the nut within
    +-0.115 x +-0.255 / +-0.25 m, the peg within its world ranges (as built in D1, turned 0-90 degrees in D2), their
    centres farther apart than MimicGen's test reads from the models (the peg geom's half sides' norm plus the nut's
    ``horizontal_radius``), the round peg at x = -10 m as its ``_load_model`` puts it (and back where robosuite builds
    it in the other variants); Stack's cubes within +-0.2 m."""
    square, senv, *_ = worlds["square"]
    model = senv.sim.model
    peg_geom = np.flatnonzero(model.geom_bodyid == model.body_name2id("peg1"))[0]
    clearance = np.linalg.norm(model.geom_size[peg_geom][:2]) + senv.env.nuts[0].horizontal_radius
    assert square.spec.mimicgen["d1"].clearance == pytest.approx(clearance, abs=1e-9)
    round_peg = model.body_name2id("peg2")
    senv.reset_to(square.sample_scene(senv, "wide", 0))
    built = senv.sim.data.xpos[round_peg].copy()
    turns = []
    for variant, (nut_x, nut_y), (peg_x, peg_y) in (("d1", (0.115, 0.255), ((-0.1, 0.3), (-0.2, 0.2))),
                                                     ("d2", (0.25, 0.25), ((-0.25, 0.25), (-0.25, 0.25)))):  # fmt: skip
        for i in range(8):
            scene = square.sample_scene(senv, variant, i)
            senv.reset_to(scene)
            nut, peg = senv.object_pose("nut")[0], senv.object_pose("peg")[0]
            assert abs(nut[0]) <= nut_x + 1e-9 and abs(nut[1]) <= nut_y + 1e-9
            assert peg_x[0] - 1e-9 <= peg[0] <= peg_x[1] + 1e-9 and peg_y[0] - 1e-9 <= peg[1] <= peg_y[1] + 1e-9
            assert np.linalg.norm((peg - nut)[:2]) > clearance
            np.testing.assert_allclose(senv.sim.data.xpos[round_peg][:2], (-10.0, 0.0))
            assert Scene.from_dict(scene.as_dict()) == scene
            turns.append((variant, scene.fixture_yaws.get("peg", 0.0)))
    senv.reset_to(square.sample_scene(senv, "wide", 0))
    np.testing.assert_allclose(
        senv.sim.data.xpos[round_peg], built
    )  # wide keeps the round peg where robosuite builds it
    with pytest.raises(ValueError, match=r"removes \['bin2'\], which no variant of square removes"):
        senv.reset_to(Scene.from_dict({**scene.as_dict(), "removed": ["bin2"]}))
    assert all(t == 0.0 for v, t in turns if v == "d1") and all(0.0 <= t <= np.pi / 2 for v, t in turns if v == "d2")
    assert len({t for v, t in turns if v == "d2"}) == 8
    stack, kenv, *_ = worlds["stack"]
    cubes = np.array(
        [stack.sample_scene(kenv, "d1", i).objects[c][0][:2] for i in range(20) for c in ("cubeA", "cubeB")]
    )
    assert np.abs(cubes).max() <= 0.2 + 1e-9 and np.ptp(cubes[:, 0]) > 0.2
    assert (
        stack.sample_scene(kenv, "d1", 0).as_dict() != stack.sample_scene(kenv, "wide", 0).as_dict()
    )  # other scenes, same ranges


def test_bad_scenes_tasks_and_variants_are_refused_by_name(worlds):
    with pytest.raises(ValueError, match="quaternion"):
        Scene({"cube": ((0.0, 0.0, 0.8), (2.0, 0.0, 0.0, 0.0))})
    with pytest.raises(ValueError, match="unknown robosuite task 'door'"):
        task_spec("door")
    task, env, *_ = worlds["lift"]
    with pytest.raises(ValueError, match="unknown variant 'd9'"):
        task.sample_scene(env, "d9", 0)


def test_symmetric_keypoints_turn_the_gripper_least():
    # closed form: the quarter turn nearest the reference
    assert reduced_yaw(np.pi - 0.1, 4, 0.0) == pytest.approx(-0.1)
    assert reduced_yaw(2.0, 2, 0.0) == pytest.approx(2.0 - np.pi)
    assert reduced_yaw(2.0, 1, 0.0) == pytest.approx(2.0)
    pos = np.array([0.1, 0.0, 0.82])
    for kind in ("cube", "peg"):  # a quarter turn leaves the keypoints where they were, in the same order
        r0, r1 = (Rotation.from_euler("z", y).as_matrix() for y in (0.3, 0.3 + np.pi / 2))
        np.testing.assert_allclose(
            object_keypoints(kind, pos, r0, 0.3, half=0.02), object_keypoints(kind, pos, r1, 0.3, half=0.02), atol=1e-12
        )
    spun = [object_keypoints("can", pos, Rotation.from_euler("z", y).as_matrix(), 0.0) for y in (0.0, 1.0, 2.5)]
    np.testing.assert_allclose(spun[0], spun[1], atol=1e-12)
    np.testing.assert_allclose(spun[0], spun[2], atol=1e-12)  # a can has no yaw to transport
    nut = [object_keypoints("nut", pos, Rotation.from_euler("z", y).as_matrix(), 0.0) for y in (0.0, np.pi / 2)]
    assert np.abs(nut[0] - nut[1]).max() > 0.05  # the handle fixes the nut's yaw


@pytest.mark.parametrize("family", ["mimicgen", "ilwr", "gp"])
def test_transport_into_the_source_scene_reproduces_the_source(worlds, family):
    from kpflow.generation.segment_transport import SegmentTransport

    transport = SegmentTransport({"mimicgen": None, "ilwr": ILWRMap, "gp": GPMap}[family], in_hand=family != "mimicgen")
    task, env, segments, *_ = worlds["square"]
    for segment in segments:
        carried = transport.carry(segment, segment.start)
        np.testing.assert_allclose(carried.positions, segment.trajectory.positions, atol=1e-7)
        np.testing.assert_allclose(carried.rotations, segment.trajectory.rotations, atol=1e-7)
        np.testing.assert_array_equal(carried.grasp, segment.trajectory.grasp)


def test_failure_reasons(worlds):
    task, env, *_ = worlds["lift"]
    env.reset_to(task.sample_scene(env, "d0", 1))
    pos, rot = env.ee_pose()
    n = 20
    closing_in_the_air = Trajectory(
        np.repeat(pos[None], n, 0), np.repeat(rot[None], n, 0), np.ones(n, bool), np.full(n, "close")
    )
    assert task.run_segment(env, closing_in_the_air).failure is None
    assert task.segment_failure(env, "pick") == "not grasped"
    far = pos + [1.5, 0.0, 0.0]
    unreachable = Trajectory(
        np.repeat(far[None], n, 0), np.repeat(rot[None], n, 0), np.zeros(n, bool), np.full(n, "approach")
    )
    assert task.run_segment(env, unreachable).failure in ("unreachable", "joint limit")
    assert task.finish(env, unreachable) == (False, "not lifted")


def test_the_source_distance_is_mimicgens_pose_measure_and_the_keypoints_see_symmetry():
    from functools import partial

    from kpflow.core.task import SegmentStart
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap

    def start(pos, yaw):
        rot = Rotation.from_euler("z", yaw).as_matrix()
        return SegmentStart(
            {"cube": (pos, rot)}, {"cube": object_keypoints("cube", pos, rot, 0.3, half=0.02)}, {"cube": yaw}, pos[None]
        )

    pos = np.array([0.1, 0.0, 0.82])
    source, now = (
        start(pos, 0.3),
        start(pos + [0.03, 0.04, 0.0], 0.3 + np.pi / 2 + 0.2),
    )  # 5 cm, a quarter turn and 0.2 rad
    mimicgen, rigid = SegmentTransport(None, in_hand=False), SegmentTransport(partial(AffineMap, kind="rigid"))
    assert mimicgen.distance(source, now) == pytest.approx(
        0.05 + np.pi / 2 + 0.2
    )  # MimicGen's |dp| + angle, pos/rot weights 1
    assert rigid.distance(source, now) == pytest.approx(
        0.05 + 0.2, abs=1e-9
    )  # a cube looks the same after a quarter turn
    assert mimicgen.distance(source, source) == pytest.approx(0.0) and rigid.distance(source, source) == pytest.approx(
        0.0, abs=1e-9
    )


def test_the_nearest_source_is_chosen_in_its_own_scene_and_random_choice_is_seeded(worlds):
    from dataclasses import replace
    from functools import partial

    from kpflow.generation.generate import Generator
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap

    task, env, segments, *_ = worlds["square"]

    def shifted(segment, dx):  # the same segment recorded with every object 20 cm away
        start = segment.start
        poses = {k: (p + dx, r) for k, (p, r) in start.poses.items()}
        return replace(
            segment, start=replace(start, poses=poses, keypoints={k: v + dx for k, v in start.keypoints.items()})
        )

    far = [shifted(s, np.array([0.2, 0.0, 0.0])) for s in segments]
    for family in (SegmentTransport(None, in_hand=False), SegmentTransport(partial(AffineMap, kind="rigid"))):
        nearest = Generator(task, {"f": family}, n_sources=2, candidates=1)
        nearest.env, nearest.sources = env, [far, segments]
        env.reset_to(task.sample_scene(env, "d0", 0))  # the scene the real source was recorded in
        assert [nearest.choose_source(family, i) for i in range(5)] == [1] * 5
    anyone = Generator(task, {"f": family}, n_sources=2)
    anyone.env, anyone.sources = env, [far, segments]
    drawn = [anyone.choose_source(family, i) for i in range(40)]
    assert drawn == [anyone.choose_source(family, i) for i in range(40)] and set(drawn) == {0, 1}
    with pytest.raises(ValueError, match="candidates"):
        Generator(task, {"f": family}, candidates=0)


def test_a_failed_check_ends_the_attempt_or_runs_on_to_the_success_test(worlds):
    from dataclasses import replace

    from kpflow.generation.generate import Generator
    from kpflow.generation.segment_transport import SegmentTransport

    task, env, segments, *_ = worlds["square"]
    pick, place = segments
    open_jaws = replace(pick, trajectory=replace(pick.trajectory, grasp=np.zeros_like(pick.trajectory.grasp)))
    family = SegmentTransport(None, in_hand=False)
    records = {}
    for stop_early in (True, False):
        generator = Generator(task, {"f": family}, stop_early=stop_early)
        generator.env, generator.sources = env, [[open_jaws, place]]
        records[stop_early] = generator.attempt("d0", 0, "f")[0]  # the source's own scene, the jaws never closing
    assert records[True]["failure"] == records[False]["failure"] == "not grasped"
    assert not records[True]["success"] and not records[False]["success"]
    # stopped after the pick, or ran the place too
    assert (
        len(pick.trajectory)
        <= records[True]["steps"]
        < len(pick.trajectory) + len(place.trajectory)
        <= records[False]["steps"]
    )


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """Two generation attempts per family on lift's d0 scenes, written like a CLI run."""
    from kpflow.generation.generate import generate
    from kpflow.generation.segment_transport import SegmentTransport

    out = tmp_path_factory.mktemp("generated")
    families = {"mimicgen": SegmentTransport(None, in_hand=False), "gp": SegmentTransport(GPMap)}
    return out, generate(out, SuiteTask("lift"), families, ["d0"], n=2, workers=1, videos=0, progress=False)


def test_one_generation_run_end_to_end_with_its_store_and_robomimic_export(generated):
    tmp_path, results = generated
    rows = {r["family"]: r for r in results["summary"]}
    assert set(rows) == {"mimicgen", "gp"} and all(r["trials"] == 2 for r in rows.values())
    assert rows["gp"]["successes"] >= 1
    saved = json.loads((tmp_path / "results.json").read_text())
    assert len(saved["attempts"]) == 4 and "| d0 | gp | 2 |" in (tmp_path / "results.md").read_text()
    with EpisodeStore(tmp_path / "d0" / "gp" / "episodes.zarr") as store:
        assert store.n_episodes == rows["gp"]["successes"]
        episode = store.episode(0)
        t = len(episode["action"])
        assert (
            episode["action"].shape == (t, 7)
            and episode["ee_target"].shape == (t, 10)
            and episode["keypoints"].shape == (t, 11, 3)
        )
        np.testing.assert_allclose(episode["ee_target"][:, :3], episode["action"][:, :3])
    with h5py.File(tmp_path / "d0" / "gp" / "demos.hdf5", "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        assert env_args["env_name"] == "Lift" and env_args["type"] == 1
        assert env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]["input_type"] == "absolute"
        demo = f["data/demo_0"]
        t = demo.attrs["num_samples"]
        assert (
            demo["actions"].shape == (t, 7)
            and demo["states"].shape[0] == t
            and demo["obs/robot0_eef_pos"].shape == (t, 3)
        )
        assert demo["obs/keypoints"].shape == (t, 11, 3)
        assert demo["dones"][-1] == 1 and demo["rewards"][:-1].sum() == 0
        assert f["data"].attrs["total"] == sum(f[f"data/{k}"].attrs["num_samples"] for k in f["data"])
        assert [n.decode() for n in f["mask/train"][:]] == sorted(f["data"], key=lambda k: int(k.split("_")[1]))


def test_generation_refuses_an_earlier_runs_folder_unless_resumed_with_its_settings(generated):
    from kpflow.generation.generate import generate
    from kpflow.generation.segment_transport import SegmentTransport

    out, _ = generated
    before = (out / "results.json").read_text()
    with pytest.raises(FileExistsError, match="already holds a generation run .* pass resume=true"):
        generate(
            out, SuiteTask("lift"), {"gp": SegmentTransport(GPMap)}, ["d0"], n=1, workers=1, videos=0, progress=False
        )
    with pytest.raises(
        ValueError, match=r"generation.json: resume=true continues a run with its own settings.*families"
    ):
        generate(
            out,
            SuiteTask("lift"),
            {"gp": SegmentTransport(GPMap)},
            ["d0"],
            n=1,
            workers=1,
            videos=0,
            progress=False,
            resume=True,
        )
    assert (out / "results.json").read_text() == before


@pytest.mark.parametrize("objective", ["icfm", "ddpm"])  # K-CFM and the DP-equivalent baseline
def test_a_policy_trained_on_generated_demos_drives_the_arm_in_closed_loop(generated, tmp_path, objective):
    import lightning

    from kpflow.core.rollout import rollout
    from kpflow.data.chunks import ChunkDataModule
    from kpflow.policies.kcfm.model import KCFM

    out, _ = generated
    data = ChunkDataModule(out / "d0" / "gp" / "episodes.zarr", horizon=16, obs_key="keypoints", action_key="ee_target",
                           val_fraction=0.0, batch_size=64, n_obs=2)  # fmt: skip
    model = KCFM(horizon=16, n_obs=2, n_keypoints=11, keypoint_dim=3, action_dim=10, network={"name": "unet", "down_dims": (16, 32)},
                 objective=objective)  # fmt: skip
    trainer = lightning.Trainer(max_steps=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                enable_model_summary=False, limit_val_batches=0, default_root_dir=tmp_path)  # fmt: skip
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    policy = bare_kcfm(tmp_path / "last.ckpt", steps=2, execute=8)
    assert type(policy.model.objective) is type(model.objective)
    with pytest.raises(ValueError, match=r"\[B, 2, 11, 3\]"):
        policy.model.sample(np.zeros((2, 11, 2)))
    env = SuiteTask("lift").make_env("d0")
    episode = rollout(env, policy, 24, 0, {"seed": 0, "options": {"stream": 20_000}}, action_dim=10)
    assert episode.steps <= 24 and episode.decisions == (episode.steps + 7) // 8
    assert episode.first_info["scene"]["objects"].keys() == {"cube"}


def test_the_export_refuses_bad_episodes_and_leaves_nothing_behind(tmp_path):
    with pytest.raises(ValueError, match="lacks"):
        export_robomimic(tmp_path / "x.hdf5", [{"action": np.zeros((3, 7))}], "Lift", {})
    with pytest.raises(ValueError, match="differ in length"):
        export_robomimic(
            tmp_path / "x.hdf5",
            [{"action": np.zeros((3, 7)), "state": np.zeros((2, 5)), "ee_pos": np.zeros((3, 3))}],
            "Lift",
            {},
        )
    assert list(tmp_path.iterdir()) == []


def _rigid(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of the rigid fit (``fit_affine(..., "rigid")``) of one pair ``[N, 3]``, as numpy."""
    import torch

    from kpflow.geometry.alignment import fit_affine

    rot, t = fit_affine(torch.as_tensor(source[None]), torch.as_tensor(target[None]), "rigid")
    return rot[0].numpy(), t[0].numpy()


def test_the_in_hand_correction_moves_the_held_object_along_the_source_path():
    from functools import partial

    from kpflow.core.task import Segment, SegmentStart
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap

    rng = np.random.default_rng(0)
    held = rng.normal(size=(5, 3)) * 0.05  # the held object's keypoints in the source's hand frame
    turn, shift = Rotation.from_rotvec([0.1, -0.2, 2.5]).as_matrix(), np.array([0.02, -0.01, 0.03])
    r, t = _rigid(held, held @ turn.T + shift)  # closed form: Kabsch recovers the motion exactly
    np.testing.assert_allclose(r, turn, atol=1e-12)
    np.testing.assert_allclose(t, shift, atol=1e-12)
    n = 6
    rotations = Rotation.random(n, random_state=1).as_matrix()
    trajectory = Trajectory(rng.normal(size=(n, 3)), rotations, np.ones(n, bool), np.full(n, "carry"))
    goal = rng.normal(size=(6, 3))
    segment = Segment("place", trajectory, SegmentStart({}, {"peg": goal}, {}, np.zeros((1, 3)), held[None]))
    now = SegmentStart({}, {"peg": goal}, {}, np.zeros((1, 3)), (held @ turn.T + shift)[None])
    carried = SegmentTransport(partial(AffineMap, kind="rigid")).carry(segment, now)
    in_world = lambda rot, pos, points: np.einsum("tij,mj->tmi", rot, points) + pos[:, None]  # noqa: E731
    np.testing.assert_allclose(
        in_world(carried.rotations, carried.positions, now.in_hand[0]),
        in_world(rotations, trajectory.positions, held),
        atol=1e-9,
    )
    uncorrected = SegmentTransport(partial(AffineMap, kind="rigid"), in_hand=False).carry(segment, now)
    np.testing.assert_allclose(uncorrected.positions, trajectory.positions, atol=1e-9)  # the goal did not move


def test_the_six_dimensional_rotation_round_trips():
    from kpflow.geometry.rotations import matrix_to_rot6d, rot6d_to_matrix

    rotations = Rotation.random(20, random_state=2).as_matrix()
    np.testing.assert_allclose(rot6d_to_matrix(matrix_to_rot6d(rotations)), rotations, atol=1e-12)
    noisy = rot6d_to_matrix(matrix_to_rot6d(rotations) + 0.05)  # Gram-Schmidt gives a rotation for any input
    np.testing.assert_allclose(
        np.einsum("tji,tjk->tik", noisy, noisy), np.broadcast_to(np.eye(3), (20, 3, 3)), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(noisy), 1.0, atol=1e-12)


def test_a_symmetric_held_object_turns_into_its_chosen_order_on_the_way_about_its_centre():
    from kpflow.generation.segment_transport import in_hand_path, turn_ramp

    phases = np.array(["carry"] * 5 + ["lower"] * 3)
    np.testing.assert_allclose(turn_ramp(phases), [0, 0.25, 0.5, 0.75, 1, 1, 1, 1])
    np.testing.assert_allclose(turn_ramp(np.array(["carry"] * 3)), [0, 0.5, 1])
    ring = np.concatenate([np.zeros((1, 3)), [[0.05, 0.05, 0], [-0.05, 0.05, 0], [-0.05, -0.05, 0], [0.05, -0.05, 0]]])
    held = ring + [0.0, 0.01, 0.02]  # in the source's hand frame
    now = ring @ Rotation.from_rotvec([0, 0, 0.3]).as_matrix().T + [0.01, 0.0, 0.02]
    nearest = _rigid(held, now)
    chosen = _rigid(held, now[[0, 2, 3, 4, 1]])  # the same ring in the next order: a quarter turn more
    ramp = np.linspace(0, 1, 7)
    rots, shifts = in_hand_path(nearest, chosen, held.mean(0), ramp)
    np.testing.assert_allclose(rots[0], nearest[0], atol=1e-12)
    np.testing.assert_allclose(rots[-1], chosen[0], atol=1e-12)
    np.testing.assert_allclose(shifts[0], nearest[1], atol=1e-12)
    np.testing.assert_allclose(shifts[-1], chosen[1], atol=1e-12)
    centres = np.einsum("tij,j->ti", rots, held.mean(0)) + shifts
    np.testing.assert_allclose(centres, np.broadcast_to(now.mean(0), centres.shape), atol=1e-12)  # the centre stays
    angles = [Rotation.from_matrix(r @ nearest[0].T).magnitude() for r in rots]
    np.testing.assert_allclose(np.diff(angles), angles[-1] / 6, atol=1e-9)  # at a constant rate
    np.testing.assert_allclose(angles[-1], np.pi / 2, atol=1e-9)


def test_the_path_cost_sees_a_turn_the_long_way_round(worlds):
    from kpflow.geometry.angles import yaw_of
    from kpflow.tasks.suite.arm_limits import MAX_PLACE_TURN, path_cost
    from kpflow.tasks.suite.demonstrator import jaws_down

    task, env = worlds["square"][:2]
    env.reset_to(task.sample_scene(env, "d0", 0))
    pos, rot = env.ee_pose()
    yaw = yaw_of(rot)
    cost = path_cost(env)
    short = [jaws_down(yaw + a) for a in np.linspace(0, 0.5, 6)]
    assert np.isfinite(cost(np.tile(pos, (6, 1)), np.stack(short)))
    # the same end, reached by turning 2 pi - 0.5 the other way: past MAX_PLACE_TURN
    long = [jaws_down(yaw - a) for a in np.linspace(0, 2 * np.pi - 0.5, 40)]
    assert 2 * np.pi - 0.5 > MAX_PLACE_TURN
    assert cost(np.tile(pos, (40, 1)), np.stack(long)) == np.inf
    # one pose: its turn from the jaws now is counted the short way, whichever way a longer path took to it
    np.testing.assert_allclose(long[-1], short[-1], atol=1e-9)
    assert cost(pos[None], long[-1][None]) == cost(np.tile(pos, (6, 1)), np.stack(short))
    # a policy's chunk is rated the same from what it observes (the joints, the jaws' yaw from the finger pads)
    from kpflow.geometry.rotations import matrix_to_rot6d
    from kpflow.tasks.suite.keypoints import policy_keypoints

    obs = {"keypoints": policy_keypoints(env, task.spec), "joints": env.arm_joints()}
    chunk = np.concatenate([np.tile(pos, (6, 1)), matrix_to_rot6d(np.stack(short)), np.ones((6, 1))], 1)
    assert task.arm_limits.cost(obs, chunk) == pytest.approx(cost(np.tile(pos, (6, 1)), np.stack(short)), abs=1e-6)
    chunk[-1, 0] = env.base_position()[0] + 0.95  # one target beyond the arm's reach
    assert task.arm_limits.cost(obs, chunk) == np.inf
    with pytest.raises(ValueError, match=r"needs the arm's joints in the observation"):
        task.arm_limits.cost({"keypoints": obs["keypoints"]}, chunk)


def test_a_place_in_another_order_starts_as_the_source_and_ends_turned_with_the_centre_on_the_source_path():
    from functools import partial

    from kpflow.core.task import Segment, SegmentStart
    from kpflow.generation.segment_transport import SegmentTransport
    from kpflow.maps import AffineMap

    ring = np.concatenate([np.zeros((1, 3)), [[0.05, 0.05, 0], [-0.05, 0.05, 0], [-0.05, -0.05, 0], [0.05, -0.05, 0]]])
    held = ring + [0.0, 0.0, 0.03]  # the ring's centre 3 cm along the hand's axis
    n = 8
    rotations = Rotation.from_rotvec(np.linspace([0, 0, 0], [0, 0, 0.4], n)).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    positions = np.linspace([0.0, 0.0, 1.0], [0.2, 0.1, 0.9], n)
    trajectory = Trajectory(positions, rotations, np.ones(n, bool), np.array(["carry"] * 5 + ["lower"] * 3))
    goal = np.random.default_rng(4).normal(size=(6, 3))
    segment = Segment("place", trajectory, SegmentStart({}, {"peg": goal}, {}, np.zeros((1, 3)), held[None]))
    turned = lambda p, r: -Rotation.from_matrix(r[-1] @ rotations[-1].T).magnitude()  # noqa: E731  prefers a turned end
    now = SegmentStart({}, {"peg": goal}, {}, np.zeros((1, 3)), np.stack([held, held[[0, 2, 3, 4, 1]]]), turned)
    carried = SegmentTransport(partial(AffineMap, kind="rigid")).carry(segment, now)
    np.testing.assert_allclose(carried.rotations[0], rotations[0], atol=1e-9)  # the nearest order at the start
    np.testing.assert_allclose(carried.positions[0], positions[0], atol=1e-9)
    ends = [Rotation.from_matrix(carried.rotations[t] @ rotations[t].T).magnitude() for t in range(n)]
    np.testing.assert_allclose(
        ends, [0, np.pi / 8, np.pi / 4, 3 * np.pi / 8, np.pi / 2, np.pi / 2, np.pi / 2, np.pi / 2], atol=1e-9
    )
    centre = lambda rot, pos: np.einsum("tij,j->ti", rot, held.mean(0)) + pos  # noqa: E731
    np.testing.assert_allclose(centre(carried.rotations, carried.positions), centre(rotations, positions), atol=1e-9)


def test_the_builder_makes_every_suite_policy_from_config_and_a_transported_episode_runs(generated, tmp_path):
    """evaluate's configs (experiment=suite_policy) build the K-CFM, the transported K-CFM (its source index from the
    training store, or saved beside the checkpoint), policy transportation and nearest neighbour for a robosuite task
    through the one builder (kpflow.policies.factory); the transported K-CFM drives the arm in a far scene."""
    import lightning
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from kpflow.cli.release import release, release_source_index
    from kpflow.core.rollout import rollout
    from kpflow.data.chunks import ChunkDataModule
    from kpflow.policies.chunk_transport import TransportPolicy
    from kpflow.policies.kcfm.model import KCFM
    from kpflow.policies.kcfm.policy import KCFMPolicy
    from kpflow.policies.nearest import NearestNeighbourPolicy
    from kpflow.policies.transported_kcfm import TransportedKCFMPolicy

    out, _ = generated
    store = out / "d0" / "gp" / "episodes.zarr"
    data = ChunkDataModule(
        store, horizon=16, obs_key="keypoints", action_key="ee_target", val_fraction=0.0, batch_size=64, n_obs=2
    )
    model = KCFM(
        horizon=16,
        n_obs=2,
        n_keypoints=11,
        keypoint_dim=3,
        action_dim=10,
        network={"name": "unet", "down_dims": (16, 32)},
    )
    trainer = lightning.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                enable_model_summary=False, limit_val_batches=0, default_root_dir=tmp_path)  # fmt: skip
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    released = release(tmp_path / "last.ckpt", tmp_path / "suite_lift_kcfm.ckpt", ema_only=True)
    release_source_index(released, SuiteTask("lift").policy_layout, store, 200, action_key="ee_target")
    obs = {"keypoints_history": data.train_dataloader().dataset[0]["history"].numpy().astype(np.float64)}
    full, ema = bare_kcfm(tmp_path / "last.ckpt"), bare_kcfm(released)
    np.testing.assert_array_equal(
        full.act(obs), ema.act(obs)
    )  # sampling uses the EMA network: the release acts the same
    common = ["experiment=suite_policy", "task=lift"]
    expected = {
        "kcfm": (KCFMPolicy, [f"policy.checkpoint={released}"]),
        "transported_kcfm": (TransportedKCFMPolicy, [f"policy.checkpoint={released}"]),  # the index beside it
        "transported_kcfm ": (
            TransportedKCFMPolicy,
            [f"policy.checkpoint={tmp_path / 'last.ckpt'}", "data=suite_store", f"data.path={store}"],
        ),
        "transport": (TransportPolicy, ["data=suite_store", f"data.path={store}"]),
        "nearest": (NearestNeighbourPolicy, ["data=suite_store", f"data.path={store}"]),
    }
    policies = {}
    with initialize_config_dir(config_dir=str(ROOT / "kpflow" / "conf"), version_base="1.3"):
        for name, (cls, args) in expected.items():
            cfg = compose("evaluate", overrides=[*common, f"policy={name.strip()}", *args])
            policies[name] = instantiate(cfg.policy)
            assert isinstance(policies[name], cls), name
    transported = policies["transported_kcfm"]
    pick = transported.transports[0]  # segment by segment (the experiment's default): Lift's one phase, on the cube
    assert (
        transported.phases is not None
        and pick.fit_on.tolist() == list(range(8))
        and pick.pulled.tolist() == [8, 9, 10]
        and transported.rotation
    )
    env = SuiteTask("lift").make_env("far")
    episode = rollout(env, transported, 16, 0, {"seed": 0, "options": {"stream": 20_000}}, action_dim=10)
    assert (
        episode.steps == 16
        and episode.decisions == 2
        and transported.last_source is not None
        and transported.last_phase == "pick"
    )


def test_the_gymnasium_env_passes_gymnasiums_checker_and_draws_scenes_by_seed():
    """SuiteGymEnv (the one closed loop's env for the robosuite tasks) follows Gymnasium's API: its spaces, seeded
    resets (scene i for seed i, the same keypoints twice) and steps; an unseeded reset draws another scene."""
    import warnings

    from gymnasium.utils.env_checker import check_env

    env = SuiteTask("lift").make_env("d0")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the observation's keypoints are unbounded world coordinates
        check_env(env, skip_render_check=True)
    first, info = env.reset(seed=3, options={"stream": 20_000})
    again, _ = env.reset(seed=3, options={"stream": 20_000})
    np.testing.assert_array_equal(first["keypoints"], again["keypoints"])
    assert (
        info["scene"] == SuiteTask("lift").sample_scene(env.sim, "d0", 3, 20_000).as_dict() and not info["is_success"]
    )
    assert not np.array_equal(env.reset()[0]["keypoints"], first["keypoints"])
    with pytest.raises(ValueError, match="has no condition 'nope'"):
        SuiteTask("lift").make_env("nope")


def test_the_gymnasium_env_refuses_what_no_robot_should_receive():
    """Issue 63.7: NaN or inf, the wrong shape and a zero rotation are refused by name before robosuite sees them;
    a target beyond the action space's 2 m is clipped to it; the simulator's state stays finite."""
    from kpflow.tasks.suite.gym_env import WORKSPACE_M

    env = SuiteTask("lift").make_env("d0")
    with pytest.raises(RuntimeError, match=r"call reset\(\) before step\(\)"):
        env.step(np.zeros(10))
    env.reset(seed=0)
    pos, rot = env.sim.ee_pose()
    good = np.r_[pos, rot[:, 0], rot[:, 1], -1.0]  # hold still, open
    for bad, refused in [
        (np.r_[np.nan, good[1:]], r"action must be 10 finite numbers"),
        (np.r_[good[:9], np.nan], r"action must be 10 finite numbers"),  # a NaN gripper was read as open
        (np.r_[good[:3], np.inf, good[4:]], r"action must be 10 finite numbers"),
        (good[:7], r"action must be 10 finite numbers"),
        ("open", r"action must be 10 finite numbers"),
        (
            np.r_[good[:3], np.zeros(6), -1.0],
            r"6-D rotation \[0.0, 0.0, 0.0, 0.0, 0.0, 0.0\] has a zero column or two parallel ones",
        ),
        (np.r_[good[:3], 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, -1.0], r"two parallel ones"),
    ]:
        with pytest.raises(ValueError, match=refused):
            env.step(bad)
    position, _, closing = env.checked_action(np.r_[1e6, -1e6, 0.5, good[3:]])
    np.testing.assert_array_equal(position, [WORKSPACE_M, -WORKSPACE_M, 0.5])
    assert not closing and env.action_space.contains(np.r_[position, good[3:]])
    obs, *_ = env.step(np.r_[1e6, -1e6, 0.5, good[3:]])
    assert np.isfinite(obs["keypoints"]).all() and np.isfinite(env.sim.sim.data.qpos).all()
