"""Packet codec: round trips, strict errors, captured fixtures."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from facewire.protocol.constants import MAX_PACKET_BYTES, REM_CODES, REM_REGIONS
from facewire.protocol.images import ImageError, check_image, image_size
from facewire.protocol.packets import (
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    PacketError,
    ReceiverStats,
    RemPatch,
    Snapshot,
    SnapshotRequest,
    decode,
)

FIXTURES = Path(__file__).parent / "fixtures" / "packets"
# Small real images (made once with OpenCV from a 16 x 16 colour ramp): 16 x 16 JPEG and
# WebP, a 12 x 9 PNG.
IMAGES = Path(__file__).parent / "fixtures" / "images"
JPEG = (IMAGES / "eyes.jpg").read_bytes()
PNG = (IMAGES / "background.png").read_bytes()
WEBP = (IMAGES / "texture.webp").read_bytes()


def png_header(width: int, height: int) -> bytes:
    """The signature and IHDR chunk of an 8-bit RGB PNG of this size (no pixel data)."""
    ihdr = b"IHDR" + struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr))


# --- hypothesis strategies ---------------------------------------------------------------------

uint32 = st.integers(0, 2**32 - 1)
int64 = st.integers(-(2**63), 2**63 - 1)
names = st.text(min_size=1, max_size=20)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
images = st.sampled_from([b"", JPEG, PNG, WEBP])
bodies = st.binary(max_size=64)

key_frames = st.builds(KeyFrame, st.integers(0, 255), uint32, uint32, int64, bodies)
delta_frames = st.builds(DeltaFrame, st.integers(0, 255), bodies)
channel_tables = st.lists(
    st.tuples(names, st.integers(1, 64), st.floats(1e-6, 10.0)),
    min_size=1,
    max_size=6,
    unique_by=lambda t: t[0],
)


@st.composite
def snapshots(draw: st.DrawFn) -> Snapshot:
    channels = draw(channel_tables)
    values = st.integers(-(2**24), 2**24)
    reference = [draw(st.lists(values, min_size=n, max_size=n)) for _, n, _ in channels]
    return draw(_snapshots(channels, reference))


def _snapshots(channels: list, reference: list) -> st.SearchStrategy[Snapshot]:
    return st.builds(
        Snapshot,
        session_id=uint32,
        seq=uint32,
        width=st.integers(1, 4096),
        height=st.integers(1, 4096),
        fps=st.floats(0.1, 240.0),
        vertices=hnp.arrays(
            np.float32,
            st.tuples(st.integers(1, 30), st.just(3)),
            elements=st.floats(-50, 50, width=32),
        ),
        texture=images,
        background=images,
        channels=st.just(channels),
        rig_hash=st.text("0123456789abcdef", min_size=64, max_size=64),
        keyframe_interval=st.integers(1, 65535),
        reference=st.just(reference),
        meta=st.dictionaries(names, st.one_of(st.text(max_size=30), int64, finite), max_size=5),
    )


rem_patches = st.builds(
    RemPatch,
    seq=uint32,
    region=st.sampled_from(REM_REGIONS),
    codec=st.just("jpeg"),
    data=st.just(JPEG),
    h_peak=st.floats(0, 360),
    s_mean=st.floats(0, 1),
    v_mean=st.floats(0, 1),
)
packets = st.one_of(
    snapshots(),
    key_frames,
    delta_frames,
    rem_patches,
    st.builds(KeyframeRequest, uint32),
    st.builds(Heartbeat, uint32, uint32, int64),
    st.builds(ReceiverStats, st.dictionaries(names, finite, max_size=8)),
    st.builds(Bye, uint32),
    st.just(SnapshotRequest()),
)


@given(packets)
def test_round_trip(packet: object) -> None:
    data = bytes(packet)  # type: ignore[call-overload]
    decoded = decode(data)
    assert decoded == packet
    assert bytes(decoded) == data
    assert type(decoded).parse(data) == packet


def test_equality_sees_field_contents() -> None:
    a = KeyFrame(1, 7, 100, 5, b"\x01\x02")
    assert a == KeyFrame(1, 7, 100, 5, b"\x01\x02")
    assert a != KeyFrame(1, 7, 100, 5, b"\x01\x03")
    assert a != DeltaFrame(1, b"\x01\x02")
    assert a != Heartbeat(7, 1, 2)


def test_frame_packets_are_small() -> None:
    # Header byte + counter + body: a delta frame is its body plus two bytes.
    assert bytes(DeltaFrame(5, b"\xab\xcd")) == b"\x29\x05\xab\xcd"
    # A keyframe adds seq, session and capture time: 1 + 1 + 4 + 4 + 8 bytes.
    assert len(bytes(KeyFrame(5, 7, 100, 2**40, b""))) == 18


def test_every_packet_starts_with_version_and_kind() -> None:
    for packet in (KeyFrame(0, 1, 2, 3, b""), DeltaFrame(0, b""), Bye(1), SnapshotRequest()):
        data = bytes(packet)
        assert data[0] >> 4 == 2 and data[0] & 0x0F == packet.KIND


# --- captured fixtures ---------------------------------------------------------------------------

EXAMPLES = {
    "snapshot": Snapshot(
        session_id=42,
        seq=100,
        width=640,
        height=480,
        fps=30.0,
        vertices=np.array([[0.0, 1.5, -2.0], [3.25, 0.0, 1.0]], np.float32),
        texture=WEBP,
        background=PNG,
        channels=[("pose.rotation", 3, 0.002), ("pose.scale", 1, 0.002), ("wire", 16, 0.05)],
        rig_hash="0123456789abcdef" * 4,
        keyframe_interval=120,
        reference=[(0, -3, 12), (-40,), tuple(range(-8, 8))],
        meta={"mesh": "canonical", "subdivision": 1, "focal_px": 600.5},
    ),
    "key_frame": KeyFrame(
        counter=3, session_id=42, seq=101, capture_us=1_700_000_123_456, body=b"\x81\x7f\x10"
    ),
    "delta_frame": DeltaFrame(counter=4, body=b"\x12\x34"),
    "rem_patch": RemPatch(101, "eye_right", "jpeg", JPEG, 12.5, 0.25, 0.75),
    "rem_patch_reference": RemPatch.referring(102, "eye_left", 96, 12.5, 0.25, 0.75),
    "keyframe_request": KeyframeRequest(99),
    "heartbeat": Heartbeat(42, 101, 1_700_000_999_000),
    "receiver_stats": ReceiverStats({"fps": 29.97, "latency_ms_p50": 31.0}),
    "bye": Bye(250),
    "snapshot_request": SnapshotRequest(),
}


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_fixture_bytes(name: str) -> None:
    data = (FIXTURES / f"{name}.bin").read_bytes()
    packet = decode(data)
    assert packet == EXAMPLES[name]
    assert bytes(packet) == data
    assert bytes(EXAMPLES[name]) == data


def test_fixture_fields() -> None:
    key = KeyFrame.parse((FIXTURES / "key_frame.bin").read_bytes())
    assert (key.counter, key.session_id, key.seq, key.capture_us) == (3, 42, 101, 1_700_000_123_456)
    assert key.body == b"\x81\x7f\x10"
    snap = Snapshot.parse((FIXTURES / "snapshot.bin").read_bytes())
    assert snap.vertices.dtype == np.float32 and snap.vertices.shape == (2, 3)
    assert snap.vertices[1].tolist() == [3.25, 0.0, 1.0]
    assert snap.channels[2] == ("wire", 16, 0.05)
    assert snap.texture == WEBP and snap.background == PNG


# --- errors ---------------------------------------------------------------------------------------

KEY = (FIXTURES / "key_frame.bin").read_bytes()
SNAPSHOT = (FIXTURES / "snapshot.bin").read_bytes()


def pack(kind: int, *items: object) -> bytes:
    data: bytes = msgpack.packb(list(items), use_bin_type=True)
    return bytes([0x20 | kind]) + data


def rem(seq: int, region: int, codec: str | int, data: bytes, s_mean: int = 0x8000) -> bytes:
    """A RemPatch's bytes as docs/protocol.md lays them out (codec by name or by code)."""
    code = REM_CODES.index(codec) if isinstance(codec, str) else codec
    return b"\x23" + struct.pack("<BBIHHH", region, code, seq, 100, s_mean, 0x8000) + data


