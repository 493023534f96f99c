"""LeRobot datasets whose observation.state is not named k0.x, k0.y, ... (issue 58): the documented ``data.keypoint_map``
(docs/concepts/data.md's worked example, read from the page) picks each keypoint's columns by name, the robot's last,
and a K-CFM trains on it through kpflow-train; a wrong map, a dataset read without one and Diffusion Policy's raw
Push-T zarr are refused naming what was expected, what was found and what to do."""

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import kpflow
from kpflow.data.chunks import DP_REPLAY_IMPORT, ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.lerobot_dataset import KeypointMap, export_lerobot, import_lerobot
from kpflow.tasks.pusht.demos import ensure_pusht_demos
from kpflow.utils.checkpoint import read_checkpoint
from tests.helpers import child_env, run_command

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "concepts" / "data.md"
CORNERS = ("nw", "ne", "se", "sw")
OFFSETS = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], np.float32)  # nw, ne, se, sw
# the state's columns in the page's order: the target's corners and the end effector shuffled among two other values
NAMES = ["target_nw_x", "joint_0", "target_nw_y", "eef_x", "eef_y", "target_ne_x", "target_ne_y", "gripper",
         "target_se_x", "target_se_y", "target_sw_x", "target_sw_y"]  # fmt: skip
EPISODES, STEPS = 10, 20


def documented_data_config() -> str:
    """The data config of the page's worked example (between its keypoint-map markers), as written."""
    block = re.search(
        r"<!-- keypoint-map:start -->\n```yaml\n(.*?)```\n<!-- keypoint-map:end -->", PAGE.read_text(), re.S
    )
    assert block, f"{PAGE} lost its keypoint-map example"
    return block[1]


def documented_map() -> dict:
    return yaml.safe_load(documented_data_config())["keypoint_map"]


def named_state_dataset(root: Path, names: list[str] = NAMES, seed: int = 0) -> np.ndarray:
    """A LeRobot v3 dataset at ``root`` of an end effector walking to a square target, its ``observation.state``
    named ``names`` (none of them kpflow's ``k<i>.<axis>``), written as the other LeRobot tests write theirs
    (:func:`export_lerobot`, the names then set in meta/info.json). Returns the keypoints ``[T, 5, 2]`` in kpflow's
    layout (the corners nw, ne, se, sw, the end effector last) that the documented map must recover."""
    rng = np.random.default_rng(seed)
    keypoints, states, actions = [], [], []
    for _ in range(EPISODES):
        target, eef = rng.uniform(0.3, 0.7, 2).astype(np.float32), rng.uniform(0, 1, 2).astype(np.float32)
        for _ in range(STEPS):
            corners = target + 0.05 * OFFSETS
            values = {"joint_0": rng.uniform(-3, 3), "gripper": rng.uniform(0, 1), "eef_x": eef[0], "eef_y": eef[1]}
            values |= {f"target_{c}_{a}": corners[i, j] for i, c in enumerate(CORNERS) for j, a in enumerate("xy")}
            keypoints.append(np.vstack([corners, eef]))
            states.append([values[n] for n in names])
            eef = eef + 0.2 * (target - eef)
            actions.append(eef)
    with EpisodeStore(root.with_suffix(".zarr"), mode="a") as store:
        for e in range(EPISODES):
            rows = slice(e * STEPS, (e + 1) * STEPS)
            store.add_episode(
                {"state": np.array(states[rows], np.float32), "action": np.array(actions[rows], np.float32)}
            )
        export_lerobot(store, root, fps=10, task="walk to the target")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"]["observation.state"]["names"] = list(names)
    info_path.write_text(json.dumps(info))
    return np.array(keypoints, np.float32)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("keypoint_map") / "my_dataset"
    return root, named_state_dataset(root)


def test_the_documented_map_reads_the_state_as_kpflows_keypoints_robot_last(dataset, tmp_path):
    root, keypoints = dataset
    spec = documented_map()
    assert list(spec["keypoints"]) == [
        "target_nw",
        "target_ne",
        "target_se",
        "target_sw",
    ]  # the keypoints' order is the map's
    store = import_lerobot(root, tmp_path / "mapped.zarr", keypoint_map=spec)
    assert store.fields == ("action", "keypoints") and store.n_episodes == EPISODES
    np.testing.assert_array_equal(store.field("keypoints"), keypoints)  # every value where kpflow expects it, eef last
    kmap = KeypointMap.from_config(spec)
    assert (
        kmap.names == ("target_nw", "target_ne", "target_se", "target_sw", "robot")
        and kmap.dim == 2
        and kmap.robot == 1
    )
    unnamed = {
        "keypoints": [list(c) for c in kmap.columns[:-1]],
        "robot": [list(kmap.columns[-1])],
    }  # the list spelling
    np.testing.assert_array_equal(
        import_lerobot(root, tmp_path / "listed.zarr", keypoint_map=unnamed).field("keypoints"), keypoints
    )
    state = EpisodeStore(root.with_suffix(".zarr")).field("state")
    np.testing.assert_array_equal(kmap.apply(state, NAMES), keypoints)  # on the robot: a state vector -> keypoints


