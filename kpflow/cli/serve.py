"""Serve a trained policy: ``kpflow-serve checkpoint=PATH [kind=transported_kcfm transport.map=gp] [host=0.0.0.0 port=8000]``.

Runs :class:`~kpflow.serving.server.PolicyServer` for the checkpoint's policy as its config says (its kind,
settings and transport: :mod:`kpflow.policies.config`), the options given on top, built by the one builder
(:class:`~kpflow.policies.factory.PolicyBuilder`; a transported K-CFM reads its source index from
``<name>.source_index.npz`` beside the checkpoint) until SIGINT or SIGTERM. ``transported=true|false`` is the old
spelling of ``kind``.
Connect with :class:`~kpflow.serving.client.PolicyClient`.

The config keys, then the host and port (the host must resolve and the port bind), are checked before the model is
loaded, so a mistyped address fails at once with one line naming it. ``input_margin`` (10 by default) is how far
outside the K-CFM's training keypoints, in extents of their box on each side, an observation may lie before it is
refused (:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`); null turns the check off.

``batch.max_size`` (8 by default; 1 turns batching off) and ``batch.max_wait_ms`` (5): the network calls of requests
from several clients in flight at once run as one forward pass of at most that many rows, its leader waiting at
most that long for the others (:mod:`kpflow.serving.batching`). A lone client never waits.
"""

import logging

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.policies.config import KINDS
from kpflow.policies.factory import SETTINGS
from kpflow.serving.deployment import load_deployment
from kpflow.serving.server import PolicyServer, check_address
from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.errors import command, config_dir_checked

log = logging.getLogger("kpflow.serve")
KEYS = {
    "checkpoint": Key(str),
    "kind": Key(str, choices=KINDS, nullable=True),
    "transported": Key(bool, nullable=True),
    "steps": Key(int, lo=1, nullable=True),
    "solver": Key(str, nullable=True),
    "execute": Key(int, lo=1, nullable=True),
    "control_hz": Key(float, lo=0),
    "host": Key(str),
    "port": Key(int, lo=0, hi=65535),
    "max_message_mb": Key(float, lo=0.001, hi=1024),  # PolicyServer takes frames of at least 1024 bytes
    "input_margin": Key(float, lo=0, nullable=True),
    "threads": Key(int, lo=1),
    "batch.max_size": Key(int, lo=1),
    "batch.max_wait_ms": Key(float, lo=0, hi=1000),
}


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="serve")
@command
def main(cfg: DictConfig) -> None:
    check_config(cfg, KEYS)
    check_address(cfg.host, cfg.port)  # before the model is loaded
    torch.set_num_threads(cfg.threads)
    kind = cfg.kind
    if cfg.transported is not None:
        old = "transported_kcfm" if cfg.transported else "kcfm"
        if kind not in (None, old):
            raise ValueError(
                f"transported={cfg.transported} (the old spelling of kind) contradicts kind={kind}: give kind alone"
            )
        kind = old
    overrides = {
        "kind": kind,
        "transport": OmegaConf.to_container(cfg.transport, resolve=True),
        **{k: cfg[k] for k in SETTINGS},
    }
    task = instantiate(cfg.task) if cfg.get("task") is not None else None
    deployment = load_deployment(
        cfg.checkpoint,
        task,
        overrides,
        cfg.control_hz,
        cfg.input_margin,
        cfg.batch.max_size,
        float(cfg.batch.max_wait_ms),
    )
    server = PolicyServer(deployment, cfg.host, cfg.port, int(cfg.max_message_mb * 2**20))
    batching = (
        f"batches of up to {cfg.batch.max_size} rows, {cfg.batch.max_wait_ms:g} ms wait"
        if cfg.batch.max_size > 1
        else "no batching"
    )
    log.info(
        "%s from %s (sha256 %s; %s); Ctrl-C stops",
        deployment.metadata.policy,
        cfg.checkpoint,
        deployment.metadata.checkpoint_sha256[:12],
        batching,
    )
    server.run()


if __name__ == "__main__":
    main()
