"""The sizes a file's hyper-parameters may ask kpflow to build: one table, checked before anything is allocated.

A checkpoint's ``hyper_parameters`` decide how large the model is and what its first call allocates, and a small
file can declare any number. :func:`check_hyper_parameters` refuses a value outside :data:`LIMITS` with one line
naming the file, the key, the value and the limit, before the module is built (its skeleton included). Each value
the table bounds must be a plain ``int`` (not a bool, a float, or a tensor, which would slip past a comparison as a
number and size the model all the same), and hyper-parameters hold no tensors at all (they are plain names,
numbers and lists; weights live in the state dict): every
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
| ``sampler.steps`` | 100 | a K-CFM's network calls per chunk |
| ``objective.train_steps`` | 10000 | a diffusion's steps (its schedule's tables; Diffusion Policy: 100) |
| ``network.down_dims`` (each), ``network.d_model``, ``network.time_dim``, ``hidden``, ``context`` | 4096 | a layer's width |
| ``network.n_layers``, ``network.n_heads``, ``n_layers``, ``encoder_depth``, ``coupling_depth`` | 256 | layers, heads |
| ``network.kernel_size`` | 63 | a convolution's width |

A K-CFM's keys are those of its config's groups (:class:`~kpflow.policies.kcfm.config.KCFMConfig`; an older file's
flat ones are moved there first); the others are the learned map's (:class:`~kpflow.maps.map_module.MapModule`).
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
    "sampler.steps": 100,
    "objective.train_steps": 10_000,
    "network.down_dims": 4096,
    "network.d_model": 4096,
    "network.time_dim": 4096,
    "network.n_layers": 256,
    "network.n_heads": 256,
    "network.kernel_size": 63,
    "hidden": 4096,
    "context": 4096,
    "n_layers": 256,
    "encoder_depth": 256,
    "coupling_depth": 256,
}


def _lookup(hparams: Mapping, key: str) -> Any:
    value: Any = hparams
    for part in key.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def _tensor_keys(value: Any, key: str = "") -> list[str]:
    """The dotted keys under which ``value`` (hyper-parameters) holds a tensor or an array."""
    if isinstance(value, Mapping):
        return [k for name, v in value.items() for k in _tensor_keys(v, f"{key}.{name}" if key else str(name))]
    if isinstance(value, (list, tuple)):
        return [k for i, v in enumerate(value) for k in _tensor_keys(v, f"{key}[{i}]")]
    return [key] if hasattr(value, "shape") and hasattr(value, "dtype") else []


def check_hyper_parameters(hparams: Mapping, where: str) -> None:
    """Raise ``ValueError`` naming ``where`` and the key when ``hparams`` holds a tensor (or array) anywhere, when a
    hyper-parameter of :data:`LIMITS` is not a plain ``int`` (each item, for a list), or when it is negative or beyond
    its limit (module docstring); keys it does not set are not checked here."""
    if not isinstance(hparams, Mapping):
        raise ValueError(
            f"{where}: hyper_parameters is a {type(hparams).__name__}, not a mapping of names to values; refusing to build it"
        )
    tensors = _tensor_keys(hparams)
    if tensors:
        raise ValueError(
            f"{where}: hyper-parameter {tensors[0]} is a tensor, not a plain number or list (hyper-parameters are plain values); refusing to build it"
        )
    for key, most in LIMITS.items():
        value = _lookup(hparams, key)
        if value is None:
            continue
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(item, bool) or not isinstance(item, int):
                raise ValueError(
                    f"{where}: hyper-parameter {key} = {item!r} is a {type(item).__name__}, not a whole number (int); refusing to build it"
                )
            if item < 0:
                raise ValueError(f"{where}: hyper-parameter {key} = {item} is negative; refusing to build it")
            if item > most:
                raise ValueError(
                    f"{where}: hyper-parameter {key} = {item} is beyond kpflow's limit {most} (kpflow/utils/limits.py); refusing to build it"
                )
