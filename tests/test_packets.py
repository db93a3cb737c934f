"""Packet codec: round trips, strict errors, captured fixtures."""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.constants import MAX_PACKET_BYTES, PNG_MAGIC
from protocol.packets import (
    Bye,
    Frame,
    Heartbeat,
    KeyframeRequest,
    PacketError,
    ReceiverStats,
    RemPatch,
    Snapshot,
    SnapshotRequest,
    decode,
)

FIXTURES = Path(__file__).parent / "fixtures" / "packets"
JPEG = b"\xff\xd8\xff\xe0" + bytes(range(40)) + b"\xff\xd9"
PNG = PNG_MAGIC + b"\x00\x00\x00\x0dIHDR" + bytes(20)

# --- hypothesis strategies ---------------------------------------------------------------------

uint32 = st.integers(0, 2**32 - 1)
int64 = st.integers(-(2**63), 2**63 - 1)
names = st.text(min_size=1, max_size=20)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
int16s = st.integers(-32768, 32767)
int16_vectors = hnp.arrays(np.int16, st.integers(0, 64), elements=int16s)
images = st.sampled_from([b"", JPEG, PNG])

frames = st.builds(
    Frame,
    seq=uint32,
    capture_us=int64,
    key=st.booleans(),
    pose=hnp.arrays(np.int16, 8, elements=int16s),
    params=int16_vectors,
    channels=st.dictionaries(names, int16_vectors, max_size=3),
)
snapshots = st.builds(
    Snapshot,
    session_id=st.integers(0, 2**63 - 1),
    seq=uint32,
    width=st.integers(1, 4096),
    height=st.integers(1, 4096),
    fps=st.floats(0.1, 240.0),
    vertices=hnp.arrays(
        np.float32, st.tuples(st.integers(1, 30), st.just(3)), elements=st.floats(-50, 50, width=32)
    ),
    texture=images,
    background=images,
    quant=st.dictionaries(names, st.floats(1e-6, 10.0), max_size=5),
    wire_layout=st.lists(st.tuples(names, st.integers(1, 64)), max_size=6),
    rig_version=uint32,
    meta=st.dictionaries(names, st.one_of(st.text(max_size=30), int64, finite), max_size=5),
)
rem_patches = st.builds(
    RemPatch,
    seq=uint32,
    region=names,
    codec=st.just("jpeg"),
    data=st.just(JPEG),
    h_peak=st.floats(0, 360),
    s_mean=st.floats(0, 1),
    v_mean=st.floats(0, 1),
)
packets = st.one_of(
    snapshots,
    frames,
    rem_patches,
    st.builds(KeyframeRequest, uint32),
    st.builds(Heartbeat, uint32, int64),
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


@given(frames)
def test_frame_arrays_are_int16_read_only(frame: Frame) -> None:
    decoded = decode(bytes(frame))
    assert isinstance(decoded, Frame)
    assert decoded.params.dtype == np.int16 and not decoded.params.flags.writeable
    assert decoded.pose.shape == (8,)


def test_equality_sees_array_contents_and_dtype() -> None:
    a = Frame(1, 2, False, np.zeros(8, np.int16), np.array([1, 2], np.int16))
    assert a == Frame(1, 2, False, np.zeros(8, np.int16), np.array([1, 2], np.int16))
    assert a != Frame(1, 2, False, np.zeros(8, np.int16), np.array([1, 3], np.int16))
    assert a != Frame(1, 2, False, np.zeros(8, np.int16), np.array([1, 2, 0], np.int16))
    assert a != Heartbeat(1, 2)


def test_frame_size_is_small() -> None:
    frame = Frame(7, 1000, True, np.zeros(8, np.int16), np.zeros(20, np.int16))
    # [1, 2, 7, 1000, true, bin8(16), bin8(40), {}]: 1+1+1+1+3+1+18+42+1 bytes
    assert len(bytes(frame)) == 69


# --- captured fixtures ---------------------------------------------------------------------------

EXAMPLES = {
    "snapshot": Snapshot(
        session_id=42,
        seq=100,
        width=640,
        height=480,
        fps=30.0,
        vertices=np.array([[0.0, 1.5, -2.0], [3.25, 0.0, 1.0]], np.float32),
        texture=JPEG,
        background=PNG,
        quant={"pose.scale": 1e-4, "pose.translation": 0.01, "wire": 0.001},
        wire_layout=[("brow_l", 6), ("lip_upper", 8)],
        rig_version=3,
        meta={"mesh": "canonical", "subdivision": 1, "focal_px": 600.5},
    ),
    "frame": Frame(
        seq=101,
        capture_us=1_700_000_123_456,
        key=True,
        pose=np.array([0, 0, 0, 32767, -12, 100, -200, 3000], np.int16),
        params=np.array([1, -1, 300, -32767, 32767], np.int16),
        channels={"gde": np.array([5, -5], np.int16), "mouth": np.array([], np.int16)},
    ),
    "rem_patch": RemPatch(101, "eyes", "jpeg", JPEG, 12.5, 0.25, 0.75),
    "keyframe_request": KeyframeRequest(99),
    "heartbeat": Heartbeat(101, 1_700_000_999_000),
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
    frame = Frame.parse((FIXTURES / "frame.bin").read_bytes())
    assert (frame.seq, frame.capture_us, frame.key) == (101, 1_700_000_123_456, True)
    assert frame.pose.tolist() == [0, 0, 0, 32767, -12, 100, -200, 3000]
    assert frame.params.tolist() == [1, -1, 300, -32767, 32767]
    assert list(frame.channels) == ["gde", "mouth"]
    snap = Snapshot.parse((FIXTURES / "snapshot.bin").read_bytes())
    assert snap.vertices.dtype == np.float32 and snap.vertices.shape == (2, 3)
    assert snap.vertices[1].tolist() == [3.25, 0.0, 1.0]
    assert snap.wire_layout == (("brow_l", 6), ("lip_upper", 8))
    assert snap.texture == JPEG and snap.background == PNG


# --- errors ---------------------------------------------------------------------------------------

FRAME = (FIXTURES / "frame.bin").read_bytes() if (FIXTURES / "frame.bin").exists() else b""


def pack(*items: object) -> bytes:
    data: bytes = msgpack.packb(list(items), use_bin_type=True)
    return data


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "empty packet"),
        (FRAME[:-5], f"truncated packet ({len(FRAME) - 5} bytes)"),
        (FRAME + b"\x00", "1 trailing bytes after the packet"),
        (b"\xc1", "malformed msgpack: invalid type byte"),
        (b"\x91" * 5000, "malformed msgpack: nesting too deep"),
        (b"garbage!", "7 trailing bytes after the packet"),
        (b"\x07", "packet must be a msgpack array, got int"),
        (msgpack.packb({"v": 1}), "packet must be a msgpack array, got map"),
        (pack(1), "packet header needs [version, kind], got 1 element(s)"),
        (pack(2, 5, 1, 2), "unsupported protocol version 2 (this peer speaks 1)"),
        (pack("1", 5, 1, 2), "protocol version must be an int, got str"),
        (pack(1, 99), "unknown packet kind 99"),
        (pack(1, "frame"), "unknown packet kind 'frame'"),
        (pack(1, 5, 1), "Heartbeat needs 2 fields, got 1"),
        (pack(1, 5, -1, 0), "Heartbeat.seq: -1 outside [0, 4294967295]"),
        (pack(1, 5, 2**32, 0), "Heartbeat.seq: 4294967296 outside [0, 4294967295]"),
        (pack(1, 5, 1.0, 0), "Heartbeat.seq: expected int, got float"),
        (pack(1, 5, True, 0), "Heartbeat.seq: expected int, got bool"),
        (pack(1, 2, 1, 2, 1, bytes(16), b"", {}), "Frame.key: expected bool, got int"),
        (pack(1, 2, 1, 2, True, bytes(14), b"", {}), "Frame.pose: expected shape (8,), got (7,)"),
        (pack(1, 2, 1, 2, True, bytes(16), b"\x00", {}), "Frame.params: odd length 1 for int16"),
        (pack(1, 2, 1, 2, True, bytes(16), [1, 2], {}), "Frame.params: expected bin, got array"),
        (pack(1, 2, 1, 2, True, bytes(16), b"", None), "Frame.channels: expected map, got nil"),
        (
            pack(1, 2, 1, 2, True, bytes(16), b"", {"": b""}),
            "Frame.channels key: must not be empty",
        ),
        (b"\x93\x01\x06\x81\x01\x02", "malformed msgpack: int is not allowed for map key"),
        (b"\x93\x01\x06\x82\xa1a\x01\xa1a\x02", "duplicate map key 'a'"),
        (pack(1, 6, {"fps": float("nan")}), "ReceiverStats.values['fps']: expected a finite"),
        (pack(1, 6, {"fps": "30"}), "ReceiverStats.values['fps']: expected float, got str"),
        (pack(1, 3, 1, "eyes", "h264", JPEG, 1.0, 0.5, 0.5), "RemPatch.codec: unknown codec"),
        (pack(1, 3, 1, "eyes", "jpeg", PNG, 1.0, 0.5, 0.5), "RemPatch.data: not a jpeg image"),
        (pack(1, 3, 1, "eyes", "jpeg", JPEG, 1.0, 1.5, 0.5), "RemPatch.s_mean: 1.5 outside"),
        (b"\x93\x01\x05\xd4\x01\x02", "malformed msgpack: 2 exceeds max_ext_len(0)"),
        (b"\x94\x01\x05\x01\xa2\xff\xfe", "malformed msgpack: 'utf-8' codec can't decode"),
    ],
)
def test_error_messages(data: bytes, message: str) -> None:
    with pytest.raises(PacketError) as info:
        decode(data)
    assert str(info.value).startswith(message), str(info.value)


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
        "quant": {},
        "wire_layout": [],
        "rig_version": 0,
        "meta": {},
    }
    fields.update(changes)
    return pack(1, 1, *fields.values())


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"n": 2}, "Snapshot.vertices: 12 bytes for 2 vertices (expected 24)"),
        ({"n": 0, "vertices": b""}, "Snapshot.n_vertices: 0 outside [1, 200000]"),
        ({"fps": 0.0}, "Snapshot.fps: must be > 0, got 0.0"),
        ({"fps": 30}, None),  # ints are accepted where floats are expected
        ({"width": 0}, "Snapshot.width: 0 outside [1, 16384]"),
        ({"texture": b"GIF89a"}, "Snapshot.texture: neither JPEG nor PNG (starts with"),
        ({"quant": {"wire": -0.1}}, "Snapshot.quant['wire']: must be > 0.0, got -0.1"),
        ({"wire_layout": [["brow", 0]]}, "Snapshot.wire_layout[0] n_ctrl: 0 outside [1, 1024]"),
        ({"wire_layout": [["brow"]]}, "Snapshot.wire_layout[0]: expected [name, n_ctrl]"),
        ({"meta": {"x": [1]}}, "Snapshot.meta['x']: expected str, int or float, got array"),
        ({"meta": {"x": True}}, "Snapshot.meta['x']: expected str, int or float, got bool"),
        ({"vertices": bytes(8) + b"\x00\x00\xc0\x7f"}, "Snapshot.vertices: non-finite"),
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


