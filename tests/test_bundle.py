"""Bundles (what a media datagram carries): elements, fragments, reports, reassembly."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facewire.protocol.bundle import (
    FRAGMENT,
    FRAGMENT_HEADER,
    MAX_PARTIAL,
    REPORT,
    BundleError,
    Fragment,
    Reassembly,
    Report,
    element_size,
    pack,
    unpack,
    varint,
)
from facewire.protocol.packets import Heartbeat, PacketError

uint32 = st.integers(0, 2**32 - 1)
elements = st.binary(min_size=1, max_size=300)


def slices(packet: bytes, message: int, sizes: list[int]) -> list[Fragment]:
    """``packet`` cut into fragments of ``sizes`` (cycled), in order."""
    out, at, i = [], 0, 0
    while at < len(packet):
        n = sizes[i % len(sizes)]
        out.append(Fragment(message, len(packet), at, packet[at : at + n]))
        at, i = at + n, i + 1
    return out


# --- elements ----------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.lists(elements, max_size=20))
def test_pack_unpack_round_trip(items: list[bytes]) -> None:
    bundle = pack(items)
    assert list(unpack(bundle)) == items
    assert len(bundle) == sum(element_size(len(e)) for e in items)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=20_000), max_size=3))
def test_pack_unpack_round_trip_long_elements(items: list[bytes]) -> None:
    assert list(unpack(pack(items))) == items


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=200))
def test_unpack_any_bytes_gives_elements_or_bundle_error(data: bytes) -> None:
    try:
        items = list(unpack(data))
    except BundleError:
        return
    assert all(items)
    assert sum(element_size(len(e)) for e in items) <= len(data)


def test_empty_bundle() -> None:
    assert pack([]) == b""
    assert list(unpack(b"")) == []


def test_empty_element_cannot_be_packed() -> None:
    with pytest.raises(ValueError, match=r"^an element is at least its kind byte$"):
        pack([b"\x21", b""])


@pytest.mark.parametrize(
    "n, encoded",
    [
        (1, "01"),
        (127, "7f"),
        (128, "8001"),
        (300, "ac02"),
        (16383, "ff7f"),
        (16384, "808001"),
        (2**21 - 1, "ffff7f"),
    ],
)
def test_varint(n: int, encoded: str) -> None:
    assert varint(n).hex() == encoded
    assert element_size(n) == len(encoded) // 2 + n


@pytest.mark.parametrize("n", [1, 127, 128, 16383, 16384, 20_000])
def test_elements_at_varint_edges(n: int) -> None:
    element = b"\x21" + bytes(n - 1)
    bundle = pack([element, b"\x25"])
    assert len(bundle) == element_size(n) + 2
    assert list(unpack(bundle)) == [element, b"\x25"]


def test_bundle_error_is_a_packet_error() -> None:
    assert issubclass(BundleError, PacketError)


def test_truncated_bundles() -> None:
    bundle = pack([b"\x21" * 10, b"\x22" * 200])  # 0a + 10 bytes, c8 01 + 200 bytes
    with pytest.raises(BundleError, match=r"^element of 10 bytes runs 5 past the bundle$"):
        list(unpack(bundle[:6]))
    with pytest.raises(BundleError, match=r"^bundle ends inside an element's length$"):
        list(unpack(bundle[:12]))  # the second length's first byte only
    with pytest.raises(BundleError, match=r"^element of 200 bytes runs 1 past the bundle$"):
        list(unpack(bundle[:-1]))
    # Elements before the fault are given first (a caller wanting all or nothing lists them).
    items = unpack(bundle[:-1])
    assert next(items) == b"\x21" * 10
    with pytest.raises(BundleError):
        next(items)


def test_over_long_lengths() -> None:
    with pytest.raises(BundleError, match=r"^element of 127 bytes runs 126 past the bundle$"):
        list(unpack(b"\x7f\x21"))
    with pytest.raises(BundleError, match=r"^element of 16383 bytes runs 16382 past the bundle$"):
        list(unpack(b"\xff\x7f\x21"))
    with pytest.raises(BundleError, match=r"^element length longer than 3 bytes$"):
        list(unpack(b"\x80\x80\x80\x80\x01" + b"\x21" * 10))
    with pytest.raises(BundleError, match=r"^element length longer than 3 bytes$"):
        list(unpack(b"\xff" * 1000))


def test_four_byte_length_is_refused() -> None:
    """docs/protocol.md 8.3: a length is 1-3 bytes. BUG (protocol/bundle.py, unpack): the
    check ``shift > 21`` lets a 4th length byte through; it should be ``shift >= 21``."""
    with pytest.raises(BundleError, match=r"^element length longer than 3 bytes$"):
        list(unpack(b"\x80\x80\x80\x01" + b"\x21" * 10))


def test_zero_length_element() -> None:
    with pytest.raises(BundleError, match=r"^empty element$"):
        list(unpack(b"\x01\x21\x00"))
    with pytest.raises(BundleError, match=r"^empty element$"):
        list(unpack(b"\x80\x00"))  # a zero written in two bytes


# --- Fragment ----------------------------------------------------------------------------------


@st.composite
def fragments(draw: st.DrawFn) -> Fragment:
    total = draw(st.integers(1, 65535))
    offset = draw(st.integers(0, total - 1))
    data = draw(st.binary(min_size=1, max_size=min(300, total - offset)))
    return Fragment(draw(st.integers(0, 255)), total, offset, data)


@settings(max_examples=300, deadline=None)
@given(fragments())
def test_fragment_round_trip(fragment: Fragment) -> None:
    element = bytes(fragment)
    assert element[0] == FRAGMENT == 0x31
    assert len(element) == FRAGMENT_HEADER + len(fragment.data)
    assert Fragment.parse(element) == fragment
    assert list(unpack(pack([element]))) == [element]


def test_fragment_bytes() -> None:
    element = bytes(Fragment(0x12, 0x0345, 0x0067, b"ab"))
    assert element.hex(" ") == "31 12 03 45 00 67 61 62"
    assert FRAGMENT_HEADER == 6


def test_bad_fragments() -> None:
    with pytest.raises(BundleError, match=r"^6-byte fragment has no data$"):
        Fragment.parse(bytes(Fragment(1, 10, 0, b"x"))[:6])
    with pytest.raises(BundleError, match=r"^3-byte fragment has no data$"):
        Fragment.parse(b"\x31\x01\x00")
    with pytest.raises(BundleError, match=r"^fragment ends at 11, past its total 10$"):
        Fragment.parse(bytes(Fragment(1, 10, 8, b"xyz")))


# --- Report ------------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(uint32, uint32, uint32, uint32)
def test_report_round_trip(highest: int, arrival: int, received: int, nbytes: int) -> None:
    report = Report(highest, arrival, received, nbytes)
    element = bytes(report)
    assert element[0] == REPORT == 0x32
    assert len(element) == 17
    assert Report.parse(element) == report


def test_report_bytes_and_wrap() -> None:
    assert bytes(Report(0x1234, 123456, 100, 4200)).hex(" ") == (
        "32 00 00 12 34 00 01 e2 40 00 00 00 64 00 00 10 68"
    )
    # Every count wraps at 2^32 (the index is 48 bits, the clock and counts run on).
    wide = Report((5 << 32) + 7, (1 << 32) + 8, (2 << 32) + 9, (3 << 32) + 10)
    assert Report.parse(bytes(wide)) == Report(7, 8, 9, 10)


def test_bad_reports() -> None:
    element = bytes(Report(1, 2, 3, 4))
    with pytest.raises(BundleError, match=r"^report of 16 bytes, expected 17$"):
        Report.parse(element[:-1])
    with pytest.raises(BundleError, match=r"^report of 18 bytes, expected 17$"):
        Report.parse(element + b"\x00")


# --- Reassembly --------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=5000), st.lists(st.integers(1, 1200), min_size=1))
def test_in_order_fragments_give_the_packet_back(packet: bytes, sizes: list[int]) -> None:
    reassembly = Reassembly()
    parts = slices(packet, 9, sizes)
    for part in parts[:-1]:
        assert reassembly.add(Fragment.parse(bytes(part))) is None
    assert reassembly.add(parts[-1]) == packet
    assert reassembly.lost == 0


def test_real_packet_through_fragments() -> None:
    packet = bytes(Heartbeat(3050556106, 42, 1_000_000))
    reassembly = Reassembly()
    assert [reassembly.add(f) for f in slices(packet, 0, [5])] == [None, None, packet]


def test_missing_middle_fragment_gives_the_message_up_once_newer_ones_push_it_out() -> None:
    packet = bytes(range(256)) * 4
    parts = slices(packet, 3, [100])
    reassembly = Reassembly()
    # parts[2] lost
    assert [reassembly.add(p) for p in parts[:2] + parts[3:]] == [None] * (len(parts) - 1)
    assert reassembly.lost == 0  # it may still come: datagrams are reordered
    # Messages that finish as they come take no room: it is still held.
    assert [reassembly.add(p) for p in slices(packet, 4, [700])] == [None, packet]
    assert reassembly.lost == 0
    # MAX_PARTIAL others held at once push it out.
    newer = [slices(packet, m, [700]) for m in range(5, 5 + MAX_PARTIAL)]
    assert [reassembly.add(n[0]) for n in newer] == [None] * MAX_PARTIAL
    assert reassembly.lost == 1
    assert [reassembly.add(n[1]) for n in newer] == [packet] * MAX_PARTIAL


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=5000), st.integers(1, 1200), st.randoms())
def test_fragments_in_any_order_and_twice_give_the_packet_back(
    packet: bytes, size: int, rng: random.Random
) -> None:
    """A link's jitter reorders datagrams sent together (a draft's three at once): in
    order, the reassembly gave the draft up 6 times running on a 40 +- 10 ms link."""
    parts = slices(packet, 7, [size])
    shuffled = parts + parts[: len(parts) // 2]  # some come twice
    rng.shuffle(shuffled)
    reassembly = Reassembly()
    got = [reassembly.add(p) for p in shuffled]
    assert [g for g in got if g is not None] == [packet]
    assert reassembly.lost == 0


def test_missing_first_fragment_gives_nothing() -> None:
    parts = slices(b"abcdefgh", 1, [3])
    reassembly = Reassembly()
    assert reassembly.add(parts[1]) is None
    assert reassembly.add(parts[2]) is None
    assert reassembly.lost == 0  # nothing was held


def test_message_number_taken_again_drops_the_old() -> None:
    old = slices(b"old packet!", 5, [4])
    new = slices(b"new one", 5, [4])
    reassembly = Reassembly()
    assert reassembly.add(old[0]) is None
    assert reassembly.add(old[1]) is None
    assert [reassembly.add(p) for p in new] == [None, b"new one"]
    assert reassembly.lost == 1


def test_at_most_max_partial_held() -> None:
    assert MAX_PARTIAL == 8
    packets = {m: bytes([m]) * 50 for m in range(100)}
    parts = {m: slices(p, m, [20]) for m, p in packets.items()}
    reassembly = Reassembly()
    for m in range(100):
        assert reassembly.add(parts[m][0]) is None
    assert reassembly.lost == 100 - MAX_PARTIAL
    assert len(reassembly._partial) == MAX_PARTIAL
    for m in range(100 - MAX_PARTIAL, 100):  # the newest are still held
        assert [reassembly.add(p) for p in parts[m][1:]] == [None, packets[m]]
    assert reassembly.lost == 100 - MAX_PARTIAL
    assert len(reassembly._partial) == 0
    for m in range(100 - MAX_PARTIAL):  # given up: their rest never makes a packet
        assert [reassembly.add(p) for p in parts[m][1:]] == [None, None]
    assert len(reassembly._partial) == MAX_PARTIAL
