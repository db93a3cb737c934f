"""A room participant's connection to the relay: nats-py's asyncio client in a thread of its
own, so the sender's and the receiver's loops (plain threads, like a two-party call's) publish
and read without an event loop of their own.

What arrives is handed to ``on_message(subject, data, arrival_us)`` on the link's thread; it
must only queue it. The snapshot bucket is JetStream KV, in memory (a snapshot is state of a
live call, not worth a disk).
"""

from __future__ import annotations

import asyncio
import logging
import random
import ssl
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from typing import Any
from urllib.parse import urlsplit

from facewire.protocol import subjects
from facewire.protocol.clock import now_us

logger = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 5.0
CALL_TIMEOUT_S = 5.0
#: A snapshot read holds the receiving loop up: no longer than this (it is tried again).
SNAPSHOT_TIMEOUT_S = 1.0
#: Reconnect quickly to another node of the cluster when the one in use dies.
RECONNECT_WAIT_S = 0.25
#: A node that dies with its process closes the connection, noticed at once; one that stops
#: answering (a machine gone, a network cut, a process hung) is noticed by PINGs going
#: unanswered: one every PING_S, the connection given up when the third is due with two still
#: unanswered, 1.0-1.5 s after the node's last word (12 bytes a PING and its PONG, 2 a second).
PING_S = 0.5
MAX_UNANSWERED_PINGS = 2
#: A cluster that has just started elects JetStream's leader before a bucket can be made, and
#: one that lost the node leading the bucket elects another (4.2-4.6 s on loopback) before a
#: write goes through: a write is tried again for this long, ...
BUCKET_WAIT_S = 10.0
#: ... each time waiting this long for the bucket's answer (it is a few ms when it comes).
BUCKET_ATTEMPT_S = 1.0
MAX_RECONNECT_ATTEMPTS = 120  # 30 s of trying, then the call ends


