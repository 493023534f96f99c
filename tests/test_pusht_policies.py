"""Nearest-neighbour and policy-transportation policies on Push-T: source search, transport, replays."""

import numpy as np
import pytest

from kpflow.core.policy import Policy
from kpflow.data.chunks import ChunkDataset
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.maps import AffineMap
from kpflow.policies.chunk_transport import TransportPolicy
from kpflow.policies.nearest import NearestNeighbourPolicy
from kpflow.tasks.pusht import PushTEnv, split_config
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.geometry import PUSHT_BLOCK, pusht_weights
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.task import PushTTask

PUSHT = PushTTask.policy_layout  # the transporting policies need the task's layout (Push-T: the agent is the robot)


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "demos.zarr"
    collect_pusht(path, 3, workers=1, progress=False)
    return EpisodeStore(path)


def test_query_is_the_weighted_argmin():
    rng = np.random.default_rng(0)
    keypoints = rng.uniform(0, 512, (500, 25, 2))
    chunks = rng.uniform(0, 512, (500, 20, 2))
    w = pusht_weights(block=2.0, goal=0.5, agent=3.0)
    index = SourceIndex(keypoints, chunks, w)
    for _ in range(20):
        q = rng.uniform(0, 512, (25, 2))
        brute = (w[:, None] * (keypoints - q) ** 2).sum((1, 2))
        i, d = index.query(q)
        assert i == int(np.argmin(brute)) and np.isclose(d, brute.min(), rtol=1e-3)
    assert index.query(keypoints[7])[0] == 7


def test_block_frame_search_ignores_rigid_motions_of_the_whole_scene(demos):
    index = SourceIndex.from_store(demos, horizon=20, weights=pusht_weights(agent=4.0), reference=PUSHT_BLOCK)
    c, s = np.cos(1.1), np.sin(1.1)
    rot, shift = np.array([[c, -s], [s, c]]), np.array([300.0, -80.0])
    for k in (3, 90, 250):
        moved = index.keypoints[k] @ rot.T + shift
        i, d = index.query(moved)
        assert i == k and d < 5.0  # float32 norms: |f|^2 ~ 1e7, so the distance carries ~1 px^2 of rounding
    with pytest.raises(ValueError, match="reference"):
        SourceIndex(index.keypoints, index.chunks, reference=(0,))


def test_index_validates_its_input():
    kp, ch = np.zeros((3, 25, 2)), np.zeros((3, 20, 2))
    kp[:, :, 0] = np.arange(3)[:, None]
    with pytest.raises(ValueError, match="shape"):
        SourceIndex(kp, ch).query(np.zeros((24, 2)))
    with pytest.raises(ValueError, match="NaN"):
        SourceIndex(kp, ch).query(np.full((25, 2), np.nan))
    with pytest.raises(ValueError, match="one entry per keypoint"):
        SourceIndex(kp, ch, np.ones(3))
    with pytest.raises(ValueError, match="agent"):
        pusht_weights(agent=-1.0)
    with pytest.raises(ValueError, match="at least one"):
        SourceIndex(kp[:0], ch[:0])


def test_index_from_store_matches_the_chunk_dataset(demos):
    index = SourceIndex.from_store(demos, horizon=20)
    data = ChunkDataset(demos, range(len(demos)), 20)
    assert len(index) == len(data) == demos.n_steps
    for k in (0, 57, len(data) - 1):
        item = data[k]
        np.testing.assert_array_equal(index.keypoints[k], item["obs"].numpy())
        np.testing.assert_array_equal(index.chunks[k], item["actions"].numpy())


def test_transport_with_an_identity_or_rigid_scene_change(demos):
    index = SourceIndex.from_store(demos, horizon=20)
    policy = TransportPolicy(index, execute=20, layout=PUSHT)
    assert isinstance(policy, Policy)
    obs = {"keypoints": index.keypoints[40].astype(np.float64)}
    np.testing.assert_allclose(policy.act(obs), index.chunks[40], atol=1e-3)  # identity map
    c, s = np.cos(0.4), np.sin(0.4)
    rot, shift = np.array([[c, -s], [s, c]]), np.array([30.0, -20.0])
    moved = {"keypoints": index.keypoints[40] @ rot.T + shift}
    one = SourceIndex(index.keypoints[40:41], index.chunks[40:41])  # the only source: the moved scene's original
    for make_map in (AffineMap, None):  # rigid fit, and ILWR (rigid alignment, then nothing left to deform)
        policy = TransportPolicy(one, **({"make_map": make_map} if make_map else {}), execute=20, layout=PUSHT)
        np.testing.assert_allclose(policy.act(moved), index.chunks[40] @ rot.T + shift, atol=1e-3)


