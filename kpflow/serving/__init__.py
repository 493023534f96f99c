"""Serving a policy over the network: a websocket server for any K-CFM checkpoint (transported online or not), its
client, and the msgpack wire format they share; the network calls of requests in flight at once run as one batch
(:mod:`kpflow.serving.batching`). ``kpflow-serve checkpoint=...`` runs the server.

The names below load on first use (PEP 562), so that the client (:mod:`kpflow.serving.client`, ``kpflow-connect``)
imports only numpy, websockets and msgpack, never torch: the server's side loads when one of its names is asked for.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as static tools (type checkers, the API reference) see them
    from kpflow.serving.batching import BatchedNetwork
    from kpflow.serving.client import PolicyClient, PolicyServerError
    from kpflow.serving.deployment import Deployment, load_deployment
    from kpflow.serving.protocol import PolicyMetadata
    from kpflow.serving.server import PolicyServer

#: public name -> the submodule that defines it
_LAZY = {
    "BatchedNetwork": "batching",
    "Deployment": "deployment",
    "PolicyClient": "client",
    "PolicyMetadata": "protocol",
    "PolicyServer": "server",
    "PolicyServerError": "client",
    "load_deployment": "deployment",
}

__all__ = [
    "BatchedNetwork",
    "Deployment",
    "PolicyClient",
    "PolicyMetadata",
    "PolicyServer",
    "PolicyServerError",
    "load_deployment",
]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value  # loaded once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
