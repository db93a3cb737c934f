"""docs/protocol.md section 5 is complete: a decoder written from it alone matches the code.

The reference decoder below uses only the document's pseudo-code (header byte, KeyFrame and
DeltaFrame layouts, range decoder, integer binarisation, channel coding, counter and chain
rules). It does not import protocol.rangecoder or protocol.channels' decoder; the code under
test only produces the packets and the values to compare with.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from facewire.protocol.channels import ChannelDecoder, ChannelEncoder, ChannelSpec

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"

# --- reference decoder, from docs/protocol.md sections 1, 2 and 5 ------------------------------


class RefError(ValueError):
    """A packet or body the document says to reject."""


class RangeDecoder:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0
        self.range = 0xFFFFFFFF
        self.code = 0
        for _ in range(4):
            self.code = (self.code << 8) | self.next_byte()

    def next_byte(self) -> int:
        b = self.data[self.pos] if self.pos < len(self.data) else 0
        self.pos += 1
        return b

    def decode(self, p0: int) -> int:
        bound = (self.range >> 12) * p0
        if self.code < bound:
            self.range = bound
            bit = 0
        else:
            self.code -= bound
            self.range -= bound
            bit = 1
        while self.range < 1 << 24:
            self.code = ((self.code << 8) | self.next_byte()) & 0xFFFFFFFF
            self.range <<= 8
        return bit

    def adaptive(self, ctx: list[list[int]], i: int) -> int:
        p0, count = ctx[i]
        bit = self.decode(p0)
        shift = count + 1
        if count < 3:
            count += 1
        if bit:
            p0 -= p0 >> shift
        else:
            p0 += (4096 - p0) >> shift
        ctx[i] = [p0, count]
        return bit


ZERO, SIGN, LENGTH = 0, 1, 2  # an IntContexts set: [zero, sign, length[0..31]]


def int_contexts() -> list[list[int]]:
    """Each context is [p0, count]."""
    return [[2048, 0] for _ in range(2 + 32)]


def magnitude(dec: RangeDecoder, c: list[list[int]]) -> int:
    n = 1
    while n < 32 and dec.adaptive(c, LENGTH + n - 1):
        n += 1
    m = 1
    for _ in range(n - 1):
        m = (m << 1) | dec.decode(2048)
    return m


def uint(dec: RangeDecoder, c: list[list[int]]) -> int:
    return 0 if dec.adaptive(c, ZERO) else magnitude(dec, c)


def sint(dec: RangeDecoder, c: list[list[int]]) -> int:
    if dec.adaptive(c, ZERO):
        return 0
    negative = dec.adaptive(c, SIGN)
    m = magnitude(dec, c)
    return -m if negative else m


class RefReceiver:
    """Frame packets (raw bytes) in, (seq, capture_us, values) out; None for a broken chain."""

    def __init__(self, table: list[tuple[str, int, float]], fps: float) -> None:
        self.table = table
        self.frame_us = round(1e6 / fps)
        self.last_counter = 0
        self.intact = False
        self.prev: tuple[int, int, dict[str, list[int]]] | None = None
        self.reset()

    def reset(self) -> None:
        self.key_ctx = {name: int_contexts() for name, _, _ in self.table}
        self.seq_step = int_contexts()
        self.time = int_contexts()
        self.delta_ctx = {name: [int_contexts() for _ in range(n)] for name, n, _ in self.table}

    def receive(self, packet: bytes) -> tuple[int, int, dict[str, list[int]]] | None:
        if len(packet) >= 2 and 0x90 <= packet[0] <= 0x9F and packet[1] == 1:
            raise RefError("unsupported protocol version 1")
        if packet[0] >> 4 != 2:
            raise RefError("unsupported protocol version")
        kind = packet[0] & 0x0F
        if kind == 2:
            if len(packet) < 18:
                raise RefError("truncated KeyFrame")
            counter, _session, seq, capture_us = struct.unpack_from("<BIIq", packet, 1)
            body = packet[18:]
        elif kind == 9:
            if len(packet) < 2:
                raise RefError("truncated DeltaFrame")
            counter, body = packet[1], packet[2:]
        else:
            raise RefError(f"not a frame packet: kind {kind}")
        if len(body) > 16384:
            raise RefError("body too long")
        expected = (self.last_counter + 1) % 256
        self.last_counter = counter
        if kind == 2:
            self.reset()
            self.intact = False
            dec = RangeDecoder(body)
            values = {
                name: self.checked([sint(dec, self.key_ctx[name]) for _ in range(n)])
                for name, n, _ in self.table
            }
            self.prev = (seq, capture_us, values)
            self.intact = True
            return self.prev
        if not self.intact or counter != expected or self.prev is None:
            self.intact = False
            return None
        self.intact = False
        prev_seq, prev_us, prev_values = self.prev
        dec = RangeDecoder(body)
        step = uint(dec, self.seq_step) + 1
        if step > 30:
            raise RefError("frame step")
        residual_ms = sint(dec, self.time)
        if abs(residual_ms) > 60000:
            raise RefError("time residual")
        values = {
            name: self.checked(
                [prev_values[name][i] + sint(dec, self.delta_ctx[name][i]) for i in range(n)]
            )
            for name, n, _ in self.table
        }
        self.prev = (prev_seq + step, prev_us + step * self.frame_us + 1000 * residual_ms, values)
        self.intact = True
        return self.prev

    @staticmethod
    def checked(values: list[int]) -> list[int]:
        if any(abs(v) > 2**24 for v in values):
            raise RefError("value out of range")
        return values


# --- tests -------------------------------------------------------------------------------------

TABLE = [("pose.rotation", 3, 0.001), ("pose.scale", 1, 0.001), ("pose.translation", 3, 0.5)]
TABLE += [("wire", 4, 0.02)]


def _as_lists(values: dict[str, np.ndarray]) -> dict[str, list[int]]:
    return {k: [int(x) for x in v] for k, v in values.items()}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reference_decoder_matches_channel_decoder(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fps = 30.0
    specs = [ChannelSpec(*t) for t in TABLE]
    frame_us = round(1e6 / fps)
    enc = ChannelEncoder(specs, frame_us, session_id=7, keyframe_interval=40)
    dec = ChannelDecoder(specs, frame_us)
    ref = RefReceiver(TABLE, fps)
    values = {name: rng.integers(-3000, 3000, n) for name, n, _ in TABLE}
    values["pose.translation"][0] = 2**24 - 5  # near the limit: long magnitudes
    seq = 1000
    decoded = skipped = 0
    for i in range(60):
        seq += 1 if rng.random() < 0.8 else int(rng.integers(2, 6))
        capture_us = 10_000_000 + seq * frame_us + int(rng.integers(-4000, 4000))
        if rng.random() < 0.15:
            pass  # nothing changed: no packet
        else:
            for name, n, _ in TABLE:
                small = rng.integers(-3, 4, n) * (rng.random(n) < 0.5)
                big = rng.integers(-70000, 70000, n) * (rng.random(n) < 0.05)
                values[name] = np.clip(values[name] + small + big, -(2**24), 2**24)
        if i == 30:
            enc.request_keyframe()
        packet, sent = enc.encode(seq, capture_us, values)
        if packet is None:
            skipped += 1
            continue
        want = dec.decode(packet)
        got = ref.receive(bytes(packet))
        assert got is not None
        assert (got[0], got[1], got[2]) == (want.seq, want.capture_us, _as_lists(want.values))
        assert (want.seq, want.capture_us) == (sent.seq, sent.capture_us)
        decoded += 1
    assert decoded > 40 and skipped > 0


def test_reference_decoder_chain_rules() -> None:
    specs = [ChannelSpec(*t) for t in TABLE]
    enc = ChannelEncoder(specs, 33333, session_id=7, keyframe_interval=1000)
    ref = RefReceiver(TABLE, 30.0)
    values = {name: np.zeros(n, np.int64) for name, n, _ in TABLE}
    packets = []
    for seq in range(1, 8):
        values["wire"] = values["wire"] + 1
        packet, _ = enc.encode(seq, seq * 33333, values)
        packets.append(bytes(packet))
    assert ref.receive(packets[0]) is not None  # keyframe
    assert ref.receive(packets[1]) is not None
    assert ref.receive(packets[3]) is None  # packets[2] lost: counter gap
    assert ref.receive(packets[4]) is None  # stays broken until a keyframe
    enc.request_keyframe()
    packet, sent = enc.encode(9, 9 * 33333, values)
    got = ref.receive(bytes(packet))
    assert got is not None and got[0] == 9 == sent.seq
    with pytest.raises(RefError, match="version 1"):
        ref.receive(bytes([0x93, 0x01, 0x02, 0x03]))


def _doc_example() -> list[tuple[bytes, tuple[int, int, dict[str, list[int]]]]]:
    text = DOC.read_text(encoding="utf-8")
    block = text.split("<!-- example:begin -->", 1)[1].split("<!-- example:end -->", 1)[0]
    packets = re.findall(r"^packet: ([0-9a-f]+)$", block, re.M)
    values = re.findall(r"^values: (.*)$", block, re.M)
    assert len(packets) == len(values) == 3
    out = []
    for hexstr, line in zip(packets, values, strict=True):
        fields = dict(item.split("=", 1) for item in line.split())
        seq = int(fields.pop("seq"))
        capture_us = int(fields.pop("capture_us"))
        vals = {k: [int(x) for x in v.split(",")] for k, v in fields.items()}
        out.append((bytes.fromhex(hexstr), (seq, capture_us, vals)))
    return out


def test_worked_example_in_the_doc_decodes_to_its_values() -> None:
    ref = RefReceiver(TABLE, 30.0)
    for packet, want in _doc_example():
        assert ref.receive(packet) == want


def test_worked_example_in_the_doc_is_what_the_code_sends() -> None:
    specs = [ChannelSpec(*t) for t in TABLE]
    enc = ChannelEncoder(specs, round(1e6 / 30), session_id=0x12345678, keyframe_interval=60)
    example = _doc_example()
    inputs = [(100, 5_000_000), (101, 5_033_500), (102, 5_066_000), (103, 5_101_000)]
    sent = []
    for seq, capture_us in inputs:
        want = next((v for _, (s, _, v) in example if s == seq), None)
        values = want if want is not None else sent[-1][1][2]  # frame 102 repeats 101
        packet, _ = enc.encode(seq, capture_us, {k: np.array(v) for k, v in values.items()})
        if packet is not None:
            sent.append((bytes(packet), (seq, 0, values)))
    assert [p for p, _ in sent] == [p for p, _ in example]


def _hex_block(after: str) -> bytes:
    """The hex bytes of the first fenced block after ``after`` in section 8.8 (comments
    after two spaces dropped)."""
    section = DOC.read_text().split("### 8.8 Worked example", 1)[1]
    block = section.split(after, 1)[1].split("```", 2)[1]
    words = []
    for line in block.strip().splitlines():
        words += line.split("  ")[0].split()
    return bytes.fromhex("".join(words))


def test_worked_datagram_in_the_doc_is_what_the_code_seals() -> None:
    from facewire.protocol.bundle import Report, pack
    from facewire.protocol.datagram import SENDER_TO_RECEIVER, Opener, Sealer
    from facewire.protocol.packets import Heartbeat

    secret = bytes(range(32))
    sealer = Sealer(secret, SENDER_TO_RECEIVER, 7)
    sealer.index = 0x1234
    bundle = pack([bytes(Heartbeat(3050556106, 42, 1_000_000))])
    datagram = sealer.seal(bundle)
    assert _hex_block("The datagram (26 bytes):") == datagram
    assert Opener(secret, SENDER_TO_RECEIVER, 7).open(datagram) == (0x1234, bundle)
    report = bytes(Report(0x1234, 123456, 100, 4200)).hex(" ")
    assert f"`{report}`" in DOC.read_text()