def test_relative_nearest_neighbour_replays_the_motion_from_the_observed_agent(demos):
    index = SourceIndex.from_store(demos, horizon=20, reference=PUSHT_BLOCK)
    source, chunk = index.keypoints[40].astype(np.float64), index.chunks[40].astype(np.float64)
    plain = NearestNeighbourPolicy(SourceIndex(source[None], chunk[None]), execute=20, relative=True)
    np.testing.assert_allclose(plain.act({"keypoints": source}), chunk, atol=1e-4)  # its own scene: the chunk itself
    shifted = source.copy()
    shifted[-1] += (7.0, -3.0)  # only the agent moved: the same motion, started from there
    np.testing.assert_allclose(plain.act({"keypoints": shifted}), chunk + (7.0, -3.0), atol=1e-4)
    c, s = np.cos(0.4), np.sin(0.4)
    rot, shift = np.array([[c, -s], [s, c]]), np.array([30.0, -20.0])
    moved = {"keypoints": source @ rot.T + shift}  # the whole scene moved: the motion turns with the block
    framed = NearestNeighbourPolicy(SourceIndex(source[None], chunk[None], reference=PUSHT_BLOCK), 20, relative=True)
    np.testing.assert_allclose(framed.act(moved), chunk @ rot.T + shift, atol=1e-3)
    np.testing.assert_allclose(plain.act(moved), chunk - source[-1] + moved["keypoints"][-1], atol=1e-3)  # world frame


@pytest.mark.parametrize("make", [NearestNeighbourPolicy, TransportPolicy])
def test_policies_replay_a_demonstration_from_its_own_start(demos, make):
    """From a demonstrated configuration every query finds the demonstration itself, so the episode succeeds."""
    index = SourceIndex.from_store(demos, horizon=20)
    policy = make(index, execute=20, **({"layout": PUSHT} if make is TransportPolicy else {}))
    config = split_config("in_distribution", demos.episode_attrs(1)["config_index"])
    result = run_episode(PushTEnv(), policy, config, 600)
    assert result.success
    chunk = policy.act({"keypoints": index.keypoints[0].astype(np.float64)})
    assert chunk.shape == (20, 2)
    with pytest.raises(ValueError, match="execute"):
        make(index, execute=21)


def test_demonstration_stores_are_reused_only_when_they_match(tmp_path, demos):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from kpflow.tasks.pusht.demos import ensure_pusht_demos

    path = str(demos.path)
    n = len(demos)
    assert len(ensure_pusht_demos(path, n)) == n
    with pytest.raises(ValueError, match=f"holds {n} episodes"):
        ensure_pusht_demos(path, n + 1)
    with pytest.raises(ValueError, match="seed"):
        ensure_pusht_demos(path, n, seed=5)
    assert len(ensure_pusht_demos(path, None)) == n  # any existing store, taken as it is
    with pytest.raises(FileNotFoundError, match="n_episodes=null"):
        ensure_pusht_demos(tmp_path / "missing.zarr", None)
    # data=pusht_human and data=pusht_store read whatever store is at data.path (here the expert demos)
    for data in ("pusht_human", "pusht_store"):
        with initialize_config_dir(str(Path(__file__).resolve().parents[1] / "kpflow" / "conf"), version_base="1.3"):
            cfg = compose("evaluate", overrides=[f"data={data}", f"data.path={path}", "policy=nearest", "logger=none"])
        policy = instantiate(cfg.policy)
        assert len(policy.index) == demos.n_steps


def test_standard_protocol_is_diffusion_policys(tmp_path):
    """split=standard: DP's start states on seeds 100000, 100001, ..., 300 steps with the goal fixed at
    (256, 256, pi/4), whatever n_configs and max_steps say; score = mean of min(max coverage / 0.95, 1)."""
    import shapely

    from kpflow.eval.policy_trial import PolicyTrial
    from kpflow.eval.reports.pusht import PushTReport
    from kpflow.eval.trials import cell_summary, run_trials
    from kpflow.tasks.pusht.geometry import AGENT_RADIUS, coverage, t_polygon
    from kpflow.tasks.pusht.scene import standard_config
    from kpflow.tasks.pusht.task import PushTTask, protocol_counts

    class HoldStill:
        def reset(self, seed=None):
            pass

        def act(self, obs):
            return np.asarray(obs["agent_pos"], float)[None]

    n_trials, first_index = protocol_counts(3, standard_episodes=12)
    trial = PolicyTrial(PushTTask(), HoldStill(), PushTReport(), "still", max_steps=1200)
    results = run_trials(tmp_path, trial, "standard", n_trials, first_index, workers=2, videos=0, progress=False)
    episodes = results["trials"]
    assert [e["index"] for e in episodes] == list(range(100_000, 100_012))  # DP's test seeds
    assert all(e["steps"] == 300 or e["success"] for e in episodes)  # DP's 300 steps, whatever max_steps says
    clear = 0
    for e in episodes:
        config = standard_config(e["index"])
        if shapely.distance(t_polygon(config.block_pose), shapely.Point(config.agent_pos)) > AGENT_RADIUS + 1:
            clear += 1  # nothing pushes the block: its coverage stays the start's
            assert e["max_coverage"] == pytest.approx(coverage(config.block_pose, config.goal_pose), abs=1e-6)
    assert clear >= 8
    score = np.mean([min(e["max_coverage"] / 0.95, 1.0) for e in episodes])
    assert cell_summary(results, "standard")["score"] == pytest.approx(score)


