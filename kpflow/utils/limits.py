"""The sizes a file's hyper-parameters may ask kpflow to build: one table, checked before anything is allocated.

A checkpoint's ``hyper_parameters`` decide how large the model is and what its first call allocates, and a small
file can declare any number. :func:`check_hyper_parameters` refuses a value outside :data:`LIMITS` with one line
naming the file, the key, the value and the limit, before the module is built (its skeleton included): every
checkpoint kpflow loads goes through it (:func:`kpflow.utils.checkpoint.load_checkpoint`). The limits sit far above
anything kpflow trains (the released K-CFMs: horizon 16, a (64, 128) U-Net; the learned map: 16 layers) and far
below what exhausts a machine.

| key | at most | what it sizes |
|---|---|---|
| ``horizon`` | 1024 | actions per chunk: the sampled noise and every network call |
| ``n_obs`` | 64 | observation frames per decision |
| ``n_keypoints`` | 4096 | keypoints per frame |
| ``keypoint_dim`` | 3 | coordinates per keypoint |
| ``action_dim`` | 1024 | values per action |
| ``sample_steps`` | 100 | network calls per chunk |
| ``objective_options.train_steps`` | 10000 | a diffusion's steps (its schedule's tables; Diffusion Policy: 100) |
| ``down_dims`` (each), ``d_model``, ``hidden``, ``context``, ``time_dim`` | 4096 | a layer's width |
| ``n_layers``, ``n_heads``, ``encoder_depth``, ``coupling_depth`` | 256 | layers, heads |
| ``kernel_size`` | 63 | a convolution's width |
"""

from __future__ import annotations

from typing import Any, Mapping

#: key (dotted for a nested option) -> the largest value allowed; a list value is checked item by item.
LIMITS: dict[str, int] = {
    "horizon": 1024,
    "n_obs": 64,
    "n_keypoints": 4096,
    "keypoint_dim": 3,
    "action_dim": 1024,
    "sample_steps": 100,
    "objective_options.train_steps": 10_000,
    "down_dims": 4096,
    "d_model": 4096,
    "hidden": 4096,
    "context": 4096,
    "time_dim": 4096,
    "n_layers": 256,
    "n_heads": 256,
    "encoder_depth": 256,
    "coupling_depth": 256,
    "kernel_size": 63,
}


def _lookup(hparams: Mapping, key: str) -> Any:
    value: Any = hparams
    for part in key.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def check_hyper_parameters(hparams: Mapping, where: str) -> None:
    """Raise ``ValueError`` naming ``where``, the key, its value and the limit for the first hyper-parameter of
    :data:`LIMITS` that ``hparams`` sets beyond it (module docstring); keys it does not set are not checked here."""
    for key, most in LIMITS.items():
        value = _lookup(hparams, key)
        if value is None:
            continue
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(item, bool) or not isinstance(item, int):
                continue  # the module's own checks name a value of the wrong type
            if item > most:
                raise ValueError(f"{where}: hyper-parameter {key} = {item} is beyond kpflow's limit {most} (kpflow/utils/limits.py); refusing to build it")
