"""Import of the standard Push-T replay buffer into an episode store, and replay of it by kpflow's physics.

Most tests use a small buffer in the standard layout written here by stepping :class:`PushTPhysics`, so that its
states are physically consistent; the last ones use the real dataset when it is present.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
import zarr

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.geometry import AGENT_RADIUS, observation_keypoints, t_polygon
from kpflow.tasks.pusht.physics import PushTPhysics
from kpflow.tasks.pusht.replay_import import (
    FIELDS,
    agent_velocities,
    import_pusht_replay,
    main,
    read_pusht_replay,
    replay_errors,
)
from kpflow.tasks.pusht.scene import FIXED_GOAL
from kpflow.tasks.pusht.workspace import WORKSPACES

ROOT = Path(__file__).resolve().parents[1]
PUSHT = Path(__file__).resolve().parents[2] / "shared/data/pusht_cchi_v7_replay.zarr"
LENGTHS = (30, 36, 42)


def make_episodes(seed: int = 0, lengths=LENGTHS):
    """Episodes recorded from PushTPhysics: the agent starts clear of the block, walks up to it and pushes it.

    Returns float32 ``states`` [T, 5] and ``actions`` [T, 2] per episode (as the standard buffer stores them) and
    the block's velocity [T, 3] at every recorded step (0 exactly where it is not being pushed).
    """
    rng = np.random.default_rng(seed)
    states, actions, block_vels = [], [], []
    for T in lengths:
        physics = PushTPhysics(WORKSPACES["standard"])  # fresh per episode: no pymunk state from the last one
        while True:
            block = np.array([*rng.uniform(200, 310, 2), rng.uniform(0, 2 * np.pi)]).astype(np.float32)
            agent = (block[:2] + rng.uniform(-180, 180, 2)).astype(np.float32)
            if shapely.distance(t_polygon(block), shapely.Point(agent)) > AGENT_RADIUS + 60:
                break
        physics.set_state(agent, block)
        push_to = block[:2] + 0.3 * (block[:2] - agent)
        s, a, v = [], [], []
        for t in range(T):
            w = min(1.0, (t + 1) / (0.75 * T))
            target = ((1 - w) * agent + w * push_to + rng.normal(0, 3, 2)).astype(np.float32)
            s.append(np.r_[physics.agent_pos, physics.block_pose])
            v.append(np.r_[physics.block.velocity, physics.block.angular_velocity])
            a.append(target)
            physics.step(target)
        states.append(np.array(s, np.float32))
        actions.append(np.array(a, np.float32))
        block_vels.append(np.array(v))
    return states, actions, block_vels


def write_standard(path: Path, states, actions, drop=(), replace=None) -> Path:
    """A zarr v2 buffer in the standard Push-T layout; ``drop`` leaves arrays out, ``replace`` swaps some in."""
    state, action = np.concatenate(states), np.concatenate(actions)
    n = len(state)
    arrays = {
        "data/state": state,
        "data/action": action,
        "data/keypoint": np.zeros((n, 9, 2), np.float32),
        "data/img": np.zeros((n, 2, 2, 3), np.float32),
        "data/n_contacts": np.zeros((n, 1), np.float32),
        "meta/episode_ends": np.cumsum([len(s) for s in states]).astype(np.int64),
    }
    arrays.update(replace or {})
    root = zarr.open_group(store=zarr.DirectoryStore(str(path)), mode="w")
    for name, value in arrays.items():
        if name not in drop:
            root.create_dataset(name, data=value)
    return path


@pytest.fixture(scope="module")
def recorded():
    return make_episodes()


@pytest.fixture(scope="module")
def source(recorded, tmp_path_factory):
    states, actions, _ = recorded
    return write_standard(tmp_path_factory.mktemp("pusht") / "replay.zarr", states, actions)


# ----------------------------------------------------------------------------------------------- import


def test_import_round_trip(source, recorded, tmp_path):
    states, actions, _ = recorded
    store = import_pusht_replay(source, tmp_path / "store", progress=False)
    assert isinstance(store, EpisodeStore)
    assert store.n_episodes == len(LENGTHS) and store.n_steps == sum(LENGTHS)
    assert list(np.diff(np.r_[0, store.episode_ends])) == list(LENGTHS)
    assert set(store.fields) == set(FIELDS)
    assert store.attrs["task"] == "pusht" and store.attrs["goal"] == "fixed" and store.attrs["workspace"] == "standard"
    assert store.attrs["source"] == str(Path(source).resolve())
    for i, episode in enumerate(store):
        T = LENGTHS[i]
        assert store.episode_attrs(i) == {"source_episode": i}
        assert all(episode[f].dtype == np.float32 for f in FIELDS)
        assert episode["keypoints"].shape == (T, 25, 2)
        expected = np.stack([observation_keypoints(s[2:5], FIXED_GOAL, s[0:2]) for s in states[i].astype(np.float64)])
        np.testing.assert_allclose(episode["keypoints"], expected, atol=1e-4)
        np.testing.assert_array_equal(episode["action"], actions[i])
        np.testing.assert_array_equal(episode["state"], states[i])
        np.testing.assert_array_equal(episode["agent_pos"], states[i][:, :2])
        np.testing.assert_array_equal(episode["block_pose"], states[i][:, 2:5])
        np.testing.assert_array_equal(episode["goal_pose"], np.tile(np.float32(FIXED_GOAL), (T, 1)))


def test_import_max_episodes_and_cli(source, tmp_path, capsys):
    assert import_pusht_replay(source, tmp_path / "two", max_episodes=2, progress=False).n_episodes == 2
    assert main([str(source), str(tmp_path / "cli"), "--max-episodes", "1", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "imported 1 episodes" in out and str(tmp_path / "cli") in out
    assert EpisodeStore(tmp_path / "cli").n_episodes == 1
    with pytest.raises(SystemExit) as refused:  # refuses to overwrite, in one line (kpflow.utils.errors.command)
        main([str(source), str(tmp_path / "cli"), "--no-progress"])
    assert refused.value.code == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "already holds 1 episodes" in err and len(err.splitlines()) == 2


def test_data_node_max_episodes(source, recorded, tmp_path):
    """``data=pusht_human data.max_episodes=N`` (Diffusion Policy's ``max_train_episodes``): training chunks and the
    transport index read only the store's first N episodes."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from kpflow.policies.factory import layout_of
    from kpflow.policies.source_search import SourceSearch
    from kpflow.tasks.pusht.task import PushTTask

    dest = import_pusht_replay(source, tmp_path / "human.zarr", progress=False).path
    node = OmegaConf.load(ROOT / "kpflow/conf/data/pusht_human.yaml")
    assert node.max_episodes is None  # all episodes unless asked
    node.path, node.workers, node.horizon = str(dest), 0, 4
    full, first2 = instantiate(node), instantiate(node, max_episodes=2, val_fraction=0.5)
    first2.setup()
    assert (first2.train_episodes, first2.val_episodes) in (([0], [1]), ([1], [0]))
    layout = layout_of(PushTTask())
    lengths = [len(s) for s in recorded[0]]
    assert len(SourceSearch().index(full, layout, 4)) == sum(lengths)
    assert len(SourceSearch().index(first2, layout, 4)) == sum(lengths[:2])


def test_refuses_to_overwrite(source, tmp_path):
    dest = tmp_path / "store"
    import_pusht_replay(source, dest, max_episodes=1, progress=False)
    with pytest.raises(FileExistsError, match="already holds 1 episodes"):
        import_pusht_replay(source, dest, progress=False)
    assert EpisodeStore(dest).n_episodes == 1  # untouched
    assert import_pusht_replay(source, dest, progress=False, overwrite=True).n_episodes == len(LENGTHS)
    assert EpisodeStore(dest).n_episodes == len(LENGTHS)
    assert [p.name for p in tmp_path.iterdir()] == ["store"]  # no temporary folder left behind

    other = tmp_path / "not_a_store"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not an episode store"):
        import_pusht_replay(source, other, progress=False, overwrite=True)
    assert (other / "notes.txt").read_text() == "keep me"
    with pytest.raises(ValueError, match="is the source"):
        import_pusht_replay(source, source, progress=False, overwrite=True)


def test_empty_dest_folder_is_used(source, tmp_path):
    (tmp_path / "empty").mkdir()
    assert import_pusht_replay(source, tmp_path / "empty", max_episodes=1, progress=False).n_episodes == 1


@pytest.mark.parametrize(
    "drop, replace, match",
    [
        (("data/state",), None, r"missing array data/state"),
        (("data/action",), None, r"missing array data/action"),
        (("meta/episode_ends",), None, r"missing array meta/episode_ends"),
        ((), {"data/state": np.zeros((108, 4), np.float32)}, r"data/state has shape \[108, 4\]; expected \[N, 5\]"),
        ((), {"data/action": np.zeros((108, 3), np.float32)}, r"data/action has shape \[108, 3\]; expected \[N, 2\]"),
        ((), {"meta/episode_ends": np.array([30, 20, 108])}, r"episode_ends is not strictly increasing"),
        ((), {"meta/episode_ends": np.array([30, 66, 200])}, r"exceeds the 108 rows"),
    ],
)
def test_validation(recorded, tmp_path, drop, replace, match):
    states, actions, _ = recorded
    bad = write_standard(tmp_path / "bad.zarr", states, actions, drop=drop, replace=replace)
    with pytest.raises(ValueError, match=match) as info:
        import_pusht_replay(bad, tmp_path / "store", progress=False)
    assert str(bad) in str(info.value)
    assert not (tmp_path / "store").exists()
    with pytest.raises(ValueError, match=match):
        replay_errors(bad)


def test_validation_nan(recorded, tmp_path):
    states, actions, _ = recorded
    state = np.concatenate(states)
    state[40, 3] = np.nan  # episode 1 (rows 30..65)
    bad = write_standard(tmp_path / "nan.zarr", states, actions, replace={"data/state": state})
    with pytest.raises(ValueError, match=r"data/state contains NaN or inf .*first row 40, episode 1"):
        import_pusht_replay(bad, tmp_path / "store", progress=False)
    assert read_pusht_replay(bad, max_episodes=1)[0].shape == (30, 5)  # only the rows read are checked


@pytest.mark.parametrize(
    "damage, match",
    [
        ("chunk bytes", r"field 'data/state' could not be read: a chunk is damaged"),
        ("zarray json", r"field 'data/action' has damaged metadata \(data/action/.zarray: JSONDecodeError"),
        ("missing chunk", r"field 'data/state' is missing chunk\(s\) of its first 108 rows"),
    ],
)
def test_damaged_buffer_names_the_field(recorded, tmp_path, damage, match):
    states, actions, _ = recorded
    bad = write_standard(tmp_path / "bad.zarr", states, actions)
    chunk = next((bad / "data" / "state").glob("0.*"))
    if damage == "chunk bytes":
        chunk.write_bytes(b"\x02\x01random bytes, not blosc" * 8)
    elif damage == "zarray json":
        (bad / "data" / "action" / ".zarray").write_text("{broken")
    else:
        chunk.unlink()
    with pytest.raises(ValueError, match=match) as info:
        import_pusht_replay(bad, tmp_path / "store", progress=False)
    assert str(bad) in str(info.value) and not (tmp_path / "store").exists()


def test_missing_source(tmp_path):
    with pytest.raises(FileNotFoundError, match="no Push-T replay buffer"):
        import_pusht_replay(tmp_path / "nothing.zarr", tmp_path / "store", progress=False)
    (tmp_path / "plain").mkdir()
    with pytest.raises(ValueError, match="not a zarr group"):
        read_pusht_replay(tmp_path / "plain")


# ----------------------------------------------------------------------------------------------- replay


def test_agent_velocities_match_physics(recorded):
    states, actions, _ = recorded
    physics = PushTPhysics(WORKSPACES["standard"])
    physics.set_state(states[0][0, :2], states[0][0, 2:5])
    pos, vel = agent_velocities(states[0][0, :2], actions[0])
    for t, a in enumerate(actions[0][:10]):
        np.testing.assert_array_equal(pos[t], physics.agent_pos)
        np.testing.assert_array_equal(vel[t], physics.agent_vel)
        physics.step(a)


def test_replay_of_self_recorded_data_is_exact(source, recorded):
    """Where the recorded state is the whole simulator state (block at rest), replay is exact up to float32."""
    _, _, block_vels = recorded
    r = replay_errors(source, horizons=(10, 1), per_step=True)
    assert r["n_episodes"] == len(LENGTHS) and r["n_steps"] == sum(LENGTHS)
    assert r["agent"]["count"] == sum(LENGTHS) and r["agent"]["max"] < 1e-4
    assert sorted(r["horizons"]) == [1, 10]
    for h, entry in r["horizons"].items():
        assert entry["count"] == sum(max(T - h, 0) for T in LENGTHS)
        assert entry["position_px"]["median"] < 1e-3 and entry["angle_deg"]["median"] < 1e-3
        at_rest = np.array([not block_vels[e][t].any() for e, t in zip(entry["episode"], entry["start"])])
        assert 0.4 < at_rest.mean() < 1.0  # both kinds of start occur
        assert entry["position_px_all"][at_rest].max() < 1e-3
        assert entry["angle_deg_all"][at_rest].max() < 1e-3
        # while the block is pushed, the velocity it carries between control steps is not in the state
        assert entry["position_px_all"].max() < 2.0 and entry["angle_deg_all"].max() < 2.0


def test_replay_errors_arguments(source):
    with pytest.raises(ValueError, match="horizons"):
        replay_errors(source, horizons=(0, 1))
    r = replay_errors(source, horizons=(3,), max_episodes=1, physically_correct=True)
    assert r["physically_correct"] and r["n_episodes"] == 1 and r["horizons"][3]["count"] == LENGTHS[0] - 3
    assert "position_px_all" not in r["horizons"][3]


def test_benchmark_script(source, tmp_path):
    out = tmp_path / "replay.md"
    cmd = [sys.executable, "benchmarks/pusht_replay.py", "--data", str(source), "--out", str(out)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    assert "| standard quirks |" in text and "| physically correct |" in text and f"| {sum(LENGTHS)} |" in text
    cmd = [sys.executable, "benchmarks/pusht_replay.py", "--data", str(tmp_path / "absent.zarr"), "--out", str(out)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "not found" in done.stderr and "skipping" in done.stderr


# ----------------------------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def real():
    if not PUSHT.exists():
        pytest.skip(f"standard Push-T dataset not found at {PUSHT}")
    return PUSHT


def test_real_dataset_import(real, tmp_path):
    store = import_pusht_replay(real, tmp_path / "pusht", max_episodes=3, progress=False)
    root = zarr.open_group(store=zarr.DirectoryStore(str(real)), mode="r")
    ends = root["meta/episode_ends"][:3]
    assert store.n_episodes == 3 and list(store.episode_ends) == list(ends)
    state = root["data/state"][0].astype(np.float64)
    np.testing.assert_allclose(
        store.episode(0)["keypoints"][0], observation_keypoints(state[2:5], FIXED_GOAL, state[:2]), atol=1e-4
    )
    np.testing.assert_array_equal(store.episode(2)["action"], root["data/action"][ends[1] : ends[2]])


def test_real_dataset_replay(real):
    r = replay_errors(real, horizons=(1, 10), max_episodes=5)
    assert r["agent"]["max"] < 1e-3
    for h in (1, 10):
        assert r["horizons"][h]["position_px"]["median"] < 0.1
        assert r["horizons"][h]["angle_deg"]["median"] < 0.1