def test_standard_config_is_diffusion_policys_draw():
    """Closed form: DP's PushTEnv.reset draws, with np.random.RandomState(seed), agent x, y in randint(50, 450),
    block x, y in randint(100, 400), then the angle randn() * 2 pi - pi, and keeps the goal (256, 256, pi/4)."""
    from kpflow.tasks.pusht.scene import STANDARD_FIRST_SEED, standard_config

    assert STANDARD_FIRST_SEED == 100_000
    for seed in (0, 1, 100_000, 100_499, 200_000, 2**32 - 1):
        rs = np.random.RandomState(seed)
        want = [
            rs.randint(50, 450),
            rs.randint(50, 450),
            rs.randint(100, 400),
            rs.randint(100, 400),
            rs.randn() * 2 * np.pi - np.pi,
        ]
        c = standard_config(seed)
        assert [*c.agent_pos, *c.block_pose] == want  # bit for bit
        assert c.goal_pose == (256.0, 256.0, np.pi / 4) and c.workspace == "standard"
    draws = np.array([[*standard_config(s).agent_pos, *standard_config(s).block_pose] for s in range(100_000, 100_500)])
    assert (
        draws[:, :2].min() >= 50
        and draws[:, :2].max() <= 449
        and draws[:, 2:4].min() >= 100
        and draws[:, 2:4].max() <= 399
    )
    assert (draws[:, :4] == draws[:, :4].round()).all()  # integer positions, as there
    for bad in (-1, 2**32, 1.5, True):
        with pytest.raises(ValueError, match="seed must be an integer"):
            standard_config(bad)


def test_query_k_is_the_sorted_weighted_distances():
    rng = np.random.default_rng(3)
    keypoints, chunks = rng.uniform(0, 512, (300, 25, 2)), rng.uniform(0, 512, (300, 20, 2))
    w = pusht_weights(agent=4.0)
    index = SourceIndex(keypoints, chunks, w)
    q = rng.uniform(0, 512, (25, 2))
    d = ((keypoints - q) ** 2 * w[:, None]).sum((1, 2))
    idx, dist = index.query_k(q, 5)
    np.testing.assert_array_equal(idx, np.argsort(d)[:5])
    np.testing.assert_allclose(dist, np.sort(d)[:5], rtol=1e-4)
    assert index.query_k(q, 1)[0][0] == index.query(q)[0]
    assert len(SourceIndex(keypoints[:3], chunks[:3]).query_k(q, 5)[0]) == 3  # fewer sources than k
    with pytest.raises(ValueError, match="k must be an integer >= 1"):
        index.query_k(q, 0)


def test_stochastic_source_choice_follows_the_rank_weights_and_is_seeded():
    """candidates=5, temperature=1.2: rank i is drawn with probability exp(-i / 1.2) / Z (the authors' choice)."""
    rng = np.random.default_rng(4)
    keypoints = rng.uniform(0, 512, (50, 25, 2))
    index = SourceIndex(keypoints, rng.uniform(0, 512, (50, 20, 2)))
    q = keypoints[7] + 0.5
    ranked, _ = index.query_k(q, 5)
    policy = TransportPolicy(index, candidates=5, temperature=1.2, layout=PUSHT)
    policy.reset(11)
    draws = [policy.source.choose(q) for _ in range(20_000)]
    freq = np.array([np.mean(np.array(draws) == i) for i in ranked])
    p = np.exp(-np.arange(5) / 1.2)
    np.testing.assert_allclose(freq, p / p.sum(), atol=0.012)  # ~4 standard errors
    policy.reset(11)
    assert [policy.source.choose(q) for _ in range(50)] == draws[:50]  # the same seed, the same draws
    assert TransportPolicy(index, layout=PUSHT).source.choose(q) == ranked[0]  # candidates=1: the nearest
    for bad, match in (
        ({"candidates": 0}, "candidates"),
        ({"temperature": 0.0}, "temperature"),
        ({"max_step": -1.0}, "max_step"),
    ):
        with pytest.raises(ValueError, match=match):
            TransportPolicy(index, **bad, layout=PUSHT)


