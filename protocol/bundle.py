"""What one media datagram carries: a bundle of elements (docs/protocol.md, section 7.2).

A bundle is a run of elements, each a length (an unsigned LEB128 varint) and that many bytes.
An element's first byte says what it is:

- ``0x2K``: a version-2 packet as it travels on ZeroMQ (a KeyFrame, a DeltaFrame, a RemPatch, a
  Refresh, an AudioFrame, a Heartbeat, a Bye): whatever is due goes in one datagram;
- ``0x31`` :class:`Fragment`: a slice of a version-2 packet too large for the datagram it
  would have gone in (a REM patch paid for a little at a time);
- ``0x32`` :class:`Report`: the receiver's reception report, which the sender's rate control
  reads (protocol/congestion.py);
- ``0x33`` (:data:`HURRY`, the byte alone): the sender asks for reports at the faster beat for
  a while (its rate control has something to follow: a queue, loss, a cut, the call's start).

An empty bundle is valid: it opens the path or keeps it open.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from facewire.protocol.packets import PacketError

FRAGMENT = 0x31
REPORT = 0x32
HURRY = 0x33
#: Largest datagram either end sends (QUIC's smallest allowed path MTU, RFC 9000 14): no IP
#: fragmentation on any real path.
MAX_DATAGRAM = 1200
#: Most packets being reassembled at once, and the largest one (bounded memory under attack).
MAX_PARTIAL = 8
MAX_REASSEMBLED = 65535

_FRAGMENT = struct.Struct(">BBHH")  # kind, message id, total length, offset
_REPORT = struct.Struct(">BIIII")  # kind, highest index, its arrival, received, bytes


class BundleError(PacketError):
    """A bundle or one of its elements is malformed."""


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def pack(elements: Iterable[bytes]) -> bytes:
    """One bundle of ``elements`` (each non-empty)."""
    out = bytearray()
    for element in elements:
        if not element:
            raise ValueError("an element is at least its kind byte")
        out += varint(len(element))
        out += element
    return bytes(out)


def element_size(element_len: int) -> int:
    """Bytes an element of ``element_len`` takes in a bundle."""
    return len(varint(element_len)) + element_len


def unpack(bundle: bytes) -> Iterator[bytes]:
    """The elements of ``bundle``; BundleError if a length runs past its end."""
    at, n = 0, len(bundle)
    while at < n:
        length = shift = 0
        while True:
            if at >= n:
                raise BundleError("bundle ends inside an element's length")
            byte = bundle[at]
            at += 1
            length |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
            if shift >= 21:
                raise BundleError("element length longer than 3 bytes")
        if length == 0:
            raise BundleError("empty element")
        if at + length > n:
            raise BundleError(f"element of {length} bytes runs {at + length - n} past the bundle")
        yield bundle[at : at + length]
        at += length


@dataclass(frozen=True)
class Fragment:
    """``data`` is bytes ``offset`` .. of message ``message`` (``total`` bytes in all)."""

    message: int
    total: int
    offset: int
    data: bytes

    def __bytes__(self) -> bytes:
        return _FRAGMENT.pack(FRAGMENT, self.message, self.total, self.offset) + self.data

    @classmethod
    def parse(cls, element: bytes) -> Fragment:
        if len(element) <= _FRAGMENT.size:
            raise BundleError(f"{len(element)}-byte fragment has no data")
        _, message, total, offset = _FRAGMENT.unpack_from(element)
        data = element[_FRAGMENT.size :]
        if offset + len(data) > total:
            raise BundleError(f"fragment ends at {offset + len(data)}, past its total {total}")
        return cls(message, total, offset, data)


FRAGMENT_HEADER = _FRAGMENT.size


@dataclass(frozen=True)
class Report:
    """The receiver's reception so far (every count wraps at 2^32).

    ``highest``: the highest datagram index received (low 32 bits); ``arrival_ms``: when it came,
    on the receiver's clock; ``received`` and ``received_bytes``: datagrams and their bytes
    (UDP payload) received since the path opened.
    """

    highest: int
    arrival_ms: int
    received: int
    received_bytes: int

    def __bytes__(self) -> bytes:
        m = 0xFFFFFFFF
        return _REPORT.pack(
            REPORT, self.highest & m, self.arrival_ms & m, self.received & m,
            self.received_bytes & m,
        )  # fmt: skip

    @classmethod
    def parse(cls, element: bytes) -> Report:
        if len(element) != _REPORT.size:
            raise BundleError(f"report of {len(element)} bytes, expected {_REPORT.size}")
        _, highest, arrival, received, nbytes = _REPORT.unpack(element)
        return cls(highest, arrival, received, nbytes)


@dataclass
class _Partial:
    total: int
    parts: dict[int, bytes]  # offset -> data
    size: int = 0


class Reassembly:
    """Puts fragmented packets back together, their fragments in any order (a link's jitter
    reorders datagrams sent together: a snapshot's draft goes as three at once); what cannot
    be finished is given up.

    At most MAX_PARTIAL messages are held at once: the oldest goes when another starts (a
    message missing a fragment is given up so; one that crosses slowly, the full snapshot
    paced behind the media, is held while the patches around it finish). A fragment whose
    ``total`` is not its message's is another message of that number: the one held is given
    up. A second copy of a fragment changes nothing.
    """

    def __init__(self) -> None:
        self._partial: dict[int, _Partial] = {}
        self.lost = 0  # messages given up

    def add(self, fragment: Fragment) -> bytes | None:
        """The whole packet when ``fragment`` completes it, else None."""
        message = fragment.message
        held = self._partial.get(message)
        if held is not None and held.total != fragment.total:
            del self._partial[message]
            self.lost += 1
            held = None
        if held is None:
            held = self._partial[message] = _Partial(fragment.total, {})
            while len(self._partial) > MAX_PARTIAL:
                del self._partial[next(iter(self._partial))]
                self.lost += 1
        if fragment.offset in held.parts:
            return None
        held.parts[fragment.offset] = fragment.data
        held.size += len(fragment.data)
        if held.size < held.total:
            return None
        del self._partial[message]
        whole = bytearray()
        for offset in sorted(held.parts):
            if offset != len(whole):  # overlapping fragments: not a sender's cut
                self.lost += 1
                return None
            whole += held.parts[offset]
        return bytes(whole)
