"""Keypoint sets, stores and configs shared by the tests."""

import math
import os
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, open_dict

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "kpflow" / "conf"


def rotation(d: int, angle: float, dtype=torch.float64) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    r = torch.eye(d, dtype=dtype)
    r[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=dtype)
    if d == 3:  # add a tilt so 3-D is not just a planar rotation
        t = torch.tensor(
            [[1, 0, 0], [0, math.cos(0.4), -math.sin(0.4)], [0, math.sin(0.4), math.cos(0.4)]], dtype=dtype
        )
        r = t @ r
    return r


def deformation(x: torch.Tensor) -> torch.Tensor:
    """A smooth non-rigid displacement field of magnitude ~0.08."""
    return 0.08 * torch.sin(2.5 * x.roll(1, -1)) * torch.cos(1.5 * x)


def keypoint_pair(d: int = 2, n: int = 25, seed: int = 0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(n, d, generator=g, dtype=dtype)
    tgt = src @ rotation(d, 0.5, dtype).T + 0.3 + deformation(src)
    return src, tgt


def grid(d: int, lo: float = -1.0, hi: float = 2.0, n: int = 12, dtype=torch.float64) -> torch.Tensor:
    """A grid three times the [0, 1]^d keypoint extent."""
    axes = [torch.linspace(lo, hi, n, dtype=dtype)] * d
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, d)


WALK_RATE, WALK_START, WALK_LEN, WALK_EPISODES = 0.1, 200.0, 20, 8


def walk_to_block_store(path) -> None:
    """Push-T-shaped episodes where the agent walks in a straight line to the block's centre, covering the share
    ``WALK_RATE`` of the remaining distance each step: the action chunk
    ``a[t+k] = centre + (1 - WALK_RATE)^(k+1) (agent_t - centre)`` (absolute targets) is a deterministic (even
    linear) function of the keypoints, and moving the whole scene rigidly moves the chunk the same way."""
    from kpflow.data.episode_store import EpisodeStore
    from kpflow.tasks.pusht.geometry import observation_keypoints, t_keypoints

    rng = np.random.default_rng(0)
    store = EpisodeStore(path, mode="a")
    for _ in range(WALK_EPISODES):
        block = (*rng.uniform(150, 350, 2), rng.uniform(-np.pi, np.pi))
        goal = (*rng.uniform(150, 350, 2), rng.uniform(-np.pi, np.pi))
        centre = t_keypoints(block).mean(0)
        angle = rng.uniform(0, 2 * np.pi)
        agent = centre + WALK_START * np.array([np.cos(angle), np.sin(angle)])
        keypoints, actions = [], []
        for _ in range(WALK_LEN):
            keypoints.append(observation_keypoints(block, goal, agent))
            agent = agent + WALK_RATE * (centre - agent)
            actions.append(agent.copy())
        store.add_episode({"keypoints": np.array(keypoints, np.float32), "action": np.array(actions, np.float32)})


class StandStill:
    """A Push-T policy that targets where the agent is: it never moves (nothing is ever pushed)."""

    def reset(self, seed=None):
        pass

    def act(self, obs):
        return np.asarray(obs["agent_pos"], dtype=np.float64)


def train_learned_map(tmp_path, sampler, n_keypoints: int, steps: int, dim: int = 2) -> str:
    """Train a small :class:`~kpflow.maps.map_module.MapModule` for ``steps`` steps on 64 pairs from ``sampler``
    (``(n, rng) -> (source, target)``) with the real Lightning loop and checkpointing; returns its last.ckpt."""
    import lightning
    from lightning.pytorch.callbacks import ModelCheckpoint

    from kpflow.data.keypoint_pairs import KeypointPairDataModule
    from kpflow.maps.map_module import MapModule
    from kpflow.utils.checkpoint import SafeCheckpointIO

    lightning.seed_everything(0, verbose=False)
    model = MapModule(n_keypoints, dim, n_layers=8, hidden=32, context=32, lr=3e-3)
    data = KeypointPairDataModule(sampler, n_pairs=64, batch_size=32)
    checkpoints = ModelCheckpoint(dirpath=tmp_path / "checkpoints", save_last=True)
    trainer = lightning.Trainer(
        max_steps=steps,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[checkpoints],
        plugins=[SafeCheckpointIO()],
        accelerator="cpu",
        deterministic=True,
        num_sanity_val_steps=0,
    )
    trainer.fit(model, datamodule=data)
    return str(tmp_path / "checkpoints" / "last.ckpt")