V1_HEARTBEAT = msgpack.packb([1, 5, 1, 2])


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "empty packet"),
        (V1_HEARTBEAT, "unsupported protocol version 1 (this peer speaks 2)"),
        (b"\x35\x90", "unsupported protocol version 3 (header byte 0x35; this peer speaks 2)"),
        (b"\x20", "unknown packet kind 0"),
        (b"\x2f", "unknown packet kind 15"),
        (KEY[:10], "truncated KeyFrame: 10 bytes, needs at least 18"),
        (b"\x29", "truncated DeltaFrame: 1 byte, needs at least 2"),
        (SNAPSHOT[:-5], f"truncated packet ({len(SNAPSHOT) - 5} bytes)"),
        (SNAPSHOT + b"\x00", "1 trailing bytes after the packet"),
        (b"\x25\xc1", "malformed msgpack: invalid type byte"),
        (b"\x25" + b"\x91" * 5000, "malformed msgpack: nesting too deep"),
        (b"\x25\x07", "Heartbeat: expected a msgpack array, got int"),
        (pack(5, 1), "Heartbeat needs 3 fields, got 1"),
        (pack(5, 1, -1, 0), "Heartbeat.seq: -1 outside [0, 4294967295]"),
        (pack(5, 1, 2**32, 0), "Heartbeat.seq: 4294967296 outside [0, 4294967295]"),
        (pack(5, 1, 1.0, 0), "Heartbeat.seq: expected int, got float"),
        (pack(5, 1, True, 0), "Heartbeat.seq: expected int, got bool"),
        (pack(5, 2**32, 1, 0), "Heartbeat.session_id: 4294967296 outside [0, 4294967295]"),
        (b"\x26\x91\x81\x01\x02", "malformed msgpack: int is not allowed for map key"),
        (b"\x26\x91\x82\xa1a\x01\xa1a\x02", "duplicate map key 'a'"),
        (pack(6, {"fps": float("nan")}), "ReceiverStats.values['fps']: expected a finite"),
        (pack(6, {"fps": "30"}), "ReceiverStats.values['fps']: expected float, got str"),
        (rem(1, 0, 9, JPEG), "RemPatch.codec: unknown codec 9"),
        (rem(1, 4, "jpeg", JPEG), "RemPatch.region: unknown region 4"),
        (b"\x23\x00\x01" + bytes(4) + b"\xff\xff" + bytes(4) + JPEG, "RemPatch.h_peak: 655.35"),
        (rem(1, 0, "jpeg", PNG), "RemPatch.data: a png image, expected jpeg"),
        (rem(1, 0, "png", b""), "truncated RemPatch: 13 bytes, needs at least 14"),
        (
            rem(1, 0, "png", png_header(16384, 16384)),
            "RemPatch.data: png image of 16384x16384 pixels, each side must be in [1, 4096]",
        ),
        (rem(9, 1, "ref", b"\x05\x00\x00"), "RemPatch.data: a reference is 4 bytes, got 3"),
        (
            rem(9, 1, "ref", b"\x0a\x00\x00\x00"),
            "RemPatch.data: a reference to a later frame than its own",
        ),
        (b"\x25\x93\x01\x05\xd4\x01\x02", "malformed msgpack: 2 exceeds max_ext_len(0)"),
        (b"\x25\x94\x01\x05\x01\xa2\xff\xfe", "malformed msgpack: 'utf-8' codec can't decode"),
    ],
)
def test_error_messages(data: bytes, message: str) -> None:
    with pytest.raises(PacketError) as info:
        decode(data)
    assert str(info.value).startswith(message), str(info.value)


