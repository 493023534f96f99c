"""The K-CFM's denoising networks, chosen by name: a 1-D temporal U-Net and a small transformer, both FiLM-conditioned.

Every network is called ``net(x [B, H, A], t, c [B, C]) -> [B, H, A]`` and built by its file's ``build(dims,
**options)`` from the :class:`NetworkDims` the model knows and the options its config names
(``model.network.<option>``). A new network is a file with such a ``build`` and one entry in :data:`NETWORKS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import nn

from . import transformer1d, unet1d


@dataclass(frozen=True)
class NetworkDims:
    """What the model fixes of its network: ``action_dim`` ``A``, ``cond_dim`` ``C``, the chunk length ``horizon``
    ``H``, and the objective's time input (``n_times`` 1: a time, 2: an interval; ``time_scale`` of its embedding)."""

    action_dim: int
    cond_dim: int
    horizon: int
    n_times: int = 1
    time_scale: float = 1000.0


#: name -> ``build(dims, **options)``
NETWORKS: dict[str, Callable[..., nn.Module]] = {"unet": unet1d.build, "transformer": transformer1d.build}


def build_network(name: str, dims: NetworkDims, **options) -> nn.Module:
    """The network called ``name`` (one of :data:`NETWORKS`) for ``dims``, built with ``options``.

    Raises:
        ValueError: an unknown name, or options the network does not take (named).
    """
    if name not in NETWORKS:
        raise ValueError(f"unknown network {name!r}; choose one of {sorted(NETWORKS)}")
    try:
        return NETWORKS[name](dims, **options)
    except TypeError as e:
        raise ValueError(
            f"bad options {options} for network {name!r}: {e} (an experiment's options for another network can be dropped: "
            f"~model.network.OPTION)"
        ) from None


__all__ = ["NETWORKS", "NetworkDims", "build_network"]