def test_clipped_steps_by_hand():
    from kpflow.policies.chunk_transport import clip_steps

    targets = np.array([[10.0, 0.0], [10.0, 9.0], [0.0, 9.0]])
    np.testing.assert_allclose(clip_steps(np.zeros(2), targets, 5.0), [[5, 0], [10, 5], [5, 9]])
    np.testing.assert_allclose(clip_steps(np.zeros(2), targets, 100.0), targets)  # a wide limit changes nothing


def test_stuck_detection_draws_elsewhere_only_when_the_object_stops_moving():
    rng = np.random.default_rng(5)
    keypoints = rng.uniform(0, 512, (80, 25, 2))
    index = SourceIndex(keypoints, rng.uniform(0, 512, (80, 20, 2)), reference=PUSHT_BLOCK)
    q = keypoints[3] + 0.1
    policy = TransportPolicy(index, stuck_decisions=3, stuck_distance=2.0, stuck_candidates=40, layout=PUSHT)
    policy.reset(0)
    nearest = index.query(q)[0]
    # the same scene four times: the first three decisions are not yet a window, the fourth is stuck
    choices = [policy.source.choose(q) for _ in range(4)]
    assert choices[:3] == [nearest] * 3 and policy.source.stuck_count == 1
    assert choices[3] in index.query_k(q, 40)[0]
    # the record starts again at the escape: stuck again 3 decisions after it, not before
    assert [policy.source.choose(q) for _ in range(2)] == [nearest] * 2 and policy.source.stuck_count == 1
    escapes = [policy.source.choose(q) for _ in range(3 * 60)][::3]
    assert policy.source.stuck_count == 61 and len(set(escapes)) > 10  # a uniform draw among 40: many different sources
    # the agent moving does not count; the object (block keypoints) moving does
    policy.reset(0)
    for step in range(12):
        moved = q.copy()
        moved[-1] += 30.0 * step  # only the agent
        policy.source.choose(moved)
    assert policy.source.stuck_count == 3
    policy.reset(0)
    for step in range(12):
        policy.source.choose(
            q + np.r_[np.full((12, 2), 3.0 * step), np.zeros((13, 2))]
        )  # the block slides 3 px a decision
    assert policy.source.stuck_count == 0
    for bad, match in (
        ({"stuck_decisions": 0}, "stuck_decisions"),
        ({"stuck_distance": -1.0}, "stuck_distance"),
        ({"stuck_candidates": 0}, "stuck_candidates"),
    ):
        with pytest.raises(ValueError, match=match):
            TransportPolicy(index, **bad, layout=PUSHT)


def test_a_map_fitted_on_block_and_agent_carries_the_chunk_with_the_block(demos):
    """fit_on=[objects, robot] (the block and the agent): the goal does not bend the map. A source whose goal coincides with its block (the end of a
    demonstration read in hindsight) cannot be fitted with the goal at all; without the goal the chunk moves rigidly
    with the block when the agent moves with it, and wherever the goal is."""
    from kpflow.policies.factory import fit_on_indices
    from kpflow.tasks.pusht.demos import PUSHT_HINDSIGHT
    from kpflow.tasks.pusht.task import PushTTask

    layout = PushTTask.policy_layout

    index = SourceIndex.from_store(demos, horizon=20, reference=PUSHT_BLOCK, hindsight=PUSHT_HINDSIGHT)
    end = demos.episode_ends[0] - 1  # the first demonstration's last step: goal keypoints == block keypoints
    source, chunk = index.keypoints[end].astype(np.float64), index.chunks[end].astype(np.float64)
    np.testing.assert_array_equal(source[12:24], source[:12])
    one = SourceIndex(source[None], chunk[None], reference=PUSHT_BLOCK)
    c, s = np.cos(0.3), np.sin(0.3)
    rot, shift = np.array([[c, -s], [s, c]]), np.array([25.0, 40.0])
    target = source @ rot.T + shift
    target[12:24] = source[12:24] + (4.0, -3.0)  # the goal somewhere else: not where the block went
    fitted = TransportPolicy(one, execute=20, fit_on=fit_on_indices(layout, ["objects", "robot"]), layout=layout)
    np.testing.assert_allclose(fitted.act({"keypoints": target}), chunk @ rot.T + shift, atol=1e-6)
    with pytest.raises(ValueError, match="duplicate source keypoints"):
        TransportPolicy(one, execute=20, fit_on=fit_on_indices(layout, "all"), layout=layout).act({"keypoints": target})
    with pytest.raises(ValueError, match=r"needs the task's PolicyLayout \(layout=task.policy_layout\)"):
        TransportPolicy(one)  # which keypoints are the robot's is the task's to say
    assert fit_on_indices(layout, "all") is None and fit_on_indices(layout, ["block", "agent"]) == (*range(12), 24)
    for bad in ([], [0, 0], [25]):
        with pytest.raises(ValueError, match="fit_on"):
            TransportPolicy(one, fit_on=bad, layout=PUSHT)
    with pytest.raises(ValueError, match="unknown keypoint group 'hand'"):
        fit_on_indices(layout, ["hand"])


