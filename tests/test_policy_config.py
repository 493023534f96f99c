"""A checkpoint is the policy (kpflow/policies/config.py, factory.PolicyBuilder): its config is saved in it, one
builder reads it for ``kpflow.load_policy``, ``kpflow-evaluate`` and ``kpflow-serve``, an option the chosen mode
ignores is refused by name, and a checkpoint from before the record still loads."""

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate

import kpflow
from kpflow.core.policy import PolicyLayout
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.suite import SuiteReport
from kpflow.policies.config import DEFAULTS, PolicyConfig, TransportConfig, map_factory
from kpflow.policies.factory import PolicyBuilder
from kpflow.policies.subgoal import SubgoalPolicy
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
from kpflow.serving import PolicyClient, PolicyServer, load_deployment
from kpflow.tasks.pusht.task import PushTTask
from kpflow.tasks.suite.task import SuiteTask
from kpflow.utils.checkpoint import read_checkpoint
from tests.helpers import compose_config

ROOT = Path(__file__).resolve().parents[1]
RELEASES = sorted((ROOT / "release").glob("*.ckpt"))
KINDS = {"pusht_table1_kcfm_35_relabelled": "transported_kcfm", "suite_": "transported_kcfm"}


def expected_kind(path: Path) -> str:
    return next((kind for prefix, kind in KINDS.items() if path.stem.startswith(prefix)), "kcfm")


# ------------------------------------------------------------------------------------------------ resolution


def test_a_value_given_wins_then_the_checkpoints_then_the_tasks_then_the_built_in():
    given = TransportConfig(map="gp", search={"candidates": 5})
    stored = TransportConfig(map="affine", pull_back="all", search={"candidates": 2, "temperature": 0.5})
    task = {"fit_on": ["objects", "robot"], "search": {"stuck_decisions": 5, "temperature": 9.0}}
    got = given.over(stored, defaults=task)
    assert (got.map, got.pull_back, got.fit_on, got.segments, got.arm, got.alternatives) == (
        "gp",
        "all",
        ("objects", "robot"),
        False,
        False,
        3,
    )
    assert got.search == {**DEFAULTS["search"], "stuck_decisions": 5, "temperature": 0.5, "candidates": 5}
    assert TransportConfig().over().record() == {**DEFAULTS, "fit_on": "all"}


def test_with_segments_the_phases_own_fit_and_frame_and_a_tasks_fit_on_is_dropped():
    got = TransportConfig().over(defaults={"segments": True, "fit_on": ["objects", "goals"]})
    assert got.segments and got.fit_on == "all" and "weights" not in got.search and "frame" not in got.search


@pytest.mark.parametrize(
    "given, stored, match",
    [
        ({"segments": True, "fit_on": ["objects"]}, {}, "ignores fit_on"),
        ({"fit_on": ["objects"]}, {"segments": True}, "ignores fit_on"),
        ({"segments": True, "search": {"frame": "objects"}}, {}, r"ignores search\.frame"),
        ({"segments": True, "search": {"weights": {"robot": 2.0}}}, {}, r"ignores search\.weights"),
        ({"alternatives": 2}, {}, "ignores alternatives"),
    ],
)
def test_an_option_the_mode_ignores_is_refused_by_name(given, stored, match):
    with pytest.raises(ValueError, match=match):
        TransportConfig.of(given).over(TransportConfig.of(stored))


@pytest.mark.parametrize(
    "record, match",
    [
        ({"maps": "ilwr"}, "has no option maps"),
        ({"pull_back": "hand"}, "pull_back must be one of"),
        ({"map": "os.system"}, "must name a file of kpflow/conf/map"),
        ({"map_options": {"_target_": "os.system"}}, r"\['_target_'\] are refused"),
        ({"search": {"nearest": 3}}, "the source search has no option nearest"),
        ({"alternatives": 0}, "alternatives must be an integer >= 1"),
        ({"segments": "yes"}, "segments must be true or false"),
    ],
)
def test_a_bad_transport_option_is_refused_naming_it(record, match):
    with pytest.raises(ValueError, match=match):
        TransportConfig.of(record)


def test_the_old_spelling_agent_reads_as_robot():
    assert TransportConfig(pull_back="agent").pull_back == "robot"


def test_a_map_is_built_from_the_packages_own_files_only():
    assert map_factory("ilwr", {"n_steps": 7})().n_steps == 7
    assert map_factory("gp_ml")().gp.iters == 6  # its defaults: [gp] merged under it
    with pytest.raises(ValueError, match="names no map of kpflow/conf/map/; the maps are affine"):
        map_factory("spline")