def test_oversized() -> None:
    data = bytes(MAX_PACKET_BYTES + 1)
    with pytest.raises(PacketError) as info:
        decode(data)
    assert str(info.value) == (
        f"packet of {MAX_PACKET_BYTES + 1} bytes exceeds the limit of {MAX_PACKET_BYTES} bytes"
    )
    big = RemPatch(1, "eyes", "jpeg", JPEG + bytes(MAX_PACKET_BYTES), 0.0, 0.0, 0.0)
    with pytest.raises(PacketError, match="exceeds the limit"):
        bytes(big)


def test_parse_checks_the_kind() -> None:
    with pytest.raises(PacketError) as info:
        Frame.parse(bytes(Heartbeat(1, 2)))
    assert str(info.value) == "expected Frame packet, got Heartbeat"


def test_not_bytes() -> None:
    with pytest.raises(PacketError, match="expected bytes, got str"):
        decode("hello")  # type: ignore[arg-type]


def test_constructors_validate_like_the_decoder() -> None:
    with pytest.raises(PacketError) as info:
        Frame(1, 2, True, np.zeros(8, np.int16), np.zeros(3, np.int64))
    assert (
        str(info.value) == "Frame.params: expected 1-D int16 array, got int64 array of shape (3,)"
    )
    with pytest.raises(PacketError) as info:
        Snapshot(1, 0, 640, 480, 30.0, np.zeros((4, 2)), b"", b"", {}, [], 0)
    assert str(info.value) == "Snapshot.vertices: expected (n, 3) float array, got shape (4, 2)"


def test_packets_are_frozen_and_copy_their_arrays() -> None:
    params = np.array([1, 2], np.int16)
    frame = Frame(1, 2, True, np.zeros(8, np.int16), params)
    params[0] = 9
    assert frame.params.tolist() == [1, 2]
    with pytest.raises(ValueError, match="read-only"):
        frame.params[0] = 5
    with pytest.raises(AttributeError):
        frame.seq = 3  # type: ignore[misc]
