"""A websocket policy server (:mod:`kpflow.serving.protocol` over :mod:`kpflow.serving.wire`).

Each connection gets the metadata, then its own policy from the deployment; its requests are answered in order, the
policy's ``act`` running in a worker thread (up to :data:`WORKERS` at once) so that other connections are served
meanwhile. A deployment loaded with ``max_batch > 1`` runs the network calls of the requests in flight together
(:mod:`kpflow.serving.batching`); each reply's ``server_ms`` still times its own request. A request that is not
well formed gets an error reply and the connection goes on, a frame larger than ``max_message_bytes`` included; one
larger than :data:`HARD_LIMIT` times that is refused by the websocket layer before it is read (close code 1009,
"message too big"), which ends that connection only. Actions that are not finite are never sent: the reply is an
error naming the cause (:func:`~kpflow.policies.checks.check_actions`). Shutting down (SIGINT,
SIGTERM, or leaving :meth:`PolicyServer.running`) stops accepting connections, lets the requests in flight finish
and closes every connection with code 1001 ("going away").
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator

from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from ..policies.checks import check_actions
from ..utils.config_checks import Key
from .deployment import Deployment
from .protocol import check_observation, check_request, check_seed
from .wire import WireError, pack, unpack

log = logging.getLogger(__name__)
MAX_MESSAGE_BYTES = 1 << 20
HARD_LIMIT = 8  # frames up to this many times max_message_bytes are read and answered with an error
WORKERS = 32  # requests whose act runs at once (asyncio's default executor would allow only cpu_count + 4)


def check_address(host: str, port: int) -> None:
    """Raise ``ValueError`` naming ``host`` and ``port`` unless the server could listen there: the host must resolve
    and the port bind (tried on every address the host resolves to, as the server binds, then closed again)."""
    Key(int, lo=0, hi=65535).check("port", port)
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as e:
        raise ValueError(f"cannot serve on {host}:{port}: the host {host!r} does not resolve ({e})") from None
    for family, kind, proto, _, address in addresses:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(
                socket.SOL_SOCKET, socket.SO_REUSEADDR, 1
            )  # as asyncio's server does, and IPv6 only on IPv6
            if family == socket.AF_INET6:
                probe.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                probe.bind(address)
            except OSError as e:
                raise ValueError(
                    f"cannot serve on {host}:{port}: binding {address[0]} port {port} failed ({e.strerror or e})"
                ) from None


class PolicyServer:
    """Serve ``deployment`` on ``ws://host:port`` (``port=0``: any free port; :attr:`port` tells which).

    After start, ``port`` is the port it listens on.
    """

    def __init__(
        self,
        deployment: Deployment,
        host: str = "127.0.0.1",
        port: int = 8000,
        max_message_bytes: int = MAX_MESSAGE_BYTES,
    ) -> None:
        if not 0 <= int(port) < 65536:
            raise ValueError(f"port must be in 0..65535, got {port}")
        if int(max_message_bytes) < 1024:
            raise ValueError(f"max_message_bytes must be at least 1024, got {max_message_bytes}")
        self.deployment, self.host, self.port = deployment, host, int(port)
        self.max_message_bytes = int(max_message_bytes)
        self.metadata = deployment.metadata
        self._in_flight = 0
        self._idle: asyncio.Condition | None = None
        self._stop: asyncio.Event | None = None

    async def _answer(self, policy, message) -> dict:
        """The reply to one message (an error reply for anything malformed; the policy's own errors too)."""
        try:
            if len(message) > self.max_message_bytes:
                raise ValueError(
                    f"the message is {len(message)} bytes; this server takes at most {self.max_message_bytes}"
                )
            kind, body = check_request(unpack(message))
            if kind == "reset":
                seed = check_seed(body)
                policy.reset(seed)
                return {"reset": seed}
            obs = check_observation(body, self.metadata.observation)
            start = time.perf_counter()
            actions = await self._loop.run_in_executor(self._executor, policy.act, obs)
            return {
                "actions": check_actions(actions, f"the served policy ({self.metadata.policy})"),
                "server_ms": 1e3 * (time.perf_counter() - start),
            }
        except (WireError, ValueError) as e:
            return {"error": str(e)}
        except Exception as e:  # the policy failed on a well-formed request: say so, keep serving
            log.exception("the policy failed")
            return {"error": f"the policy failed ({type(e).__name__}: {e})"}

    async def _handle(self, ws: ServerConnection) -> None:
        peer = ws.remote_address
        if self._stop.is_set():
            await ws.close(1001, "the server is shutting down")
            return
        log.info("connection from %s", peer)
        policy = self.deployment.make_policy()
        await ws.send(pack({"metadata": self.metadata.to_dict(), "max_message_bytes": self.max_message_bytes}))
        try:
            async for message in ws:
                if self._stop.is_set():  # shutting down: this connection is closed with 1001 once the rest finish
                    await ws.send(pack({"error": "the server is shutting down"}))
                    continue
                async with self._idle:
                    self._in_flight += 1
                try:
                    await ws.send(pack(await self._answer(policy, message)))
                finally:
                    async with self._idle:
                        self._in_flight -= 1
                        self._idle.notify_all()
        except ConnectionClosed as e:
            log.info("connection from %s closed: %s", peer, e)

    async def serve(self, on_start: Callable[[], None] | None = None) -> None:
        """Serve until :meth:`stop` (or SIGINT/SIGTERM when run by :meth:`run`), then shut down gracefully;
        ``on_start`` is called once the port is bound."""
        self._loop = asyncio.get_running_loop()
        self._idle, self._stop = asyncio.Condition(), asyncio.Event()
        with ThreadPoolExecutor(WORKERS, thread_name_prefix="kpflow-policy") as self._executor:
            await self._serve(on_start)
        if self.deployment.network is not None:
            stats = self.deployment.network.stats()
            log.info(
                "batching: %d network calls in %d forward passes (%.2f rows each)",
                stats["calls"],
                stats["passes"],
                stats["mean_batch"],
            )

    async def _serve(self, on_start: Callable[[], None] | None) -> None:
        async with serve(
            self._handle, self.host, self.port, max_size=HARD_LIMIT * self.max_message_bytes, compression=None
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            log.info("serving %s on ws://%s:%d", self.metadata.policy, self.host, self.port)
            if on_start is not None:
                on_start()
            await self._stop.wait()
            async with self._idle:  # new connections are turned away meanwhile (_handle)
                await self._idle.wait_for(lambda: self._in_flight == 0)  # the requests in flight finish
            server.close(close_connections=True)  # then every connection is told "going away" (1001)
            await server.wait_closed()

    def stop(self) -> None:
        """Ask a serving server to shut down (thread-safe)."""
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    def run(self) -> None:
        """Serve in this thread until SIGINT or SIGTERM."""

        async def main() -> None:
            loop = asyncio.get_running_loop()

            def on_start() -> None:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    loop.add_signal_handler(sig, self._stop.set)

            await self.serve(on_start)

        asyncio.run(main())

    @contextmanager
    def running(self, timeout: float = 30.0) -> Iterator[str]:
        """Serve from a background thread; yields the server's ``ws://`` address and shuts down on exit."""
        started = threading.Event()
        failure: list[BaseException] = []

        def target() -> None:
            try:
                asyncio.run(self.serve(started.set))
            except BaseException as e:  # e.g. the port is taken: re-raised in the caller's thread
                failure.append(e)
                started.set()

        thread = threading.Thread(target=target, name="kpflow-policy-server", daemon=True)
        thread.start()
        started.wait(timeout)
        if failure:
            raise failure[0]
        try:
            yield f"ws://{self.host}:{self.port}"
        finally:
            self.stop()
            thread.join(timeout)