@pytest.mark.parametrize(
    "task", [PushTTask(), *(SuiteTask(name) for name in ("lift", "can", "square", "stack"))], ids=lambda t: t.name
)
def test_a_layout_record_reads_back_as_the_same_layout(task):
    layout = task.policy_layout
    back = PolicyLayout.from_record(layout.record())
    assert back.record() == layout.record() and back.phases == layout.phases and back.symmetries == layout.symmetries
    assert back.groups == layout.groups and back.transport == layout.transport
    with pytest.raises(ValueError, match="its keypoint layout record is malformed"):
        PolicyLayout.from_record({"n_keypoints": 3})


# ------------------------------------------------------------------------------------------------ checkpoints


@pytest.mark.parametrize("path", RELEASES, ids=lambda p: p.stem)
def test_every_release_holds_its_config_and_builds_with_no_overrides(path):
    config = PolicyConfig.of_checkpoint(read_checkpoint(path), str(path))
    assert config.kind == expected_kind(path) and config.layout is not None
    builder = PolicyBuilder(path)
    policy = builder.build()
    if config.kind == "transported_kcfm":
        inner = policy.policy if isinstance(policy, SubgoalPolicy) else policy
        assert isinstance(inner, TransportedKCFMPolicy)
        assert builder.config.transport.segments == path.stem.startswith("suite_")
    if config.settings.reach is not None:
        assert isinstance(policy, SubgoalPolicy) and policy.reach == config.settings.reach


def test_a_checkpoint_from_before_the_record_migrates_on_read(tmp_path):
    old = {k: v for k, v in read_checkpoint(ROOT / "release" / "suite_lift_kcfm.ckpt").items() if k != "policy_config"}
    torch.save(old, tmp_path / "old.ckpt")
    config = PolicyConfig.of_checkpoint(old)
    assert config.kind == "kcfm" and config.transport is None and config.layout is None
    assert (
        type(kpflow.load_policy(tmp_path / "old.ckpt")).__name__ == "KCFMPolicy"
    )  # its bare shape, no groups: the K-CFM
    (tmp_path / "old.source_index.npz").write_bytes(
        (ROOT / "release" / "suite_lift_kcfm.source_index.npz").read_bytes()
    )
    policy = kpflow.load_policy(
        tmp_path / "old.ckpt", task=SuiteTask("lift"), kind="transported_kcfm"
    )  # the task's defaults: segments
    assert isinstance(policy, TransportedKCFMPolicy) and policy.phases is not None


def test_a_kcfm_given_transport_options_or_a_malformed_record_is_refused(tmp_path):
    with pytest.raises(
        ValueError, match=r"kind=kcfm is the K-CFM as it is, not transported: transport options \['map'\]"
    ):
        kpflow.load_policy("release:pusht_standard_fast", kind="kcfm", transport={"map": "gp"})
    with pytest.raises(ValueError, match="unknown policy option"):
        kpflow.load_policy("release:pusht_standard_fast", segments=True)
    bad = read_checkpoint(ROOT / "release" / "pusht_standard_fast.ckpt")
    bad["policy_config"] = {"kind": "diffusion"}
    torch.save(bad, tmp_path / "bad.ckpt")
    with pytest.raises(ValueError, match="policy kind must be one of"):
        kpflow.load_policy(tmp_path / "bad.ckpt")


# ------------------------------------------------------------------------------------------------ one build path


def episodes(trial: PolicyTrial, condition: str, indices) -> list[tuple]:
    out = []
    for i in indices:
        result = trial.run(condition, i, {"policy": "p"}, seed=0)
        episode = result.artefacts["episode"]
        out.append((result.success, episode.steps, episode.records["action"].tobytes()))
    return out


class Served:
    """A policy served over a websocket in this process, acting through a client (what a robot computer sees)."""

    def __init__(self, deployment):
        self.server = PolicyServer(deployment, port=0)
        self.context = self.server.running()
        self.client = PolicyClient(self.context.__enter__())
        self.n_obs = self.client.n_obs

    def reset(self, seed=None):
        self.client.reset(seed)

    def act(self, obs):
        return self.client.act(obs)

    def close(self):
        self.client.close()
        self.context.__exit__(None, None, None)