def compose_config(entry: str, overrides: list[str], tmp_path):
    """The config ``entry`` (train, evaluate, ...) of ``conf/`` with ``overrides``, as its entry point would see it:
    Hydra's runtime output dir set to ``tmp_path`` and its choices filled in."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(entry, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):  # what Hydra's runtime would fill in
        cfg.hydra.runtime.output_dir = str(tmp_path)
        cfg.hydra.runtime.choices = OmegaConf.create(
            {k: v for k, v in cfg.hydra.runtime.choices.items() if v is not None}
        )
    HydraConfig.instance().set_config(cfg)
    return cfg


def child_env(**extra: str) -> dict[str, str]:
    """This process's environment for a command it runs, without the rendering platform chosen here (robosuite's
    import sets ``PYOPENGL_PLATFORM=egl`` when it finds no choice): the child chooses its own, consistently
    (:func:`kpflow.utils.headless.use_headless_gl`)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    return {**env, **extra}


def yaw_matrix(a: float) -> np.ndarray:
    """The rotation by ``a`` (rad) about the vertical, ``[3, 3]``."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cube_corners(centre, yaw: float, half: float = 0.021) -> np.ndarray:
    """The 8 corners ``[8, 3]`` of a cube of half side ``half`` at ``centre``, turned by ``yaw``."""
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return np.asarray(centre) + (signs * half) @ yaw_matrix(yaw).T


def run_command(module: str, *args: str, env: dict[str, str] | None = None):
    """Run command ``module`` (``kpflow.cli.serve``, what ``python -m module`` runs: its ``main``) in this process with
    ``args`` as its command line, as a subprocess would run it but without importing everything again: a
    ``subprocess.CompletedProcess`` of its exit code and what it printed. ``env`` sets variables for the run (the
    traceback switches are cleared unless given); the run folder it claimed is let go after, as at a process's end.

    For error paths, where a fresh process adds nothing but its imports; true end-to-end runs stay subprocesses."""
    import contextlib
    import importlib
    import io
    import subprocess
    import sys

    from kpflow.utils.run import end_run

    main = importlib.import_module(module).main
    saved_argv, saved_env, saved_cwd = sys.argv, dict(os.environ), os.getcwd()
    os.chdir(ROOT)  # where a subprocess of these tests runs: relative paths (release/...) read from the clone
    out, err, code = io.StringIO(), io.StringIO(), 0
    os.environ.pop("KPFLOW_TRACEBACK", None)
    os.environ.pop("HYDRA_FULL_ERROR", None)
    os.environ.update(env or {})
    sys.argv = [module, *args]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                result = main()
                code = result if isinstance(result, int) else 0
            except SystemExit as stop:
                code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
            finally:
                end_run()
    finally:
        os.chdir(saved_cwd)
        sys.argv = saved_argv
        os.environ.clear()
        os.environ.update(saved_env)
    return subprocess.CompletedProcess([module, *args], code, out.getvalue(), err.getvalue())


def load_kcfm(path):
    """The K-CFM model of a checkpoint (weights_only, on the CPU), for tests that assemble a policy around it."""
    from kpflow.policies.kcfm.model import KCFM
    from kpflow.utils.checkpoint import load_checkpoint
    from kpflow.utils.releases import resolve_release

    return load_checkpoint(KCFM, resolve_release(path), map_location="cpu")


def bare_kcfm(path, *args, **kwargs):
    """The bare :class:`~kpflow.policies.kcfm.policy.KCFMPolicy` of a checkpoint (no goal limit, whatever it
    records): ``KCFMPolicy(model, steps, execute, input_margin, solver)``."""
    from kpflow.policies.kcfm.policy import KCFMPolicy

    return KCFMPolicy(load_kcfm(path), *args, **kwargs)


def random_kcfm_3d(index, n_keypoints: int, horizon: int, n_obs: int):
    """A small 3-D K-CFM (10-D actions) with random weights (seed 0) and ``index``'s normalisation, in eval mode."""
    import torch

    from kpflow.policies.kcfm.model import KCFM

    torch.manual_seed(0)
    model = KCFM(
        n_keypoints, horizon, n_obs, action_dim=10, keypoint_dim=3, network={"name": "unet", "down_dims": (16, 32)}
    )
    model.processor.fit(index.keypoints, index.chunks[:, 0])
    return model.eval()
