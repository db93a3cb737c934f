"""ZeroMQ's framing (facewire/wire.py) against a real call's TCP streams, counted byte by byte
through a relay: joining, the media key, the snapshot and the back channel go this way, and
the media too while no datagram gets through (here none can: the relay carries TCP only)."""

from __future__ import annotations

import selectors
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from transport_helpers import TIMEOUT_MS, frame, join, keypairs, snapshot

from facewire import wire
from facewire.protocol.packets import KeyFrame, MediaKey
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint


class CountingRelay:
    """A TCP relay on loopback for one connection: counts the stream bytes each way."""

    def __init__(self, target_port: int) -> None:
        self._target = target_port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self.up = 0  # client -> server (the receiver is the client)
        self.down = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def counts(self) -> tuple[int, int]:
        with self._lock:
            return self.up, self.down

    def _run(self) -> None:
        self._listener.settimeout(TIMEOUT_MS / 1000)
        try:
            client, _ = self._listener.accept()
        except OSError:
            return
        server = socket.create_connection(("127.0.0.1", self._target))
        sel = selectors.DefaultSelector()
        sel.register(client, selectors.EVENT_READ, server)
        sel.register(server, selectors.EVENT_READ, client)
        with client, server, sel:
            while not self._stop.is_set():
                for key, _ in sel.select(0.05):
                    src, dst = key.fileobj, key.data
                    assert isinstance(src, socket.socket)
                    try:
                        data = src.recv(65536)
                    except OSError:
                        data = b""
                    if not data:
                        return
                    with self._lock:
                        if src is client:
                            self.up += len(data)
                        else:
                            self.down += len(data)
                    dst.sendall(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._listener.close()


def _wait_for(relay: CountingRelay, up: int, down: int) -> None:
    """Until the relay has passed at least these counts (the bytes are in flight)."""
    event = threading.Event()
    for _ in range(TIMEOUT_MS // 10):
        if relay.counts()[0] >= up and relay.counts()[1] >= down:
            return
        event.wait(0.01)


@pytest.fixture(params=["curve", "plain"])
def call(
    request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[tuple[SenderEndpoint, ReceiverEndpoint, CountingRelay, CountingRelay, bool]]:
    curve = request.param == "curve"
    keys = keypairs(tmp_path, "sender", "receiver")
    s_kw: dict[str, Any]
    r_kw: dict[str, Any]
    if curve:
        s_kw = {"secret_key_file": keys["sender"][1], "allowed_keys": [keys["receiver"][0]]}
        r_kw = {"secret_key_file": keys["receiver"][1], "server_key_file": keys["sender"][0]}
    else:
        s_kw = r_kw = {"plain": True}
    with SenderEndpoint("127.0.0.1", **s_kw) as sender:
        sender.set_snapshot(snapshot())
        pub, back = CountingRelay(sender.ports[0]), CountingRelay(sender.ports[1])
        try:
            with ReceiverEndpoint("127.0.0.1", pub.port, back.port, **r_kw) as receiver:
                yield sender, receiver, pub, back, curve
        finally:
            pub.close()
            back.close()


def test_zmtp_stream_bytes_are_the_model_to_the_byte(
    call: tuple[SenderEndpoint, ReceiverEndpoint, CountingRelay, CountingRelay, bool],
) -> None:
    sender, receiver, pub, back, curve = call
    join(sender, receiver)
    # Sizes either side of the short-frame limit (a 255-byte body) with and without CURVE.
    bodies = [1, 180, 204, 205, 206, 212, 213, 240, 1000, 5000]
    sent = [frame(i + 1, size=n) for i, n in enumerate(bodies)]
    for packet in sent:
        sender.publish(packet)
    got = 0
    while got < len(sent):
        update = receiver.recv(TIMEOUT_MS)
        assert update is not None, "an update did not arrive"
        got += isinstance(update, KeyFrame)
    receiver.send_stats({"fps": 30.0})
    assert any(p.__class__.__name__ == "ReceiverStats" for p in sender.poll(TIMEOUT_MS))
    assert {len(bytes(p)) for p in sent} & {222, 223}, "the test spans the CURVE frame limit"

    # Every payload the endpoints counted, in both directions, priced by the model...
    expected: dict[str, dict[str, int]] = {"up": {}, "down": {}}
    streams = {"PUB": pub, "ROUTER": back}
    for client, server in wire.CALL_CONNECTIONS:
        up, down = wire.zmtp_handshake(client, server, curve)
        expected["up"][server], expected["down"][server] = up, down
    # The media key goes on ROUTER just before the snapshot (the only control message of its
    # size here: the others are heartbeats); it is one byte longer for a key id over 127.
    key_sizes = {len(bytes(MediaKey(key_id, bytes(32), 1))) for key_id in (0, 255)}
    keys = {s: n for s, n in sender.sizes_sent["control"].items() if s in key_sizes}
    assert sum(keys.values()) == 1, sender.sizes_sent["control"]
    for channel, sizes in sender.sizes_sent.items():
        for size, n in sizes.items():
            on_router = channel == "snapshot" or (channel == "control" and size in keys)
            expected["down"]["ROUTER" if on_router else "PUB"] += n * wire.zmtp_message(size, curve)
    for sizes in sender.sizes_received.values():  # the back channel: DEALER -> ROUTER
        expected["up"]["ROUTER"] += sum(n * wire.zmtp_message(s, curve) for s, n in sizes.items())
    # ... is what went through the TCP streams, to the byte. Upstream everything counted was
    # read by the sender, so it has passed the relay; downstream the receiver has what came
    # after the join. One exception: a probe's answer published before the SUB's
    # subscription reached the PUB is counted by the sender and dropped by libzmq.
    for link, relay in streams.items():
        _wait_for(relay, expected["up"][link], expected["down"][link])
    assert back.counts() == (expected["up"]["ROUTER"], expected["down"]["ROUTER"])
    up, down = pub.counts()
    assert up == expected["up"]["PUB"]
    heartbeat = wire.zmtp_message(len(bytes(sender._heartbeat())), curve)
    lost, rest = divmod(expected["down"]["PUB"] - down, heartbeat)
    heartbeats = sum(sender.sizes_sent["control"].values()) - 1
    assert rest == 0 and 0 <= lost < heartbeats, (down, lost)
    # Both ends count the same messages.
    assert receiver.sizes_sent["control"] == sender.sizes_received["control"]
    assert receiver.sizes_received["geometry"] == sender.sizes_sent["geometry"]
    assert receiver.sizes_received["snapshot"] == sender.sizes_sent["snapshot"]
    assert sender.sizes_sent["geometry"][len(bytes(sent[0]))] == 1
    assert sum(sender.sizes_sent["geometry"].values()) == len(sent)


def test_frame_limits_and_costs() -> None:
    assert wire.zmtp_message(253, curve=False) == 255
    assert wire.zmtp_message(254, curve=False) == 256
    assert wire.zmtp_message(256, curve=False) == 265
    # CURVE: 33 bytes more inside, so the short frame ends at a 222-byte payload.
    assert wire.zmtp_message(222, curve=True) == 222 + 33 + 2
    assert wire.zmtp_message(223, curve=True) == 223 + 33 + 9
    # SRTP: 50 bytes of headers per RTP packet, a packet per 1200 bytes of a frame.
    assert wire.rtp_bytes(1000) == 1050 and wire.rtp_bytes(1201) == 1201 + 100