#: The shortest well-formed packet of each binary kind: its fixed fields and the least body
#: (a KeyFrame's may be empty, a DeltaFrame's too, an AudioFrame holds at least one byte).
SHORTEST = {"key_frame": 18, "delta_frame": 2, "audio_frame": 14}


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_a_binary_packet_a_byte_short_of_its_fixed_fields_is_refused(name: str) -> None:
    """Their bodies declare no length, so a cut inside the body is another valid packet; a cut
    into the fixed fields is not, even by one byte (a decoder that pads a missing byte was
    once taken: only a cut of 8 bytes was tried)."""
    data = (FIXTURES / f"{name}.bin").read_bytes()
    kind = type(decode(data)).__name__
    shortest = SHORTEST[name]
    decoded = decode(data[:shortest])
    assert type(decoded).__name__ == kind
    assert bytes(decoded) == data[:shortest]
    for length in range(1, shortest):
        with pytest.raises(PacketError) as info:
            decode(data[:length])
        plural = "byte" if length == 1 else "bytes"
        assert str(info.value) == (
            f"truncated {kind}: {length} {plural}, needs at least {shortest}"
        ), length


@pytest.mark.parametrize("name", ["rem_patch", "rem_patch_reference"])
def test_a_rem_patch_cut_short_is_refused(name: str) -> None:
    """Its fixed fields cut short, whatever the cut; a reference cut short too (an image cut
    inside its pixels may still have a valid header: the receiver's decoder refuses it)."""
    data = (FIXTURES / f"{name}.bin").read_bytes()
    for length in range(1, 14):
        with pytest.raises(PacketError) as info:
            decode(data[:length])
        plural = "byte" if length == 1 else "bytes"
        assert str(info.value) == f"truncated RemPatch: {length} {plural}, needs at least 14"
    if name == "rem_patch_reference":
        for length in range(14, len(data)):
            with pytest.raises(PacketError, match="a reference is 4 bytes"):
                decode(data[:length])