@pytest.mark.parametrize(
    "release, entry, condition, max_steps",
    [
        ("pusht_standard_fast", ["policy=kcfm"], "standard", 80),
        ("pusht_table1_kcfm_35_relabelled", ["policy=transported_kcfm"], "object_ood", 80),
        ("suite_stack_kcfm", ["experiment=suite_policy", "task=stack", "policy=transported_kcfm"], "wide", 40),
    ],
)
def test_load_policy_and_serve_act_episode_by_episode_as_evaluate(release, entry, condition, max_steps, tmp_path):
    """Each release kind, with no overrides: kpflow-evaluate's policy (its config composed and instantiated),
    ``kpflow.load_policy`` and a served one act the same actions, step by step, on the same scenes (the evaluate
    config's default data node is there, and not used: the release's own source index is)."""
    cfg = compose_config("evaluate", [*entry, f"checkpoint=release:{release}"], tmp_path)
    task = instantiate(cfg.task)
    evaluated = instantiate(cfg.policy)
    report = SuiteReport() if isinstance(task, SuiteTask) else None
    want = episodes(PolicyTrial(task, evaluated, report, max_steps=max_steps), condition, [0, 1])
    loaded = kpflow.load_policy(f"release:{release}")
    assert episodes(PolicyTrial(task, loaded, report, max_steps=max_steps), condition, [0, 1]) == want
    served = Served(load_deployment(f"release:{release}"))
    try:
        assert episodes(PolicyTrial(task, served, report, max_steps=max_steps), condition, [0, 1]) == want
    finally:
        served.close()
    assert np.frombuffer(want[0][2], np.float32).size > 0


def test_the_map_group_and_policy_options_reach_the_transport_and_a_silent_ignore_is_refused(tmp_path):
    """``map=affine`` on the command line is the transport's map (by name), ``policy.transport.*`` its options; an
    option the release's phase-by-phase mode ignores is refused, not dropped."""
    base = ["experiment=suite_policy", "task=lift", "policy=transported_kcfm", "checkpoint=release:suite_lift_kcfm"]
    cfg = compose_config("evaluate", [*base, "map=affine", "policy.transport.search={candidates: 2}"], tmp_path)
    policy = instantiate(cfg.policy)
    assert (
        isinstance(policy.make_map(), kpflow.maps.AffineMap)
        and policy.source.candidates == 2
        and policy.phases is not None
    )
    cfg = compose_config("evaluate", [*base, "policy.transport.fit_on=[objects]"], tmp_path)
    with pytest.raises(InstantiationException, match="the transport ignores fit_on"):
        instantiate(cfg.policy)
    cfg = compose_config(
        "evaluate", [*base, "policy.transport.segments=false", "policy.transport.fit_on=[objects]"], tmp_path
    )
    assert instantiate(cfg.policy).phases is None


def test_a_checkpoint_of_no_kpflow_task_is_released_transported_with_its_robot_named(walk_store, tmp_path):
    """``kpflow-release robot=[-1] data=store ...``: the layout of data of no kpflow task (a LeRobot dataset's, say):
    the robot's keypoints named, the rest the scene; the release then loads as a transported K-CFM with no task."""
    from tests.helpers import run_command

    dst = tmp_path / "mine.ckpt"
    args = [f"src={ROOT / 'release' / 'pusht_table1_kcfm_35_corrected.ckpt'}", f"dst={dst}", "kind=transported_kcfm", "robot=[-1]",
            "settings.reach=false", "settings.turn_deg=false", "data=store", f"data.path={walk_store}", "data.n_obs=1"]  # fmt: skip
    done = run_command("kpflow.cli.release", *args)
    assert done.returncode == 0, done.stderr
    policy = kpflow.load_policy(dst)
    assert isinstance(policy, TransportedKCFMPolicy) and policy.phases is None
    assert PolicyConfig.of_checkpoint(read_checkpoint(dst)).layout["groups"]["robot"] == [24]
    policy.reset(0)
    obs = {"keypoints": policy.index.keypoints[3].astype(np.float64) + 2.0}
    assert np.isfinite(policy.act(obs)).all()
    refused = run_command(
        "kpflow.cli.release", *[a for a in args if not a.startswith("robot=")], f"dst={tmp_path / 'no.ckpt'}"
    )
    assert refused.returncode != 0 and "robot=[<index>, ...]" in refused.stderr and not (tmp_path / "no.ckpt").exists()


def test_a_run_records_the_transport_it_resolved(tmp_path):
    """evaluate's config.yaml gets the transport as resolved (every option, none null): what the run used."""
    from omegaconf import OmegaConf

    from kpflow.cli.evaluate import record_used

    cfg = compose_config(
        "evaluate",
        ["experiment=suite_policy", "task=lift", "policy=transported_kcfm", "checkpoint=release:suite_lift_kcfm"],
        tmp_path,
    )
    described = PolicyTrial(SuiteTask("lift"), instantiate(cfg.policy), SuiteReport()).describe()
    assert described["transport"]["segments"] is True and described["transport"]["map"] == "ilwr"
    record_used(cfg, described)
    used = OmegaConf.to_container(cfg.policy.transport)
    assert used == described["transport"] and None not in used.values()
