"""Serving a policy over the network: a websocket server for any K-CFM checkpoint (transported online or not), its
client, and the msgpack wire format they share; the network calls of requests in flight at once run as one batch
(:mod:`kpflow.serving.batching`). ``kpflow-serve checkpoint=...`` runs the server."""

from kpflow.serving.batching import BatchedNetwork
from kpflow.serving.client import PolicyClient, PolicyServerError
from kpflow.serving.deployment import Deployment, load_deployment
from kpflow.serving.protocol import PolicyMetadata
from kpflow.serving.server import PolicyServer

__all__ = [
    "BatchedNetwork",
    "Deployment",
    "PolicyClient",
    "PolicyMetadata",
    "PolicyServer",
    "PolicyServerError",
    "load_deployment",
]