def test_a_rem_patch_is_made_only_of_what_can_travel() -> None:
    """Its region is one of the table's, its colour figures in range, its image not empty;
    the figures are rounded to the steps they travel in, so that a packet equals its copy."""
    for region, codec, data, s_mean, message in [
        ("eyes", "jpeg", JPEG, 0.5, "RemPatch.region: unknown region 'eyes'"),
        ("eye_left", "png", b"", 0.5, "RemPatch.data: must not be empty"),
        ("eye_left", "jpeg", JPEG, 1.5, "RemPatch.s_mean: 1.5 outside"),
        ("eye_left", "h264", JPEG, 0.5, "RemPatch.codec: unknown codec 'h264'"),
    ]:
        with pytest.raises(PacketError, match=message):
            RemPatch(1, region, codec, data, 10.0, s_mean, 0.5)
    patch = RemPatch(1, "mouth_interior", "jpeg", JPEG, 359.987654, 1 / 3, 1.0)
    assert (patch.h_peak, patch.s_mean, patch.v_mean) == pytest.approx(
        (359.99, 1 / 3, 1.0), abs=1e-5
    )
    assert decode(bytes(patch)) == patch


def test_every_msgpack_packet_a_byte_short_is_refused() -> None:
    """msgpack packets say their own length: one byte short is an error, whichever kind."""
    for path in sorted(FIXTURES.glob("*.bin")):
        data = path.read_bytes()
        if path.stem in SHORTEST or path.stem.startswith("rem_patch"):
            continue
        with pytest.raises(PacketError, match=r"truncated packet|needs|expected"):
            decode(data[:-1])


