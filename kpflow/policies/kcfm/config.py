"""What a K-CFM is, as one config (LeRobot's config dataclass per policy): its layout, its processor's frames, its
network and objective each a registered name plus options, how it samples and how it is optimised.

The config is what a checkpoint's ``hyper_parameters`` hold, as plain names, numbers, lists and dicts
(:meth:`KCFMConfig.hparams`), and what ``kpflow/conf/model/kcfm.yaml`` composes (``model.network.down_dims=[64,128]``,
``model/objective=ddpm``, ``model.processor.origin=-3``). Checkpoints written before the config existed held the same
values as one flat list of constructor arguments (``down_dims``, ``objective_options``, ``sample_steps``...):
:func:`migrate` moves them into their groups when such a file is read.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

LR_SCHEDULES = ("cosine", "constant")


@dataclass(frozen=True)
class ProcessorConfig:
    """The processor's frames (:class:`~kpflow.policies.kcfm.processor.KeypointProcessor`): ``goal_frame`` (planar:
    the goal's keypoints and their template), ``relative`` (actions as offsets from the agent), ``origin`` (keypoints
    and action positions relative to this keypoint)."""

    goal_frame: dict | None = None
    relative: bool = False
    origin: int | None = None


@dataclass(frozen=True)
class Named:
    """A registered ``name`` (a network of :data:`~kpflow.policies.kcfm.networks.NETWORKS`, an objective of
    :data:`~kpflow.policies.kcfm.objectives.OBJECTIVES`) and the ``options`` it is built with."""

    name: str
    options: dict = field(default_factory=dict)

    @classmethod
    def of(cls, value: Mapping | str | None, default: str, what: str) -> Named:
        """From ``{"name": NAME, **options}``, a bare ``NAME``, or None (``default``); ``ValueError`` naming ``what``."""
        if value is None:
            return cls(default)
        if isinstance(value, str):
            return cls(value)
        if not isinstance(value, Mapping) or not isinstance(value.get("name", default), str):
            raise ValueError(f"{what} must be a name or {{name: NAME, option: value, ...}}; got {value!r}")
        return cls(value.get("name", default), {k: v for k, v in value.items() if k != "name"})

    def hparams(self) -> dict:
        return {"name": self.name, **self.options}


@dataclass(frozen=True)
class SamplerConfig:
    """How a chunk is sampled unless :meth:`KCFM.sample` is told: ``steps`` network calls of ``solver`` (None: the
    objective's first)."""

    steps: int = 10
    solver: str | None = None


@dataclass(frozen=True)
class OptimConfig:
    """AdamW (``lr``, ``weight_decay``), the LR schedule (``"cosine"`` to 0 over the run, or ``"constant"``) after
    ``warmup_steps`` of linear warm-up, and the EMA of the weights (``ema_decay``)."""

    lr: float = 1e-3
    weight_decay: float = 1e-6
    lr_schedule: str = "cosine"
    warmup_steps: int = 0
    ema_decay: float = 0.999

    def __post_init__(self) -> None:
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"optim.lr_schedule must be one of {LR_SCHEDULES}; got {self.lr_schedule!r}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"optim.ema_decay must be in [0, 1); got {self.ema_decay}")
        if self.warmup_steps < 0:
            raise ValueError(f"optim.warmup_steps must be >= 0; got {self.warmup_steps}")


def _group(cls, value: Mapping | None, what: str):
    if value is None:
        return cls()
    if not isinstance(value, Mapping):
        raise ValueError(f"{what} must be a mapping of options; got {value!r}")
    try:
        return cls(**value)
    except TypeError as e:
        raise ValueError(f"bad {what} options {dict(value)}: {e}") from None


@dataclass(frozen=True)
class KCFMConfig:
    """A K-CFM (module docstring): ``n_keypoints`` ``K`` per observation, chunks of ``horizon`` ``H`` actions of
    ``action_dim`` ``A`` values, conditioned on the last ``n_obs`` frames of ``keypoint_dim``-D keypoints."""

    n_keypoints: int
    horizon: int = 20
    n_obs: int = 1
    action_dim: int = 2
    keypoint_dim: int = 2
    processor: ProcessorConfig = ProcessorConfig()
    network: Named = Named("unet")
    objective: Named = Named("icfm")
    sampler: SamplerConfig = SamplerConfig()
    optim: OptimConfig = OptimConfig()

    def __post_init__(self) -> None:
        dims = (self.horizon, self.n_obs, self.n_keypoints, self.action_dim, self.keypoint_dim)
        if min(dims) < 1:
            raise ValueError(
                f"need horizon, n_obs, n_keypoints, action_dim, keypoint_dim >= 1; got {', '.join(map(str, dims))}"
            )

    @classmethod
    def of(cls, n_keypoints: int, horizon: int = 20, n_obs: int = 1, action_dim: int = 2, keypoint_dim: int = 2,
           processor=None, network=None, objective=None, sampler=None, optim=None) -> KCFMConfig:  # fmt: skip
        """The config of plain values (what a Hydra node or a checkpoint's hyper-parameters hold): each group a
        mapping of its options, ``network`` and ``objective`` ``{name: NAME, **options}`` or a bare name."""
        return cls(n_keypoints, horizon, n_obs, action_dim, keypoint_dim,
                   processor if isinstance(processor, ProcessorConfig) else _group(ProcessorConfig, processor, "processor"),
                   network if isinstance(network, Named) else Named.of(network, "unet", "network"),
                   objective if isinstance(objective, Named) else Named.of(objective, "icfm", "objective"),
                   sampler if isinstance(sampler, SamplerConfig) else _group(SamplerConfig, sampler, "sampler"),
                   optim if isinstance(optim, OptimConfig) else _group(OptimConfig, optim, "optim"))  # fmt: skip

    def hparams(self) -> dict[str, Any]:
        """The config as plain values, ``KCFM(**config.hparams())`` building the same model."""
        return {
            "n_keypoints": self.n_keypoints,
            "horizon": self.horizon,
            "n_obs": self.n_obs,
            "action_dim": self.action_dim,
            "keypoint_dim": self.keypoint_dim,
            "processor": asdict(self.processor),
            "network": self.network.hparams(),
            "objective": self.objective.hparams(),
            "sampler": asdict(self.sampler),
            "optim": asdict(self.optim),
        }


#: the flat constructor arguments of checkpoints from before :class:`KCFMConfig`, by the group each moved to
_OLD_PROCESSOR = ("goal_frame", "relative", "origin")
_OLD_NETWORK = {"unet": ("down_dims", "kernel_size", "n_groups", "time_dim"),
                "transformer": ("d_model", "n_layers", "n_heads", "time_dim")}  # fmt: skip
_OLD_OPTIM = ("lr", "weight_decay", "lr_schedule", "warmup_steps", "ema_decay")
_OLD_KEYS = {*_OLD_PROCESSOR, *_OLD_OPTIM, *(k for ks in _OLD_NETWORK.values() for k in ks), "objective_options",
             "sample_steps", "solver"}  # fmt: skip


def migrate(hparams: Mapping) -> Mapping:
    """A checkpoint's K-CFM hyper-parameters in :class:`KCFMConfig`'s groups: flat ones of an older file (module
    docstring) moved into ``processor``, ``network``, ``objective``, ``sampler`` and ``optim``; the options of the
    network it did not use dropped (they built nothing); current ones, and anything not a mapping, as they are."""
    if not isinstance(hparams, Mapping) or not (_OLD_KEYS & set(hparams) or isinstance(hparams.get("network"), str)):
        return hparams
    old = dict(hparams)
    new = {k: old.pop(k) for k in ("n_keypoints", "horizon", "n_obs", "action_dim", "keypoint_dim") if k in old}
    new["processor"] = {k: old.pop(k) for k in _OLD_PROCESSOR if k in old}
    network = old.pop("network", "unet")
    options = {k: old.pop(k) for k in _OLD_NETWORK.get(network, ()) if k in old} if isinstance(network, str) else {}
    for k in {k for ks in _OLD_NETWORK.values() for k in ks}:
        old.pop(k, None)
    new["network"] = {"name": network, **options}
    objective = old.pop("objective_options", None) or {}
    if not isinstance(objective, Mapping):  # left for the model to refuse by name
        old["objective_options"], objective = objective, {}
    new["objective"] = {"name": old.pop("objective", "icfm"), **objective}
    new["sampler"] = {"steps": old.pop("sample_steps", 10), "solver": old.pop("solver", None)}
    new["optim"] = {k: old.pop(k) for k in _OLD_OPTIM if k in old}
    return {**new, **old}  # anything else stays, and is refused by name when the model is built
