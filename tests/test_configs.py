"""Every option of every ``conf/`` group composes with its entry point and instantiates into what it names
(lightning-hydra-template's config tests). A new file in ``conf/`` must be added here, or the coverage test fails."""

from dataclasses import is_dataclass
from functools import partial
from pathlib import Path

import lightning
import pytest
import torch
from hydra.utils import get_class, instantiate
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import OmegaConf

from kpflow.cli.train import fill_from_data
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.maps.base import TransportMap
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import CONF, compose_config, keypoint_pair, train_learned_map, walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ROOT / "release" / "pusht_standard_kcfm_human.ckpt"

# group -> {option: entry point that composes it}
ENTRIES = {
    "map": dict.fromkeys(["affine", "ilwr", "gp", "gp_ml", "flow", "mlp", "ensemble", "learned"], "evaluate"),
    "logger": dict.fromkeys(["csv", "default", "none"], "train"),
    "trainer": dict.fromkeys(["cpu", "gpu", "ddp", "ddp_cpu"], "train"),
    "hydra/launcher": dict.fromkeys(["pool", "local", "slurm"], "train"),
    "callbacks": {"default": "train"},
    "data": dict.fromkeys(
        [
            "frames_transported",
            "pusht_expert",
            "pusht_human",
            "pusht_store",
            "pusht_pairs",
            "frames_pairs",
            "suite_store",
            "store",
        ],
        "train",
    ),
    "model": dict.fromkeys(["kcfm", "neural_field", "learned_map"], "train"),
    "model/network": dict.fromkeys(["unet", "transformer"], "train"),
    "model/objective": dict.fromkeys(["icfm", "otcfm", "ddpm", "meanflow", "reflow"], "train"),
    "policy": dict.fromkeys(["nearest", "transport", "kcfm", "transported_kcfm"], "evaluate"),
    "keypoints": dict.fromkeys(["sim", "camera", "camera_clean"], "generate"),
    "task": {
        **dict.fromkeys(["frames", "pusht", "packing", "stacking"], "evaluate"),
        **dict.fromkeys(["lift", "stack", "can", "square"], "generate"),
    },
    "experiment": {
        **dict.fromkeys(
            ["frames", "packing", "pusht", "pusht_demo", "stacking", "suite_policy", "gym_policy", "offline"],
            "evaluate",
        ),
        **dict.fromkeys(
            [
                "frames_field",
                "frames_map",
                "pusht_kcfm",
                "pusht_kcfm_fast",
                "pusht_kcfm_gpu",
                "pusht_map",
                "suite_kcfm",
                "kcfm",
            ],
            "train",
        ),
    },
}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("configs") / "demos.zarr"
    walk_to_block_store(path)
    return path


def test_every_config_file_is_covered():
    on_disk: dict[str, set] = {}
    for f in CONF.glob("*/**/*.yaml"):
        on_disk.setdefault(str(f.parent.relative_to(CONF)), set()).add(f.stem)
    assert on_disk == {group: set(options) for group, options in ENTRIES.items()}


@pytest.mark.parametrize("name", sorted(set(ENTRIES["hydra/launcher"]) - {"pool"}))
def test_submitit_launchers_compose(name, tmp_path):
    cfg = compose_config("train", [f"hydra/launcher={name}"], tmp_path)
    launcher = cfg.hydra.launcher
    assert launcher._target_.startswith("hydra_plugins.hydra_submitit_launcher") and launcher.timeout_min > 0
    assert launcher.submitit_folder.endswith(".submitit/%j")


def test_the_joblib_launcher_composes(tmp_path):
    launcher = compose_config("train", ["hydra/launcher=pool"], tmp_path).hydra.launcher
    assert (
        launcher._target_ == "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
        and launcher.n_jobs >= 1
    )


@pytest.fixture(scope="module")
def learned_checkpoint(tmp_path_factory):
    """A learned map for 25 2-D keypoints, trained for a few steps (the map option's checkpoint)."""

    def pairs(n, rng):
        src, tgt = keypoint_pair(2)
        return src.expand(n, -1, -1).numpy(), tgt.expand(n, -1, -1).numpy()

    return train_learned_map(tmp_path_factory.mktemp("learned"), pairs, n_keypoints=25, steps=2)