def snapshot_fields(**changes: object) -> bytes:
    fields: dict[str, object] = {
        "session_id": 1,
        "seq": 0,
        "width": 640,
        "height": 480,
        "fps": 30.0,
        "n": 1,
        "vertices": bytes(12),
        "texture": b"",
        "background": b"",
        "channels": [["wire", 4, 0.1]],
        "rig_hash": "ab" * 32,
        "keyframe_interval": 60,
        "meta": {},
        "reference": [[0, 0, 0, 0]],
    }
    fields.update(changes)
    return pack(1, *fields.values())


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"n": 3}, "Snapshot.vertices: 12 bytes for 3 vertices (expected 18 as float16 or 36"),
        ({"n": 2}, None),  # 12 bytes for 2 vertices: float16
        ({"n": 1, "vertices": bytes(4) + b"\x00\x7c"}, "Snapshot.vertices: non-finite"),
        ({"n": 0, "vertices": b""}, "Snapshot.n_vertices: 0 outside [1, 200000]"),
        ({"fps": 0.0}, "Snapshot.fps: 0.0 outside [0.01, 1000.0]"),
        ({"fps": 5e-324}, "Snapshot.fps: 5e-324 outside [0.01, 1000.0]"),
        ({"fps": 0.01}, None),
        ({"fps": 30}, None),  # ints are accepted where floats are expected
        ({"width": 0}, "Snapshot.width: 0 outside [1, 4096]"),
        ({"height": 16384}, "Snapshot.height: 16384 outside [1, 4096]"),
        ({"texture": b"GIF89a"}, "Snapshot.texture: unknown image format (starts with 4749"),
        ({"texture": b"RIFF\x04\x00\x00\x00WAVE"}, "Snapshot.texture: unknown image format"),
        ({"background": b"RIFF\x04\x00\x00\x00WEBP"}, "Snapshot.background: truncated WebP"),
        ({"texture": WEBP, "background": JPEG}, None),
        ({"background": png_header(4096, 4096)}, None),  # the header is all decode reads
        (
            {"background": png_header(4097, 16)},
            "Snapshot.background: png image of 4097x16 pixels, each side must be in [1, 4096]",
        ),
        ({"texture": png_header(0, 16)}, "Snapshot.texture: png image of 0x16 pixels"),
        ({"texture": PNG[:20]}, "Snapshot.texture: truncated PNG header (20 bytes, need 33)"),
        ({"texture": JPEG[:2] + b"\xff\xda"}, "Snapshot.texture: JPEG scan (SOS) before the"),
        ({"channels": [["wire", 4, -0.1]]}, "Snapshot.channels[0] step: must be > 0, got -0.1"),
        ({"channels": [["wire", 0, 0.1]]}, "Snapshot.channels[0] size: 0 outside [1, 8192]"),
        ({"channels": [["wire", 4]]}, "Snapshot.channels[0]: expected [name, size, step]"),
        ({"channels": []}, "Snapshot.channels: 0 channels outside [1, 32]"),
        ({"channels": [["a", 1, 1.0], ["a", 1, 1.0]]}, "Snapshot.channels: duplicate channel"),
        ({"rig_hash": "AB" * 32}, "Snapshot.rig_hash: expected 64 lowercase hex digits"),
        ({"keyframe_interval": 0}, "Snapshot.keyframe_interval: 0 outside [1, 65535]"),
        ({"meta": {"x": [1]}}, "Snapshot.meta['x']: expected str, int or float, got array"),
        ({"meta": {"x": True}}, "Snapshot.meta['x']: expected str, int or float, got bool"),
        ({"vertices": bytes(8) + b"\x00\x00\xc0\x7f"}, "Snapshot.vertices: non-finite"),
        ({"reference": [[0, 0, 0]]}, "Snapshot.reference['wire']: 3 values, expected 4"),
        ({"reference": []}, "Snapshot.reference: 0 channels, the table has 1"),
        ({"reference": [[0, 0, 0, 2**25]]}, "Snapshot.reference['wire']: 33554432 outside"),
    ],
)
def test_snapshot_errors(changes: dict[str, object], message: str | None) -> None:
    data = snapshot_fields(**changes)
    if message is None:
        assert isinstance(decode(data), Snapshot)
        return
    with pytest.raises(PacketError) as info:
        decode(data)
    assert str(info.value).startswith(message), str(info.value)


