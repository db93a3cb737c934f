"""What messages cost on the wire: our call over ZeroMQ and TCP/IP, a codec over RTP.

Our call (ZeroMQ over TCP, the demo encrypted with CURVE):

- ZMTP 3.1 frame: a flags byte and a 1-byte size when the frame body is at most 255 bytes,
  else an 8-byte size. Every facewire message is a single frame.
- CURVE (RFC 26, CurveZMQ) turns each message into a MESSAGE command: its name (1 + 7
  bytes), an 8-byte short nonce and a box of 16 bytes of MAC, a flags byte and the payload:
  33 bytes more than the payload.
- Connection set-up, per connection (the receiver's SUB to the sender's PUB, its DEALER to
  the sender's ROUTER): the 64-byte greeting each way; with CURVE, HELLO (200-byte body),
  WELCOME (168), INITIATE (257 plus the client's metadata) and READY (30 plus the
  server's), with NULL only READY (6 plus metadata) each way; the SUB's subscription (a
  10-byte SUBSCRIBE command). Metadata is Socket-Type, plus an empty Identity for DEALER
  and ROUTER. All of this is exact: tests/test_wire.py counts the bytes of a real call's
  TCP streams through a relay and finds these figures to the byte.
- TCP/IP, a model: 52 bytes of headers per segment (IPv4 20, TCP 20, timestamps option 12),
  segments of at most 1448 bytes (an Ethernet MTU of 1500), each message in segments of its
  own, and one pure ACK (52 bytes) back for each data segment. Both are upper bounds:
  libzmq writes messages queued together in one segment, and Linux's delayed ACK may
  acknowledge two segments at once (on a call paced at 30 frames a second it acknowledges
  each: measured on loopback through TCP_INFO). A connection opens with SYN and SYN-ACK (60
  bytes each, with options) and an ACK, and closes with a FIN and an ACK each way. Link
  framing (Ethernet: 38 bytes a packet with preamble and gap) is not counted.

An ordinary codec in a call (WebRTC) goes over SRTP: each encoded frame in RTP packets of
at most 1200 bytes of payload, each with 50 bytes of headers (IPv4 20, UDP 8, RTP 12, SRTP
authentication tag 10); payload descriptors, header extensions and RTCP are not counted (a
lower bound).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

logger = logging.getLogger(__name__)

ZMTP_SHORT_BODY = 255
ZMTP_SHORT_HEADER = 2
ZMTP_LONG_HEADER = 9
ZMTP_GREETING = 64
ZMTP_SIGNATURE = 10
CURVE_MESSAGE_OVERHEAD = 1 + len(b"MESSAGE") + 8 + 16 + 1
CURVE_HELLO_BODY = 200
CURVE_WELCOME_BODY = 168
CURVE_INITIATE_BODY = 257  # plus metadata
CURVE_READY_BODY = 30  # plus metadata
NULL_READY_BODY = 1 + len(b"READY")  # plus metadata
SUBSCRIBE_BODY = 1 + len(b"SUBSCRIBE")  # the empty topic: every message

IP_TCP_HEADERS = 20 + 20 + 12
TCP_MSS = 1500 - 20 - 20 - 12
TCP_SYN = IP_TCP_HEADERS + 8  # MSS, SACK-permitted, window scale (and padding) beside timestamps

RTP_HEADERS = 20 + 8 + 12 + 10
RTP_MAX_PAYLOAD = 1200

#: The two connections of a call, (client socket, server socket): the receiver connects.
CALL_CONNECTIONS = (("SUB", "PUB"), ("DEALER", "ROUTER"))


def zmtp_frame(body: int) -> int:
    """Bytes of a ZMTP frame with a ``body``-byte body."""
    return body + (ZMTP_SHORT_HEADER if body <= ZMTP_SHORT_BODY else ZMTP_LONG_HEADER)


def zmtp_message(payload: int, curve: bool) -> int:
    """Bytes on the TCP stream for one single-frame message of ``payload`` bytes."""
    return zmtp_frame(payload + (CURVE_MESSAGE_OVERHEAD if curve else 0))


def _metadata(socket_type: str) -> int:
    def prop(name: str, value: str) -> int:
        return 1 + len(name) + 4 + len(value)

    size = prop("Socket-Type", socket_type)
    if socket_type in ("DEALER", "ROUTER", "REQ", "REP"):
        size += prop("Identity", "")
    return size


def zmtp_handshake(client: str, server: str, curve: bool) -> tuple[int, int]:
    """(client -> server, server -> client) stream bytes of a connection's ZMTP handshake,
    the SUB's subscription included."""
    up = down = ZMTP_GREETING
    if curve:
        up += zmtp_frame(CURVE_HELLO_BODY) + zmtp_frame(CURVE_INITIATE_BODY + _metadata(client))
        down += zmtp_frame(CURVE_WELCOME_BODY) + zmtp_frame(CURVE_READY_BODY + _metadata(server))
    else:
        up += zmtp_frame(NULL_READY_BODY + _metadata(client))
        down += zmtp_frame(NULL_READY_BODY + _metadata(server))
    if client == "SUB":
        up += zmtp_message(SUBSCRIBE_BODY, curve)
    return up, down