@pytest.mark.parametrize("name", sorted(ENTRIES["map"]))
def test_map_options_build_a_fitted_map(name, tmp_path, request):
    src, tgt = keypoint_pair(2)
    options = {"flow": ["map.steps=5"], "mlp": ["map.steps=5"]}.get(name, [])
    if name == "learned":
        options = [f"map.checkpoint={request.getfixturevalue('learned_checkpoint')}"]
    cfg = compose_config("evaluate", [f"map={name}", "logger=none", *options], tmp_path)
    phi = instantiate(cfg.map)().fit(src, tgt)
    assert isinstance(phi, TransportMap) and phi(src).shape == src.shape


@pytest.mark.parametrize("name", sorted(ENTRIES["logger"]))
def test_logger_options_build_lightning_loggers(name, tmp_path):
    cfg = compose_config("train", [f"logger={name}"], tmp_path)
    loggers = [instantiate(node) for node in (cfg.logger or {}).values()]
    assert all(isinstance(lg, lightning.pytorch.loggers.Logger) for lg in loggers)
    assert len(loggers) == {"none": 0, "csv": 1, "default": 2}[name]


@pytest.mark.parametrize("name", sorted(ENTRIES["trainer"]))
def test_trainer_options_name_a_lightning_trainer(name, tmp_path):
    cfg = compose_config("train", [f"trainer={name}", "logger=none"], tmp_path)
    assert get_class(cfg.trainer._target_) is lightning.Trainer
    if cfg.trainer.accelerator == "cpu" or torch.cuda.is_available():
        trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
        assert trainer.max_epochs == cfg.trainer.max_epochs


def test_callbacks_checkpoint_into_the_run_folder(tmp_path):
    cfg = compose_config("train", ["logger=none"], tmp_path)
    callbacks = {name: instantiate(node) for name, node in cfg.callbacks.items()}
    assert isinstance(callbacks["model_checkpoint"], ModelCheckpoint)
    assert Path(callbacks["model_checkpoint"].dirpath) == tmp_path / "checkpoints"


@pytest.mark.parametrize("name", sorted(ENTRIES["data"]))
def test_data_options_build_datamodules(name, store, tmp_path):
    path = [f"data.path={store}", "data.n_episodes=null"] if name.startswith("pusht") else []
    if name == "pusht_pairs":
        path = [f"data.sampler.path={store}", "data.sampler.n_episodes=null", "data.n_pairs=20"]
    if name == "frames_pairs":
        path = ["data.n_pairs=20"]
    if name == "suite_store":  # any store with keypoints and an action field (a generated one has ee_target)
        path = [f"data.path={store}", "data.action_key=action"]
    if name == "store":
        path = [f"data.path={store}"]
    cfg = compose_config("train", ["~experiment", f"data={name}", "logger=none", *path], tmp_path)
    datamodule = instantiate(cfg.data)
    assert isinstance(datamodule, lightning.LightningDataModule)
    datamodule.setup("fit")
    batch = next(iter(datamodule.train_dataloader()))
    values = batch.values() if isinstance(batch, dict) else vars(batch).values() if is_dataclass(batch) else batch
    assert all(torch.isfinite(v).all() for v in values)


@pytest.mark.parametrize("name", sorted(ENTRIES["model"]))
def test_model_options_build_lightning_modules(name, tmp_path):
    # K-CFM's horizon and history come from the Push-T data, its keypoints from the task (its experiment sets them)
    data = ["data=pusht_expert", "model.n_keypoints=25"] if name == "kcfm" else []
    cfg = compose_config("train", ["~experiment", f"model={name}", "logger=none", *data], tmp_path)  # the group alone
    model = instantiate(cfg.model, _convert_="all")
    assert isinstance(model, lightning.LightningModule) and sum(p.numel() for p in model.parameters()) > 0


@pytest.mark.parametrize("group", ["model/network", "model/objective"])
def test_each_kcfm_network_and_objective_builds_by_name(group, tmp_path):
    for name in ENTRIES[group]:
        teacher = [f"model.objective.teacher={RELEASED}"] if name == "reflow" else []  # read when training starts
        cfg = compose_config("train", ["experiment=pusht_kcfm", f"{group}={name}", "logger=none", *teacher], tmp_path)
        model = instantiate(cfg.model, _convert_="all")
        assert model.hparams[group.split("/")[1]]["name"] == name


