"""What messages cost on the wire, as models: ZeroMQ's framing, and an ordinary codec over SRTP.

Our call's media travel as sealed UDP datagrams (docs/protocol.md section 8); what they cost
on the wire is counted on a real link, not modelled here (facewire/onlink.py, and
``facewire bandwidth``). A model of that path was tried and dropped, as it did not meet the
count within 3%: the payload ``facewire demo`` counts, each message with its 1-2 length
bytes, in one datagram per two frames with 40 bytes of headers each (IPv4 20, UDP 8, the
datagram's own 12), and back four reception reports a second of 58 bytes each (the 17-byte
report, its length byte, 12, 28). Against a veth link's counts (``facewire bandwidth``'s
window, 2026-11): back it was 6-8% over on every clip (the receiver reports on its first
frame at least 250 ms after the last report: 3.75 a second at 30 fps, not 4); forward 0.7%
under on claire_qcif, 3.5% over on carphone_qcif and 10% over on the bundled clip (fewer
datagrams than one per two frames: two frames with no update send none; and what the demo
sends over a clip is not what a window of the same clip looping sends).

What ZeroMQ still carries (joining, the snapshot, the back channel, and the media when no
datagram gets through), and how its framing adds up, exactly:

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

An ordinary codec in a call (WebRTC) goes over SRTP, a model: each encoded frame in RTP
packets of at most 1200 bytes of payload, each with 50 bytes of headers (IPv4 20, UDP 8,
RTP 12, SRTP authentication tag 10); payload descriptors, header extensions and RTCP are not
counted (a lower bound).
"""

from __future__ import annotations

import logging
import math

logger = logging.getLogger(__name__)

ZMTP_SHORT_BODY = 255
ZMTP_SHORT_HEADER = 2
ZMTP_LONG_HEADER = 9
ZMTP_GREETING = 64
CURVE_MESSAGE_OVERHEAD = 1 + len(b"MESSAGE") + 8 + 16 + 1
CURVE_HELLO_BODY = 200
CURVE_WELCOME_BODY = 168
CURVE_INITIATE_BODY = 257  # plus metadata
CURVE_READY_BODY = 30  # plus metadata
NULL_READY_BODY = 1 + len(b"READY")  # plus metadata
SUBSCRIBE_BODY = 1 + len(b"SUBSCRIBE")  # the empty topic: every message

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


def rtp_bytes(frame_bytes: int) -> int:
    """IP packet bytes of one encoded frame sent over SRTP (see the module doc)."""
    packets = max(1, math.ceil(frame_bytes / RTP_MAX_PAYLOAD))
    return frame_bytes + packets * RTP_HEADERS