@given(st.floats(allow_nan=False, allow_infinity=False) | st.floats(0, 0.02))
def test_a_snapshot_frame_rate_gives_a_frame_interval(fps: float) -> None:
    """Whatever fps a peer states, the frame interval 1e6 / fps a receiver derives from an
    accepted snapshot is a sane integer (a subnormal fps made it infinite)."""
    try:
        snapshot = decode(snapshot_fields(fps=fps))
    except PacketError as exc:
        assert str(exc).startswith("Snapshot.fps: ") and not 0.01 <= fps <= 1000
        return
    assert isinstance(snapshot, Snapshot)
    assert 1000 <= round(1e6 / snapshot.fps) <= 10**8


sides = st.one_of(st.integers(0, 4100), st.integers(0, 2**31 - 1))


@given(sides, sides)
def test_image_sizes_are_checked_at_decode(width: int, height: int) -> None:
    data = snapshot_fields(background=png_header(width, height))
    if 1 <= width <= 4096 and 1 <= height <= 4096:
        assert isinstance(decode(data), Snapshot)
        return
    with pytest.raises(PacketError, match=f"Snapshot.background: png image of {width}x{height}"):
        decode(data)


@given(st.sampled_from([JPEG, PNG, WEBP]), st.integers(0, 60), st.binary(min_size=1, max_size=8))
def test_decode_takes_an_image_exactly_when_its_header_checks(
    image: bytes, at: int, junk: bytes
) -> None:
    """Damaged headers: the packet decodes if and only if protocol.images accepts the image
    (and, in a RemPatch, finds the codec the patch names)."""
    blob = image[:at] + junk + image[at + len(junk) :]
    try:
        codec: str | None = check_image(blob, "x")[0]
    except ImageError:
        codec = None
    cases: list[tuple[type, bytes, bool]] = [
        (Snapshot, snapshot_fields(texture=blob), codec is not None)
    ]
    named = image_size(image)[0]
    patch = rem(1, 0, named, blob)
    cases.append((RemPatch, patch, codec == named))
    for kind, data, good in cases:
        if good:
            assert isinstance(decode(data), kind)
        else:
            with pytest.raises(PacketError):
                decode(data)


def test_oversized() -> None:
    data = bytes(MAX_PACKET_BYTES + 1)
    with pytest.raises(PacketError) as info:
        decode(data)
    assert str(info.value) == (
        f"packet of {MAX_PACKET_BYTES + 1} bytes exceeds the limit of {MAX_PACKET_BYTES} bytes"
    )
    big = RemPatch(1, "eye_left", "jpeg", JPEG + bytes(MAX_PACKET_BYTES), 0.0, 0.0, 0.0)
    with pytest.raises(PacketError, match="exceeds the limit"):
        bytes(big)


def test_parse_checks_the_kind() -> None:
    with pytest.raises(PacketError) as info:
        KeyFrame.parse(bytes(Heartbeat(1, 1, 2)))
    assert str(info.value) == "expected KeyFrame packet, got Heartbeat"


def test_not_bytes() -> None:
    with pytest.raises(PacketError, match="expected bytes, got str"):
        decode("hello")  # type: ignore[arg-type]


def test_constructors_validate_like_the_decoder() -> None:
    with pytest.raises(PacketError) as info:
        DeltaFrame(256, b"")
    assert str(info.value) == "DeltaFrame.counter: 256 outside [0, 255]"
    with pytest.raises(PacketError) as info:
        Snapshot(1, 0, 640, 480, 30.0, np.zeros((4, 2)), b"", b"", [], "ab" * 32, 1, [])
    assert str(info.value) == "Snapshot.vertices: expected (n, 3) float array, got shape (4, 2)"
    with pytest.raises(PacketError, match="DeltaFrame.body: 20000 bytes exceeds 16384"):
        DeltaFrame(0, bytes(20000))


def test_packets_are_frozen() -> None:
    frame = KeyFrame(1, 2, 3, 4, b"")
    with pytest.raises(AttributeError):
        frame.seq = 3  # type: ignore[misc]
