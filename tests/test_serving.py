"""The websocket policy server, with a real client over loopback: the wire format refuses what could not be rebuilt
safely; metadata arrives on connect; every connection has its own policy state; each kind of bad message gets an
error reply and the connection goes on; several clients at once (a bounded load test that reports latency
percentiles against in-process ``act``); graceful shutdown; the CLI; and a closed-loop Push-T episode driven through
the server that equals the in-process one exactly. Real K-CFM checkpoints (the released Push-T one, and a tiny one
trained here for the transported policy's source index); no mocks."""

import hashlib
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import lightning
import numpy as np
import pytest

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.policies.factory import source_index_path
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.source_search import SourceSearch
from kpflow.policies.subgoal import SubgoalPolicy
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
from kpflow.serving import PolicyClient, PolicyServer, PolicyServerError, load_deployment
from kpflow.serving.server import HARD_LIMIT
from kpflow.serving.wire import WireError, pack, unpack
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, PUSHT_BLOCK, PUSHT_GOAL, observation_keypoints, pusht_weights
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import split_config
from kpflow.tasks.pusht.task import PushTTask
from kpflow.tasks.suite.task import SuiteTask
from tests.helpers import bare_kcfm, load_kcfm, run_command, walk_to_block_store

PUSHT = PushTTask.policy_layout  # the transporting policies need the task's layout (Push-T: the agent is the robot)

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ROOT / "release" / "pusht_standard_kcfm_human.ckpt"
H = 8


def observation(seed: int) -> dict:
    return {"keypoints": np.random.default_rng(seed).uniform(100, 400, (25, 2))}


@pytest.fixture(scope="module")
def released():
    return load_deployment(RELEASED, PushTTask(), {"steps": 4})