def test_a_3d_map(tmp_path):
    rng = np.random.default_rng(1)
    names = ["cup.z", "cup.x", "tcp.x", "cup.y", "tcp.y", "tcp.z", "elbow"]
    with EpisodeStore(tmp_path / "s.zarr", mode="a") as s:
        s.add_episode({"state": rng.random((6, 7), dtype=np.float32), "action": rng.random((6, 4), dtype=np.float32)})
        root = export_lerobot(s, tmp_path / "lr")
    info = json.loads((root / "meta" / "info.json").read_text())
    info["features"]["observation.state"]["names"] = {"motors": names}  # LeRobot's dict spelling
    (root / "meta" / "info.json").write_text(json.dumps(info))
    store = import_lerobot(
        root,
        tmp_path / "b.zarr",
        keypoint_map={"keypoints": {"cup": ["cup.x", "cup.y", "cup.z"]}, "robot": ["tcp.x", "tcp.y", "tcp.z"]},
    )
    state = EpisodeStore(tmp_path / "s.zarr").field("state")
    np.testing.assert_array_equal(store.field("keypoints"), state[:, [[1, 3, 0], [2, 4, 5]]])


def test_a_kcfm_trains_through_the_documented_map_with_kpflow_train(dataset, tmp_path):
    """The page's data config in a --config-dir, kpflow-train experiment=kcfm data=mine: the checkpoint's layout is
    the map's (5 keypoints in 2-D, 2-D actions) and its keypoint normalisation is the mapped keypoints', end effector
    last; the released policy acts on keypoints the map makes of a state vector."""
    root, keypoints = dataset
    (tmp_path / "my_dataset").symlink_to(root)  # the config's path: my_dataset
    (tmp_path / "conf" / "data").mkdir(parents=True)
    (tmp_path / "conf" / "data" / "mine.yaml").write_text(documented_data_config())
    cmd = [sys.executable, "-m", "kpflow.cli.train", "--config-dir", "conf", "experiment=kcfm", "data=mine", "logger=none",
           "trainer.max_epochs=1", "trainer.enable_progress_bar=false", "data.batch_size=32", "model.network.down_dims=[8,16]",
           "hydra.run.dir=run"]  # fmt: skip
    done = subprocess.run(
        cmd, cwd=tmp_path, env=child_env(OMP_NUM_THREADS="1"), capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    checkpoint = read_checkpoint(tmp_path / "run" / "checkpoints" / "last.ckpt")
    hp = checkpoint["hyper_parameters"]
    assert (hp["n_keypoints"], hp["keypoint_dim"], hp["action_dim"]) == (5, 2, 2)
    data = ChunkDataModule(root, keypoint_map=documented_map())  # training's split (seed 0)
    data.setup()
    rows = np.concatenate([np.arange(e * STEPS, (e + 1) * STEPS) for e in data.train_episodes])
    np.testing.assert_allclose(
        checkpoint["state_dict"]["processor.kp_mean"].numpy().reshape(5, 2), keypoints[rows].mean(0), atol=1e-5
    )
    assert "keypoint_map" in (tmp_path / "run" / "config.yaml").read_text()  # the run records the map
    policy = kpflow.load_policy(tmp_path / "run" / "checkpoints" / "last.ckpt")
    policy.reset(0)
    state = EpisodeStore(root.with_suffix(".zarr")).field("state")[:2]
    actions = policy.act({"keypoints_history": KeypointMap.from_config(documented_map()).apply(state, NAMES)})
    assert actions.shape == (8, 2) and np.isfinite(actions).all()


def test_a_column_the_state_lacks_is_named_with_the_columns_found(dataset):
    root, _ = dataset
    spec = {"keypoints": {"target": ["target_nw_x", "target_nw_z"]}, "robot": ["eef_x", "eef_y"]}
    with pytest.raises(ValueError, match=r"observation.state has no columns \['target_nw_z'\] that keypoint_map names; its columns are "
                       r"\['target_nw_x', 'joint_0', 'target_nw_y', 'eef_x'.*'target_sw_y'\]: correct data.keypoint_map \(docs/"):  # fmt: skip
        ChunkDataModule(root, horizon=4, keypoint_map=spec).setup()


@pytest.mark.parametrize(
    "spec, message",
    [
        (
            {"keypoint": {"a": ["x", "y"]}},
            r"takes the keys keypoints and robot, e.g. data.keypoint_map='\{keypoints:.*it has the keys \['keypoint'\]",
        ),
        (
            {"keypoints": ["target_nw_x", "target_nw_y"]},
            r"keypoints lists column names \['target_nw_x', 'target_nw_y'\]: give each keypoint its own list",
        ),
        (
            {"keypoints": {"a": ["target_nw_x", "target_nw_y"]}, "robot": ["eef_x", "eef_y", "gripper"]},
            r"the same number of columns, 2 \(x, y\) or 3 \(x, y, z\); it gives a: \['target_nw_x', 'target_nw_y'\], robot: \['eef_x'",
        ),
        (
            {"keypoints": {"a": ["target_nw_x", "eef_x"]}, "robot": ["eef_x", "eef_y"]},
            r"names the columns \['eef_x'\] more than once",
        ),
        ({"keypoints": {"a": "target_nw_x"}}, r"keypoint_map.keypoints: a must be a list of its 2 or 3 column names"),
    ],
)
def test_a_malformed_map_is_refused_saying_what_a_map_holds(spec, message):
    with pytest.raises(ValueError, match=message):
        KeypointMap.from_config(spec)


def test_without_a_map_other_names_are_refused_naming_expected_found_and_the_override(dataset):
    root, _ = dataset
    with pytest.raises(ValueError, match=r"gave no field 'keypoints' \(it gave \['action', 'state'\]\)\. kpflow reads keypoints from feature "
                       r"observation.state named k0.x, k0.y\[, k0.z\].*named \['target_nw_x', 'joint_0'.*\.\.\.\. Say which of its "
                       r"columns are keypoints and which the robot's with data.keypoint_map, e.g. data.keypoint_map="):  # fmt: skip
        ChunkDataModule(root, horizon=4).setup()


def test_a_map_for_an_episode_store_is_refused_and_a_store_without_keypoints_named(dataset):
    root, _ = dataset
    with pytest.raises(
        ValueError,
        match=r"my_dataset.zarr has no field 'keypoints' \(it has \['action', 'state'\]\): .* data.obs_key=FIELD",
    ):
        ChunkDataModule(root.with_suffix(".zarr")).setup()
    with pytest.raises(
        ValueError,
        match=r"maps a LeRobot dataset's observation.state, but .*my_dataset.zarr is not one .*leave keypoint_map out",
    ):
        ChunkDataModule(root.with_suffix(".zarr"), keypoint_map={"keypoints": [["eef_x", "eef_y"]]}).setup()


def raw_pusht_replay(path: Path) -> Path:
    """Diffusion Policy's raw Push-T replay layout (data/state [N, 5], data/action, data/keypoint [N, 9, 2],
    meta/episode_ends), small."""
    with EpisodeStore(path, mode="a") as store:
        for _ in range(2):
            store.add_episode(
                {
                    "state": np.zeros((5, 5), np.float32),
                    "action": np.zeros((5, 2), np.float32),
                    "keypoint": np.zeros((5, 9, 2), np.float32),
                }
            )
    return path


def test_diffusion_policys_raw_zarr_is_refused_naming_its_importer(tmp_path):
    assert importlib.util.find_spec(DP_REPLAY_IMPORT.split()[-1]) is not None  # the command named exists
    raw = raw_pusht_replay(tmp_path / "pusht_cchi_v7_replay.zarr")
    expected = (rf"{re.escape(str(raw))} is Diffusion Policy's raw Push-T replay buffer \(data/state, data/action, data/keypoint, "
                rf"meta/episode_ends; .*\), not a kpflow store: it has no field 'keypoints'\. Import it once into a store with kpflow's 25 "
                rf"keypoints: python -m kpflow.tasks.pusht.replay_import {re.escape(str(raw))} \(into kpflow's data folder, kpflow/utils/data_dir.py\), then train on that: data=pusht_human")  # fmt: skip
    with pytest.raises(ValueError, match=expected):
        ChunkDataModule(raw).setup()
    with pytest.raises(ValueError, match=expected):  # data=pusht_human's reader: refused before it reads a store
        ensure_pusht_demos(raw, None)
    shared = ROOT.parent / "shared" / "data" / "pusht_cchi_v7_replay.zarr"  # the real one, where this checkout has it
    if shared.is_dir():
        with pytest.raises(ValueError, match="is Diffusion Policy's raw Push-T replay buffer"):
            ChunkDataModule(shared).setup()
    done = run_command(
        "kpflow.cli.train", "experiment=kcfm", f"data.path={raw}", "logger=none", f"hydra.run.dir={tmp_path / 'run'}"
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and re.fullmatch(f"error: {expected}.*", lines[0]) and len(lines) == 2, done.stderr[
        -3000:
    ]
