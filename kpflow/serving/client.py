"""The policy server's client: a :class:`~kpflow.core.task.Policy` (``reset(seed)``, ``act(obs)``) whose decisions
are taken by a remote :class:`~kpflow.serving.server.PolicyServer`.

``act`` sends only the observation keys the server's metadata names (an episode loop's ``obs`` may hold more), so a
client drops in wherever an in-process policy runs: ``run_episode(env, PolicyClient(uri), config, ...)``.
"""

from __future__ import annotations

import time
from contextlib import ExitStack

import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from .protocol import PolicyMetadata, check_seed
from .wire import pack, unpack


class PolicyServerError(RuntimeError):
    """The server refused a request (its reply's ``error``) or closed the connection."""


class PolicyClient:
    """Connect to ``uri`` (``ws://host:port``) and read the server's metadata.

    ``wait``: seconds to keep trying while nothing answers at ``uri`` (a server still loading its model).

    Attributes: ``metadata`` (:class:`PolicyMetadata`), ``max_message_bytes`` (the server's frame limit),
    ``n_obs`` (what an episode loop reads to pass an observation history), ``server_ms`` (the last reply's
    inference time on the server).
    """

    def __init__(self, uri: str, timeout: float = 30.0, wait: float = 0.0) -> None:
        self._stack = ExitStack()
        deadline = time.monotonic() + wait  # a server still starting (loading its model) is waited for this long
        while True:
            try:
                connection = connect(
                    uri, open_timeout=timeout, close_timeout=timeout, compression=None, proxy=None, max_size=1 << 24
                )
                self._ws = self._stack.enter_context(connection)
                break
            except (OSError, TimeoutError) as e:
                if time.monotonic() >= deadline:
                    waited = f" after waiting {wait:g} s" if wait else ""
                    raise ConnectionError(f"no policy server at {uri}{waited} ({type(e).__name__}: {e})") from None
                time.sleep(0.2)
        self.uri, self.timeout = uri, timeout
        hello = self._receive()
        self.metadata = PolicyMetadata.from_dict(hello["metadata"])
        self.max_message_bytes = int(hello["max_message_bytes"])
        self.n_obs = self.metadata.n_obs
        self.server_ms: float | None = None

    def _receive(self) -> dict:
        try:
            reply = unpack(self._ws.recv(timeout=self.timeout))
        except ConnectionClosed as e:
            raise PolicyServerError(f"the server at {self.uri} closed the connection: {e}") from None
        if isinstance(reply, dict) and "error" in reply:
            raise PolicyServerError(reply["error"])
        return reply

    def request(self, message: dict) -> dict:
        """Send one request (:mod:`kpflow.serving.protocol`) and return its reply; ``PolicyServerError`` for an
        error reply or a closed connection."""
        data = pack(message)
        if len(data) > self.max_message_bytes:
            raise PolicyServerError(
                f"the request is {len(data)} bytes; the server takes at most {self.max_message_bytes}"
            )
        try:
            self._ws.send(data)
        except ConnectionClosed as e:
            raise PolicyServerError(f"the server at {self.uri} closed the connection: {e}") from None
        return self._receive()

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode on the server (``seed``, an integer or None, reseeds the connection's policy).

        Raises ``ValueError`` for any other seed (a bool, a float, a string): it is refused, not truncated."""
        self.request({"reset": {"seed": check_seed({"seed": seed})}})

    def act(self, obs: dict) -> np.ndarray:
        """The server policy's actions ``[execute, A]`` (float64) for ``obs`` (its keys beyond the metadata's ignored)."""
        missing = sorted(set(self.metadata.observation) - set(obs))
        if missing:
            raise ValueError(f"obs lacks {missing}: the server's policy reads {self.metadata.observation}")
        reply = self.request({"obs": {k: np.asarray(obs[k]) for k in self.metadata.observation}})
        self.server_ms = float(reply["server_ms"])
        return np.array(reply["actions"], dtype=np.float64)

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> "PolicyClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