class _QuietTLSClose(logging.Filter):
    """asyncio warns of nats-py's protocol when a TLS connection is refused; the refusal is
    said in one line of our own."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "eof_received() has no effect when using ssl" not in record.getMessage()


logging.getLogger("asyncio").addFilter(_QuietTLSClose())


class RelayUnreachable(RuntimeError):
    """No relay answered (the message says which and why, in one line)."""


def _hidden(url: str) -> str:
    """``url`` without its token (for messages)."""
    scheme, _, rest = url.partition("://")
    return f"{scheme}://{rest.rpartition('@')[2]}" if rest else url


def _pool(servers: list[str]) -> tuple[list[str], str | None]:
    """``servers`` in a random order (participants spread over a cluster's nodes) and, when
    they all carry one token, the URLs without it and the token: nats-py gives it to every
    node then, also to those the cluster tells of (their URLs have no token; with it in the
    URLs they were tried and refused, an attempt each, when a node died)."""
    order = random.sample(servers, len(servers))
    parts = [urlsplit(s) for s in servers]
    tokens = {p.username for p in parts}
    if len(tokens) != 1 or None in tokens or any(p.password or not p.scheme for p in parts):
        return order, None
    return [_hidden(s) for s in order], tokens.pop()


class RoomLink:
    def __init__(
        self,
        servers: list[str],
        room: str,
        name: str,
        on_message: Callable[[str, bytes, int], None],
        notify: Callable[[str], None],
        tls: ssl.SSLContext | None = None,
        on_reconnected: Callable[[], None] = lambda: None,
    ) -> None:
        self.servers = servers
        self.tls = tls  # None: the system's CAs, when a relay asks for TLS
        self.room = room
        self.name = name
        self.on_message = on_message
        self.notify = notify
        #: Called on the link's thread once it is connected again (to another node).
        self.on_reconnected = on_reconnected
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="nats", daemon=True)
        self._nc: Any = None
        self._kv: Any = None
        self.reconnects = 0
        self._closing = False
        #: The connection closed for good (no node answered for MAX_RECONNECT_ATTEMPTS).
        self.lost = False
        self.published = 0
        self.published_bytes = 0

    # --- on the caller's thread ------------------------------------------------------------

    def start(self) -> None:
        """Connect, open the room's bucket and subscribe; RelayUnreachable when it cannot."""
        self._thread.start()
        try:
            self._call(self._start(), CONNECT_TIMEOUT_S + BUCKET_WAIT_S + CALL_TIMEOUT_S)
        except RelayUnreachable:
            self.close()
            raise
        except Exception as exc:  # nats-py's errors name no server: say which
            self.close()
            where = ", ".join(_hidden(s) for s in self.servers)
            why = str(exc) or type(exc).__name__
            raise RelayUnreachable(f"cannot join through {where}: {why}") from None

    def _call(self, coroutine: Any, timeout: float = CALL_TIMEOUT_S) -> Any:
        future: Future[Any] = asyncio.run_coroutine_threadsafe(coroutine, self._loop)
        return future.result(timeout)

    def publish(self, subject: str, data: bytes) -> None:
        """Queue ``data`` for ``subject`` (never blocks: a bundle must not wait for the net)."""
        self.published += 1
        self.published_bytes += len(data)
        self._loop.call_soon_threadsafe(self._publish, subject, data)

    def put_snapshot(self, data: bytes) -> None:
        self.put_entry(self.name, data)

    def put_entry(self, key: str, data: bytes) -> None:
        """Put ``data`` in the room's bucket under ``key`` (a snapshot, a sealed key box)."""
        self._call(self._write(self._kv.put, key, data), BUCKET_WAIT_S + CALL_TIMEOUT_S)

    def get_snapshot(self, name: str) -> bytes | None:
        """``name``'s sealed snapshot; None when the bucket has none, or cannot say now (a
        cluster electing the bucket's leader after a node died, a reconnection)."""
        return self.get_entry(name)

    def get_entry(self, key: str) -> bytes | None:
        """The room's bucket's entry ``key``; None as for :meth:`get_snapshot`."""
        try:
            return self._call(self._get(key), SNAPSHOT_TIMEOUT_S)
        except Exception as exc:
            logger.info("the bucket's %s: %s", key, str(exc) or type(exc).__name__)
            return None

    def delete_snapshot(self) -> None:
        self._call(self._write(self._kv.delete, self.name), BUCKET_WAIT_S + CALL_TIMEOUT_S)

    @property
    def connected_url(self) -> str | None:
        nc = self._nc
        if nc is None or nc.connected_url is None:
            return None
        url = nc.connected_url
        return f"{url.scheme or 'nats'}://{url.hostname}:{url.port}"

    def close(self) -> None:
        self._closing = True
        if self._thread.is_alive():
            try:
                self._call(self._close(), CALL_TIMEOUT_S)
            except Exception as exc:  # leaving anyway
                logger.info("closing the NATS connection: %s", exc)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(CALL_TIMEOUT_S)
        if not self._loop.is_running():
            self._loop.close()

    # --- on the link's thread --------------------------------------------------------------

    async def _start(self) -> None:
        import nats

        failures: list[str] = []

        async def error(exc: Exception) -> None:
            failures.append(str(exc) or type(exc).__name__)
            logger.info("nats: %s", exc)

        async def disconnected() -> None:
            if not self._closing:
                self.notify("lost the relay; reconnecting")

        async def closed() -> None:
            if not self._closing:
                self.lost = True

        async def reconnected() -> None:
            self.reconnects += 1
            self.notify(f"reconnected to the relay at {self.connected_url}")
            self.on_reconnected()

        servers, token = _pool(self.servers)
        try:
            # nats-py retries a first connection as it would a lost one: bound it.
            self._nc = await asyncio.wait_for(
                nats.connect(
                    servers,
                    token=token,
                    # In our order: the node just lost is the last one tried again (one that
                    # stopped answering takes connect_timeout to refuse).
                    dont_randomize=True,
                    name=f"facewire {self.room}/{self.name}",
                    connect_timeout=2,
                    allow_reconnect=True,
                    reconnect_time_wait=RECONNECT_WAIT_S,
                    max_reconnect_attempts=MAX_RECONNECT_ATTEMPTS,
                    ping_interval=PING_S,  # type: ignore[arg-type]  # nats-py sleeps it: a float
                    max_outstanding_pings=MAX_UNANSWERED_PINGS,
                    no_echo=True,  # our own bundles do not come back to us
                    tls=self.tls,
                    error_cb=error,
                    disconnected_cb=disconnected,
                    reconnected_cb=reconnected,
                    closed_cb=closed,
                ),
                CONNECT_TIMEOUT_S,
            )
        except Exception as exc:
            where = ", ".join(_hidden(s) for s in self.servers)
            why = failures[-1] if failures else (str(exc) or type(exc).__name__)
            if "CERTIFICATE_VERIFY_FAILED" in why:
                why += " (--tls-ca FILE: the relay's certificate, or the CA that signed it)"
            raise RelayUnreachable(f"cannot reach the relay at {where}: {why}") from None
        self._kv = await self._bucket()
        await self._nc.subscribe(subjects.media(self.room), cb=self._deliver)
        await self._nc.subscribe(subjects.control(self.room, self.name), cb=self._deliver)
        await self._nc.flush()

    async def _bucket(self) -> Any:
        """The room's KV bucket, made by whoever comes first: three replicas on a cluster of
        three or more nodes (the snapshots outlive a node), else one."""
        from nats.errors import TimeoutError as NatsTimeout
        from nats.js.api import KeyValueConfig, StorageType
        from nats.js.errors import BadRequestError, BucketNotFoundError, ServiceUnavailableError

        js = self._nc.jetstream(timeout=BUCKET_ATTEMPT_S)
        nodes = {(u.hostname, u.port) for u in self._nc.servers}
        config = KeyValueConfig(
            bucket=subjects.bucket(self.room),
            storage=StorageType.MEMORY,
            history=1,
            replicas=3 if len(nodes) >= 3 else 1,
        )
        deadline = asyncio.get_running_loop().time() + BUCKET_WAIT_S
        while True:
            try:
                try:
                    return await js.create_key_value(config)
                except BadRequestError:  # made already, by someone who saw the cluster otherwise
                    return await js.key_value(config.bucket)
            # A new cluster still electing its meta leader answers late, or not at all, or
            # refuses a stream that its peers are still making: all pass within seconds.
            except (ServiceUnavailableError, NatsTimeout, BucketNotFoundError):
                if asyncio.get_running_loop().time() > deadline:
                    raise
                await asyncio.sleep(0.25)

    async def _write(self, write: Callable[..., Awaitable[Any]], *args: Any) -> None:
        """``write(*args)`` to the bucket, again while the cluster has no leader for it (a
        node died; the others elect one) for up to BUCKET_WAIT_S."""
        from nats.errors import TimeoutError as NatsTimeout
        from nats.js.errors import NoStreamResponseError, ServiceUnavailableError

        deadline = asyncio.get_running_loop().time() + BUCKET_WAIT_S
        while True:
            try:
                await write(*args)
                return
            except (NatsTimeout, NoStreamResponseError, ServiceUnavailableError) as exc:
                if asyncio.get_running_loop().time() > deadline:
                    raise
                logger.info("the bucket did not answer (%s): again", type(exc).__name__)
                await asyncio.sleep(0.1)

    async def _deliver(self, msg: Any) -> None:
        self.on_message(msg.subject, msg.data, now_us())

    def _publish(self, subject: str, data: bytes) -> None:
        if self._nc is not None and not self._nc.is_closed:
            asyncio.ensure_future(self._nc.publish(subject, data))

    async def _get(self, name: str) -> bytes | None:
        from nats.js.errors import KeyNotFoundError

        try:
            entry = await self._kv.get(name)
        except KeyNotFoundError:  # also a deleted key
            return None
        return bytes(entry.value) if entry.value else None

    async def _close(self) -> None:
        if self._nc is not None and not self._nc.is_closed:
            await self._nc.drain()