def segments(stream_bytes: int) -> int:
    """TCP segments that carry one message of ``stream_bytes`` (see the module doc)."""
    return math.ceil(stream_bytes / TCP_MSS)


def tcp_bytes(stream_bytes: int) -> int:
    """IP packet bytes for one message: its segments with their headers, and their ACKs."""
    return stream_bytes + 2 * IP_TCP_HEADERS * segments(stream_bytes)


def tcp_connection() -> int:
    """IP packet bytes to open and close one TCP connection, data aside."""
    return 2 * TCP_SYN + IP_TCP_HEADERS + 4 * IP_TCP_HEADERS


@dataclass(frozen=True)
class WireCost:
    """Bytes of a set of messages: payload, on the ZeroMQ stream, and as IP packets."""

    messages: int = 0
    payload: int = 0
    zmtp: int = 0
    ip: int = 0

    def __add__(self, other: WireCost) -> WireCost:
        return WireCost(
            self.messages + other.messages,
            self.payload + other.payload,
            self.zmtp + other.zmtp,
            self.ip + other.ip,
        )


def message_cost(sizes: Iterable[tuple[int, int]], curve: bool) -> WireCost:
    """The cost of messages given as (payload bytes, how many) pairs."""
    total = WireCost()
    for size, count in sizes:
        stream = zmtp_message(size, curve)
        total += WireCost(count, count * size, count * stream, count * tcp_bytes(stream))
    return total


def setup_cost(curve: bool) -> WireCost:
    """Opening and closing a call's two connections, their ZMTP handshakes included.

    The handshake commands are counted as messages of their own (segments and ACKs each).
    """
    total = WireCost()
    for client, server in CALL_CONNECTIONS:
        up, down = zmtp_handshake(client, server, curve)
        parts = _handshake_parts(client, server, curve)
        ip = sum(tcp_bytes(p) for p in parts) + tcp_connection()
        total += WireCost(0, 0, up + down, ip)
    return total


def _handshake_parts(client: str, server: str, curve: bool) -> list[int]:
    """Stream bytes of each write of a handshake (greetings, commands)."""
    # libzmq sends a greeting in two writes: the 10-byte signature, then the rest.
    parts = [ZMTP_SIGNATURE, ZMTP_GREETING - ZMTP_SIGNATURE] * 2
    if curve:
        parts += [
            zmtp_frame(CURVE_HELLO_BODY),
            zmtp_frame(CURVE_WELCOME_BODY),
            zmtp_frame(CURVE_INITIATE_BODY + _metadata(client)),
            zmtp_frame(CURVE_READY_BODY + _metadata(server)),
        ]
    else:
        parts += [
            zmtp_frame(NULL_READY_BODY + _metadata(client)),
            zmtp_frame(NULL_READY_BODY + _metadata(server)),
        ]
    if client == "SUB":
        parts.append(zmtp_message(SUBSCRIBE_BODY, curve))
    return parts


def channel_costs(
    messages: Mapping[str, Mapping[str, Iterable[tuple[int, int]]]], curve: bool
) -> dict[str, WireCost]:
    """Per channel, the cost of a call's messages in both directions.

    messages : {direction: {channel: [(payload bytes, how many), ...]}}, as ``facewire
    demo``'s stats file holds them under ``messages``.
    """
    out: dict[str, WireCost] = {}
    for by_channel in messages.values():
        for channel, sizes in by_channel.items():
            pairs = [(int(s), int(n)) for s, n in sizes]
            out[channel] = out.get(channel, WireCost()) + message_cost(pairs, curve)
    return out


def rtp_bytes(frame_bytes: int) -> int:
    """IP packet bytes of one encoded frame sent over SRTP (see the module doc)."""
    packets = max(1, math.ceil(frame_bytes / RTP_MAX_PAYLOAD))
    return frame_bytes + packets * RTP_HEADERS