@pytest.mark.parametrize("name", sorted(ENTRIES["policy"]))
def test_policy_options_build_policies_that_act(name, store, tmp_path):
    from kpflow.tasks.pusht import PushTEnv, split_config

    checkpoint = [f"policy.checkpoint={RELEASED}"] if "kcfm" in name else []
    cfg = compose_config(
        "evaluate", [f"policy={name}", "data=pusht_store", f"data.path={store}", "logger=none", *checkpoint], tmp_path
    )
    policy = instantiate(cfg.policy)
    env = PushTEnv()
    obs, _ = env.reset(options={"config": split_config("in_distribution", 0)})
    policy.reset()
    chunk = policy.act(obs)
    assert chunk.ndim == 2 and chunk.shape[1] == 2 and torch.isfinite(torch.as_tensor(chunk)).all()


@pytest.mark.parametrize("search, stuck", [(None, 5), ("{stuck_decisions: false}", None), ("{stuck_decisions: 3}", 3)])
def test_the_source_search_is_the_tasks_unless_the_policy_says(search, stuck, store, tmp_path):
    """``policy.search`` unset: Push-T's own search (a stuck block after 5 decisions, compared relative to the block);
    given: its options over the task's, ``false`` turning stuck detection off."""
    given = [] if search is None else [f"policy.search={search}"]
    cfg = compose_config(
        "evaluate", ["policy=transport", "data=pusht_store", f"data.path={store}", "logger=none", *given], tmp_path
    )
    policy = instantiate(cfg.policy)
    assert policy.source.stuck_decisions == stuck
    assert policy.index.reference == list(PushTTask.policy_layout.indices("objects"))
    from kpflow.cli.evaluate import record_used
    from kpflow.eval.policy_trial import PolicyTrial
    from kpflow.eval.reports.pusht import PushTReport

    record_used(cfg, PolicyTrial(PushTTask(), policy, PushTReport()).describe())  # config.yaml: what the run used
    assert cfg.policy.search.stuck_decisions == stuck and dict(cfg.policy.search.weights) == {
        "objects": 1.0,
        "goals": 1.0,
        "robot": 4.0,
    }
    assert list(cfg.policy.fit_on) == ["objects", "robot"]


@pytest.mark.parametrize("name", sorted(n for n, entry in ENTRIES["task"].items() if entry == "evaluate"))
def test_task_options_build_tasks_that_sample_scenes(name, tmp_path):
    cfg = compose_config("evaluate", [f"task={name}", "logger=none"], tmp_path)
    task = instantiate(cfg.task, _convert_="all")
    assert task.name == name
    scenes = [task.sample_scene(task.conditions[-1], i).as_dict() for i in range(3)]
    assert scenes[0] == task.sample_scene(task.conditions[-1], 0).as_dict() and scenes[0] != scenes[1]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(n for n, entry in ENTRIES["task"].items() if entry == "generate"))
def test_generation_tasks_and_transports_build_from_the_generate_config(name, tmp_path):
    from kpflow.generation.segment_transport import SegmentTransport

    cfg = compose_config("generate", [f"task={name}"], tmp_path)
    task = instantiate(cfg.task)
    assert task.name == name and set(cfg.families) <= set(cfg.transports)
    assert all(isinstance(instantiate(t), SegmentTransport) for t in cfg.transports.values())
    env = task.make_sim()
    scenes = [task.sample_scene(env, "wide", i).as_dict() for i in (0, 0, 1)]
    assert scenes[0] == scenes[1] != scenes[2]


# every entry point that builds a robosuite task or packing: keypoints=... switches where their keypoints come from
KEYPOINT_ENTRIES = [
    *[("generate", [f"task={t}"]) for t in ("lift", "stack", "can", "square")],
    ("evaluate", ["experiment=suite_policy", "task=lift", "policy.checkpoint=model.ckpt"]),
    ("evaluate", ["experiment=packing"]),
    ("release", ["task=square", "src=a.ckpt", "dst=b.ckpt"]),
    ("serve", ["task=can", "checkpoint=model.ckpt"]),
]