def test_clipped_transport_starts_from_the_robot_keypoint_of_the_observation():
    """``max_step`` reads where the robot is from the observed keypoints (the layout's robot; Push-T's agent, the
    last), not from a task's own observation key: with an identical source scene the map is the identity and the
    first target moves at most 5 px per axis from the agent keypoint."""
    from kpflow.policies.chunk_transport import TransportPolicy, clip_steps

    rng = np.random.default_rng(0)
    keypoints = rng.uniform(0, 512, (1, 25, 2))
    chunks = keypoints[:, -1:] + np.cumsum(rng.uniform(-20, 20, (1, 20, 2)), axis=1)
    policy = TransportPolicy(SourceIndex(keypoints, chunks), execute=20, max_step=5.0, layout=PUSHT)
    moved = policy.act({"keypoints": keypoints[0].astype(np.float64)})  # no "agent_pos": not needed
    np.testing.assert_allclose(
        moved, clip_steps(keypoints[0, -1].astype(np.float64), chunks[0].astype(np.float64), 5.0), atol=1e-3
    )
    assert np.abs(moved[0] - keypoints[0, -1]).max() <= 5.0 + 1e-3


def test_one_source_search_reaches_every_transporting_policy(demos):
    """``policy.search=`` gives the search options to nearest neighbour and policy transportation over the task's
    defaults (Push-T: a stuck block after 5 decisions; weights layered group by group), and a served (or evaluated)
    transported K-CFM's ``transport.search`` takes the same options, checked as one options object."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from kpflow.policies.source_search import SourceSearch

    conf = str(Path(__file__).resolve().parents[1] / "kpflow" / "conf")
    overrides = ["data=pusht_store", f"data.path={demos.path}", "logger=none",
                 "policy.search={candidates: 5, weights: {robot: 2.0}, frame: world}"]  # fmt: skip
    with initialize_config_dir(conf, version_base="1.3"):
        transport = instantiate(compose("evaluate", overrides=[*overrides, "policy=transport"]).policy)
        nearest = instantiate(compose("evaluate", overrides=[*overrides, "policy=nearest"]).policy)
        served = compose("serve", overrides=["checkpoint=x", "transport.search={candidates: 5}"]).transport.search
    assert transport.source.candidates == 5 and transport.source.stuck_decisions == 5  # Push-T's: a stuck block after 5
    assert transport.index.reference is None and nearest.index.reference is None  # frame=world
    agent = list(PushTTask.policy_layout.indices("robot"))
    assert transport.index.weights[agent].tolist() == nearest.index.weights[agent].tolist() == [2.0]
    block = list(PushTTask.policy_layout.indices("objects"))
    assert set(transport.index.weights[block].tolist()) == {1.0}  # the other groups' weights: the defaults'
    never = compose_evaluate(conf, [*overrides[:3], "policy=transport", "policy.search={stuck_decisions: false}"])
    assert instantiate(never.policy).source.stuck_decisions is None  # false: never, over the task's 5
    assert (
        SourceSearch.of(served).candidates == 5 and SourceSearch.of(served).stuck_decisions is None
    )  # the rest: the checkpoint's
    with pytest.raises(
        ValueError, match="the source search has no option canidates; its options are candidates, frame"
    ):
        SourceSearch.of({"canidates": 3})
    with pytest.raises(ValueError, match="temperature must be a positive number"):
        TransportPolicy(demos_index(demos), layout=PUSHT, **SourceSearch(temperature=0.0).choice())


def compose_evaluate(conf: str, overrides: list[str]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(conf, version_base="1.3"):
        return compose("evaluate", overrides=overrides)


def demos_index(store) -> SourceIndex:
    return SourceIndex.from_store(store, 20, pusht_weights(), None)