@pytest.fixture(scope="module")
def uri(released):
    server = PolicyServer(released, port=0, max_message_bytes=64 * 1024)
    with server.running() as address:
        yield address


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny K-CFM trained for 20 steps on synthetic episodes, with its source index beside the checkpoint."""
    root = tmp_path_factory.mktemp("served")
    walk_to_block_store(root / "demos.zarr")
    lightning.seed_everything(0, verbose=False)
    trainer = lightning.Trainer(max_steps=20, accelerator="cpu", logger=False, enable_checkpointing=False, default_root_dir=root,
                                enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)  # fmt: skip
    model, data = (
        KCFM(N_KEYPOINTS, horizon=H),
        ChunkDataModule(root / "demos.zarr", horizon=H, batch_size=64, val_fraction=0.0),
    )
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(root / "kcfm.ckpt")
    index = SourceIndex.from_store(
        EpisodeStore(root / "demos.zarr"), horizon=H, weights=pusht_weights(agent=4.0), reference=PUSHT_BLOCK
    )
    return root / "kcfm.ckpt", index


# ------------------------------------------------------------------------------------------------ wire format


def test_wire_round_trips_arrays_and_scalars():
    message = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([True, False]), "c": np.int64(7),
               "d": [1, "x", None, 2.5], "e": np.zeros((0, 4), np.uint8), "f": np.arange(4, dtype=">f8")}  # fmt: skip
    back = unpack(pack(message))
    for key in ("a", "b", "e", "f"):
        assert back[key].dtype == message[key].dtype and np.array_equal(back[key], message[key])
    assert back["c"] == 7 and isinstance(back["c"], np.int64) and back["d"] == [1, "x", None, 2.5]


@pytest.mark.parametrize(
    "data, match",
    [
        (b"\xc1", "not a msgpack message"),
        (pack({"__ndarray__": True, "data": b"\x00" * 8, "dtype": "|O", "shape": [1]}), "dtype"),
        (pack({"__ndarray__": True, "data": b"\x00" * 7, "dtype": "<f8", "shape": [1]}), "needs 8 bytes"),
        (pack({"__ndarray__": True, "data": b"", "dtype": "<f8", "shape": [-1]}), "non-negative"),
        (pack({"__ndarray__": True, "data": "text", "dtype": "<f8", "shape": [0]}), "bytes"),
        (pack([1]) + b"\x01", "not a msgpack message"),
        ("text", "binary"),
    ],
)
def test_wire_refuses_what_it_cannot_rebuild_safely(data, match):
    with pytest.raises(WireError, match=match):
        unpack(data)


def test_wire_cannot_send_objects():
    with pytest.raises(TypeError, match="dtype object"):
        pack({"x": np.array([object()])})
    with pytest.raises(TypeError, match="Path"):
        pack({"x": Path(".")})


# ------------------------------------------------------------------------------------------------ the server


def test_metadata_arrives_on_connect(uri, released):
    with PolicyClient(uri) as client:
        meta = client.metadata
        assert meta == released.metadata and client.max_message_bytes == 64 * 1024
        assert meta.observation == {"keypoints": [25, 2]} and meta.keypoint_groups == {
            "block": 12,
            "goal": 12,
            "agent": 1,
        }
        assert meta.action_shape == [8, 2] and meta.horizon == 16 and meta.n_obs == 1 and meta.control_hz == 10.0
        assert meta.checkpoint_sha256 == hashlib.sha256(RELEASED.read_bytes()).hexdigest()


def test_served_actions_equal_in_process_ones_per_connection(uri, released):
    local = released.make_policy()
    with PolicyClient(uri) as a, PolicyClient(uri) as b:
        a.reset(3), b.reset(5), local.reset(3)
        first = a.act(observation(0))
        np.testing.assert_array_equal(first, local.act(observation(0)))
        b.act(observation(0))  # another connection's requests leave a's noise alone
        np.testing.assert_array_equal(a.act(observation(1)), local.act(observation(1)))
        a.reset(3)
        np.testing.assert_array_equal(a.act(observation(0)), first)  # reset reseeds the connection's policy
        assert first.shape == (8, 2) and first.dtype == np.float64 and a.server_ms > 0


@pytest.mark.parametrize(
    "message, match",
    [
        ({"obs": {"keypoints": np.zeros((24, 2))}}, r"shape \[25, 2\]"),
        ({"obs": {"keypoints": np.full((25, 2), np.nan)}}, "50 NaN or inf"),
        ({"obs": {"keypoints": np.zeros((25, 2)), "extra": np.zeros(2)}}, r"unknown \['extra'\]"),
        ({"obs": {}}, r"missing \['keypoints'\]"),
        ({"obs": {"keypoints": [[0.0, 0.0]] * 25}}, "numeric array"),
        ({"act": 1}, "exactly one key"),
        ({"obs": {"keypoints": np.zeros((25, 2))}, "reset": {}}, "exactly one key"),
        ({"reset": {"seed": "zero"}}, "integer or None"),
        ([1, 2], "must be a map"),
    ],
)
def test_a_bad_request_gets_an_error_and_the_connection_goes_on(uri, message, match):
    with PolicyClient(uri) as client:
        with pytest.raises(PolicyServerError, match=match):
            client.request(message)
        client.reset(0)
        assert client.act(observation(0)).shape == (8, 2)


def test_reset_refuses_a_seed_that_is_not_an_integer(uri):
    """PolicyClient.reset(1.5) used to send seed 1: a bool, float or string seed is refused on the client, naming it,
    and nothing is sent; numpy integers are integers."""
    with PolicyClient(uri) as client:
        for seed in (1.5, 2.0, True, "1"):
            with pytest.raises(
                ValueError, match=rf"reset's seed must be an integer or None, got {seed!r} \({type(seed).__name__}\)"
            ):
                client.reset(seed)
        client.reset(np.int64(3))
        first = client.act(observation(0))
        client.reset(3)
        np.testing.assert_array_equal(client.act(observation(0)), first)


def test_garbage_text_and_oversized_frames_get_error_replies(uri):
    with PolicyClient(uri) as client:
        for frame, match in ((b"\xc1\xff\x00", "not a msgpack message"), ("hello", "must be binary"),
                             (b"\x00" * (100 * 1024), "takes at most 65536")):  # fmt: skip
            client._ws.send(frame)
            assert match in unpack(client._ws.recv(timeout=10))["error"]
        assert client.act(observation(0)).shape == (8, 2)  # still serving this connection
        with pytest.raises(PolicyServerError, match="at most 65536"):  # the client refuses to send it at all
            client.request({"obs": {"keypoints": np.zeros((5000, 2))}})


def test_a_frame_past_the_hard_limit_closes_that_connection_only(uri):
    with PolicyClient(uri) as big, PolicyClient(uri) as other:
        big._ws.send(b"\x00" * (HARD_LIMIT * 64 * 1024 + 1))
        with pytest.raises(PolicyServerError, match="1009"):
            big._receive()
        assert other.act(observation(0)).shape == (8, 2)
    with PolicyClient(uri) as again:
        assert again.act(observation(0)).shape == (8, 2)


def test_load_several_clients_at_once(uri, released):
    """4 clients x 25 requests at once; every reply equals its in-process twin. Prints latency percentiles against
    in-process ``act`` (the benchmark, benchmarks/serving.py, measures them properly)."""
    n_clients, n_requests = 4, 25
    local = released.make_policy()
    local_ms = []
    expected = {}
    for c in range(n_clients):
        local.reset(c)
        for r in range(n_requests):
            t = time.perf_counter()
            expected[c, r] = local.act(observation(r))
            local_ms.append(1e3 * (time.perf_counter() - t))
    got, latency, failures = {}, [], []

    def drive(c: int) -> None:
        try:
            with PolicyClient(uri) as client:
                client.reset(c)
                for r in range(n_requests):
                    t = time.perf_counter()
                    got[c, r] = client.act(observation(r))
                    latency.append(1e3 * (time.perf_counter() - t))
        except Exception as e:  # reported below: a thread's exception would otherwise vanish
            failures.append(e)

    threads = [threading.Thread(target=drive, args=(c,)) for c in range(n_clients)]
    start = time.perf_counter()
    [t.start() for t in threads]
    [t.join(120) for t in threads]
    wall = time.perf_counter() - start
    assert not failures and len(got) == n_clients * n_requests
    for key, actions in expected.items():
        np.testing.assert_array_equal(got[key], actions)
    q = lambda x: " / ".join(f"{v:.1f}" for v in np.percentile(x, [50, 90, 99]))  # noqa: E731
    print(f"\nin-process act() p50/p90/p99 {q(local_ms)} ms; served, {n_clients} clients at once: {q(latency)} ms; "
          f"{len(latency) / wall:.0f} requests/s")  # fmt: skip


def test_graceful_shutdown_finishes_requests_then_says_going_away(released):
    server = PolicyServer(released, port=0)
    with server.running() as address:
        client = PolicyClient(address)
        done = {}
        slow = threading.Thread(target=lambda: done.update(actions=client.act(observation(0))))
        slow.start()
        time.sleep(0.01)
    slow.join(30)
    assert done["actions"].shape == (8, 2)  # the request in flight was answered before the server went
    with pytest.raises(PolicyServerError, match="1001"):
        client.act(observation(1))
    with pytest.raises(ConnectionError, match="no policy server"):
        PolicyClient(address, timeout=2)
    start = time.monotonic()
    with pytest.raises(ConnectionError, match=r"no policy server at .* after waiting 0.6 s"):
        PolicyClient(address, timeout=2, wait=0.6)  # it kept trying for that long before giving up
    assert time.monotonic() - start >= 0.6


def test_transported_policy_is_served_with_its_source_index(tiny_run):
    checkpoint, index = tiny_run
    with pytest.raises(FileNotFoundError, match="source_index.npz"):
        load_deployment(checkpoint, PushTTask(), {"kind": "transported_kcfm"})
    index.save(source_index_path(checkpoint))
    loaded = SourceIndex.load(source_index_path(checkpoint))
    for a, b in ((loaded.keypoints, index.keypoints), (loaded.chunks, index.chunks), (loaded.weights, index.weights)):
        np.testing.assert_array_equal(a, b)
    assert loaded.reference == index.reference
    deployment = load_deployment(
        checkpoint, PushTTask(), {"kind": "transported_kcfm", "steps": 4, "transport": {"fit_on": "all"}}
    )
    assert deployment.metadata.policy == "transported_kcfm/ilwr"  # a checkpoint without settings: the goal as observed
    local = TransportedKCFMPolicy(load_kcfm(checkpoint), index, steps=4, layout=PUSHT)
    obs = {"keypoints": index.keypoints[10].astype(np.float64) + 3.0}
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        client.reset(1), local.reset(1)
        np.testing.assert_array_equal(client.act(obs), local.act(obs))
    # the evaluated configuration (kpflow/conf/policy/transported_kcfm.yaml): map on the block and the agent, stuck detection
    # and the default search's weights and frame, a stuck block after 2
    fit_on, search = (
        [*range(12), 24],
        SourceSearch({"objects": 1.0, "goals": 1.0, "robot": 4.0}, "objects", stuck_decisions=2),
    )
    SEARCH = {"weights": {"objects": 1.0, "goals": 1.0, "robot": 4.0}, "frame": "objects", "stuck_decisions": 2}
    deployment = load_deployment(
        checkpoint,
        PushTTask(),
        {"kind": "transported_kcfm", "steps": 4, "transport": {"fit_on": ["objects", "robot"], "search": SEARCH}},
    )
    searched, choice = search.reindexed(index, PUSHT), search.choice()
    local = TransportedKCFMPolicy(load_kcfm(checkpoint), searched, steps=4, fit_on=fit_on, **choice, layout=PUSHT)
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        client.reset(2), local.reset(2)
        for _ in range(4):  # the same scene four times: the fourth decision is taken as stuck, on both sides
            np.testing.assert_array_equal(client.act(obs), local.act(obs))
        assert local.source.stuck_count == 1
    # shown its goal within reach and turn (Table 1's transported K-CFM): what SubgoalPolicy around it returns in process
    deployment = load_deployment(checkpoint, PushTTask(), {"kind": "transported_kcfm", "steps": 4, "transport": {"fit_on": ["block", "agent"], "search": SEARCH}, "reach": 60,
                                                 "turn_deg": 30})  # fmt: skip
    assert deployment.metadata.policy == "transported_kcfm/ilwr/reach=60/turn_deg=30"
    limited = SubgoalPolicy(
        TransportedKCFMPolicy(load_kcfm(checkpoint), searched, steps=4, fit_on=fit_on, **choice, layout=PUSHT),
        PUSHT_BLOCK,
        PUSHT_GOAL,
        60,
        30,
    )
    far = {"keypoints": observation_keypoints((300.0, 250.0, 0.3), (150.0, 150.0, 2.5), (240.0, 320.0))}
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        client.reset(2), limited.reset(2), local.reset(2)
        served = client.act(far)
        np.testing.assert_array_equal(served, limited.act(far))
        assert not np.array_equal(served, local.act(far))  # the goal, 180 px off and turned 2.2 rad, was moved
    with pytest.raises(ValueError, match="unknown keypoint group 'hand'"):
        load_deployment(checkpoint, PushTTask(), {"kind": "transported_kcfm", "transport": {"fit_on": ["hand"]}})
    with pytest.raises(ValueError, match="transport.map='spline' names no map of kpflow/conf/map/"):
        load_deployment(checkpoint, PushTTask(), {"kind": "transported_kcfm", "transport": {"map": "spline"}})


def test_kcfm_within_reach_is_served_as_it_acts_in_process():
    """``reach`` serves the K-CFM shown its goal within that distance of the block, as SubgoalPolicy acts in process."""
    deployment = load_deployment(
        RELEASED, PushTTask(), {"steps": 4, "reach": 60, "turn_deg": False}
    )  # no turn limit (the release has 60)
    assert deployment.metadata.policy == "kcfm/reach=60"
    local = SubgoalPolicy(bare_kcfm(RELEASED, steps=4), PUSHT_BLOCK, PUSHT_GOAL, 60)
    plain = bare_kcfm(RELEASED, steps=4)
    obs = {"keypoints": observation_keypoints((420.0, 120.0, 0.3), (256.0, 256.0, np.pi / 4), (100.0, 400.0))}
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        client.reset(3), local.reset(3), plain.reset(3)
        served = client.act(obs)
        np.testing.assert_array_equal(served, local.act(obs))
        assert not np.array_equal(
            served, plain.act(obs)
        )  # the goal, 221 px from the block, was moved: the check has teeth
    with pytest.raises(
        ValueError, match="is a policy for 25 keypoints in 2-D and 2-D actions, but lift shows 11 keypoints in 3-D"
    ):
        load_deployment(RELEASED, SuiteTask("lift"), {"reach": 60})
    with pytest.raises(ValueError, match="reach must be a positive finite number or None"):
        load_deployment(RELEASED, PushTTask(), {"reach": 0})
    with pytest.raises(ValueError, match="turn_deg must be a positive finite number or None"):
        load_deployment(RELEASED, PushTTask(), {"turn_deg": -1})


def test_kcfm_within_reach_and_turn_is_served_as_it_acts_in_process():
    """``turn_deg`` with ``reach`` serves what SubgoalPolicy with both returns in process."""
    deployment = load_deployment(RELEASED, PushTTask(), {"steps": 4, "reach": 60, "turn_deg": 30})
    assert deployment.metadata.policy == "kcfm/reach=60/turn_deg=30"
    local = SubgoalPolicy(bare_kcfm(RELEASED, steps=4), PUSHT_BLOCK, PUSHT_GOAL, 60, 30)
    reach_only = SubgoalPolicy(bare_kcfm(RELEASED, steps=4), PUSHT_BLOCK, PUSHT_GOAL, 60)
    obs = {
        "keypoints": observation_keypoints((300.0, 280.0, np.pi / 4 + 2.0), (256.0, 256.0, np.pi / 4), (100.0, 400.0))
    }
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        client.reset(3), local.reset(3), reach_only.reset(3)
        served = client.act(obs)
        np.testing.assert_array_equal(served, local.act(obs))
        assert not np.array_equal(
            served, reach_only.act(obs)
        )  # the block is turned 2 rad from its goal: the goal was turned


def test_bad_source_index_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "source_index.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="is not a usable source index"):
        SourceIndex.load(bad)


@pytest.mark.slow
def test_closed_loop_pusht_episode_through_the_server_equals_in_process(uri, released):
    config = split_config("in_distribution", 3, seed=0)
    local = run_episode(PushTEnv(), released.make_policy(), config, 120, seed=7, record=True)
    with PolicyClient(uri) as client:
        served = run_episode(PushTEnv(), client, config, 120, seed=7, record=True)
    assert served.steps == local.steps and served.coverage == local.coverage and served.max_coverage > 0
    for key, value in local.episode.items():
        np.testing.assert_array_equal(served.episode[key], value)


@pytest.mark.slow
def test_serve_cli_answers_then_stops_on_sigterm():
    proc = subprocess.Popen([sys.executable, "-m", "kpflow.cli.serve", "task=pusht", f"checkpoint={RELEASED}", "port=0", "steps=2"], cwd=ROOT,
                            stderr=subprocess.STDOUT, stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        line = ""
        deadline = time.time() + 120
        while (
            not ("serving kcfm" in line and " on ws://" in line) and time.time() < deadline
        ):  # kcfm/reach=60/turn_deg=60: the release's settings
            line = proc.stdout.readline()  # Hydra logs to stdout
            assert line or proc.poll() is None, "the server exited before serving"
        address = line.split("on ", 1)[1].split()[0]
        with PolicyClient(address) as client:
            assert client.metadata.checkpoint_sha256 == hashlib.sha256(RELEASED.read_bytes()).hexdigest()
            assert client.act(observation(0)).shape == (8, 2)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
        assert not (ROOT / "serve.log").exists()  # the server logs to the console, not into the working folder
    finally:
        proc.kill()


def test_serve_cli_refuses_a_bad_config():
    done = run_command("kpflow.cli.serve", f"checkpoint={RELEASED}", "transported=maybe")
    assert done.returncode != 0 and "config key transported must be true or false" in done.stderr