@pytest.mark.parametrize(
    ("entry", "overrides"), KEYPOINT_ENTRIES, ids=lambda v: v if isinstance(v, str) else "-".join(v)
)
@pytest.mark.parametrize("keypoints", sorted(ENTRIES["keypoints"]))
def test_keypoint_options_switch_every_entry_points_task(entry, overrides, keypoints, tmp_path):
    from kpflow.tasks.packing.perception import PackingCamera
    from kpflow.tasks.suite.keypoints import SimulatorPoses
    from kpflow.tasks.suite.perception import CameraKeypoints

    cfg = compose_config(entry, [*overrides, f"keypoints={keypoints}", "logger=none"] if entry == "evaluate" else
                         [*overrides, f"keypoints={keypoints}"], tmp_path)  # fmt: skip
    task = instantiate(cfg.task, _convert_="all")
    camera = keypoints != "sim"
    assert task.keypoints.kind == ("camera" if camera else "sim")
    assert task.keypoints.noise.mask_px == (2 if keypoints == "camera" else 0) or not camera
    if task.name == "packing":
        assert isinstance(task.camera, PackingCamera) if camera else task.camera is None
        assert task.keypoint_sources == (task.keypoints.kind,)
    else:
        assert isinstance(task.perception, CameraKeypoints if camera else SimulatorPoses)
        assert not camera or task.perception.cameras.names == ("frontview", "birdview", "agentview")


def square_kcfm(tmp_path) -> Path:
    """An untrained K-CFM checkpoint with the square task's layout (its policy keypoints and end-effector actions)."""
    from kpflow.policies.kcfm.model import KCFM
    from kpflow.tasks.suite.task import SuiteTask

    layout = SuiteTask("square").policy_layout
    model = KCFM(
        n_keypoints=layout.n_keypoints,
        keypoint_dim=layout.keypoint_dim,
        action_dim=layout.action_dim,
        horizon=16,
        network={"name": "unet", "down_dims": [16, 32]},
    )
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams)}, tmp_path / "square.ckpt")
    return tmp_path / "square.ckpt"


@pytest.mark.parametrize(("name", "entry"), sorted(ENTRIES["experiment"].items()))
def test_experiment_options_compose_and_instantiate(name, entry, store, tmp_path):
    # suite_policy evaluates a trained checkpoint of its task's layout (square's: an untrained K-CFM saved here); the
    # generic experiments read any store; gym_policy needs a Gymnasium task of the user's (kpflow-example reach_task: test_docs)
    extra = {
        "suite_policy": [f"policy.checkpoint={square_kcfm(tmp_path)}"],
        "offline": ["checkpoint=model.ckpt", f"data.path={store}"],
        "kcfm": [f"data.path={store}"],
        "gym_policy": ["policy.checkpoint=model.ckpt"],
    }.get(name, [])
    cfg = compose_config(entry, [f"experiment={name}", "logger=none", *extra], tmp_path)
    if name == "gym_policy":
        assert get_class(cfg.experiment.trial._target_) is PolicyTrial and "task" not in cfg  # task=<yours> adds it
    elif name == "kcfm":  # the model's size is left to the data
        assert cfg.model.n_keypoints is None
        fill_from_data(cfg.model, instantiate(cfg.data))
        model = instantiate(cfg.model, _convert_="all")
        assert (model.hparams.n_keypoints, model.hparams.keypoint_dim, model.hparams.action_dim) == (25, 2, 2)
    elif entry == "evaluate":
        run = instantiate(cfg.experiment)
        assert isinstance(run, partial) and callable(run)
    else:
        assert isinstance(instantiate(cfg.model, _convert_="all"), lightning.LightningModule)


def test_evaluate_takes_condition_and_still_reads_split_its_old_spelling(tmp_path):
    from kpflow.cli.spellings import read_split

    new = compose_config("evaluate", ["condition=standard"], tmp_path)
    old = compose_config("evaluate", ["split=standard"], tmp_path)
    read_split(new), read_split(old)
    assert new.condition == old.condition == "standard" and old.split is None
    assert OmegaConf.to_container(old.experiment, resolve=True)["conditions"] == "standard"
    with pytest.raises(
        ValueError, match="split=robot_ood \\(the old spelling of condition\\) contradicts condition=standard"
    ):
        read_split(compose_config("evaluate", ["split=robot_ood", "condition=standard"], tmp_path))
