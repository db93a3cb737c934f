"""Wire packets: small frozen dataclasses, msgpack framing, one strict decoder.

Every packet starts with one header byte, ``0x20 | kind`` (version 2 in the high nibble).
Frame packets (:class:`KeyFrame`, :class:`DeltaFrame`) are then a few fixed binary fields and
a range-coded body (:mod:`facewire.protocol.channels` decodes the body); every other kind is one
msgpack array of its fields. See docs/protocol.md for the layout of each kind. Each class has
``parse(data)`` and ``__bytes__``; :func:`decode` is the one dispatch point that turns any
received bytes into a packet or raises :class:`PacketError` with a precise message.
Constructors validate their fields the same way, so a packet that can be built can be encoded
and decoded again, and ``decode(bytes(p)) == p``.

Vertices are stored as a read-only float32 array and travel as little-endian bytes. Nothing is
ever unpickled.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numbers
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self, TypeAlias

import msgpack
import numpy as np
from numpy.typing import NDArray

from facewire.protocol import mesh_code
from facewire.protocol.constants import (
    CHANNEL_AUDIO,
    CHANNEL_CONTROL,
    CHANNEL_GEOMETRY,
    CHANNEL_REM,
    CHANNEL_SNAPSHOT,
    INT64_MAX,
    INT64_MIN,
    MAX_ARRAY_LEN,
    MAX_AUDIO_BYTES,
    MAX_CHANNEL_VALUE,
    MAX_CHANNELS,
    MAX_FPS,
    MAX_FRAME_BODY,
    MAX_IMAGE_SIDE,
    MAX_MAP_LEN,
    MAX_PACKET_BYTES,
    MAX_PARAMS,
    MAX_REFRESH_SIDE,
    MAX_STR_LEN,
    MAX_VERTICES,
    MIN_FPS,
    PROTOCOL_VERSION,
    REM_CODECS,
    REM_CODES,
    REM_HUE_STEP,
    REM_REFERENCE,
    REM_REGIONS,
    REM_UNIT_STEPS,
    UINT32_MAX,
    Kind,
)
from facewire.protocol.images import ImageError, check_image

logger = logging.getLogger(__name__)


class PacketError(ValueError):
    """A packet is malformed, truncated, oversized, of unknown kind or of the wrong version."""


# --- field validation helpers (all raise PacketError naming the field) ---------------------------


def _wire_type(value: object) -> str:
    """The msgpack name of a decoded value's type, for error messages."""
    names = {list: "array", tuple: "array", dict: "map", str: "str", bytes: "bin", bool: "bool"}
    names.update({int: "int", float: "float", type(None): "nil", bytearray: "bin"})
    return names.get(type(value), type(value).__name__)


def _int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise PacketError(f"{name}: expected int, got {_wire_type(value)}")
    v = int(value)
    if not lo <= v <= hi:
        raise PacketError(f"{name}: {v} outside [{lo}, {hi}]")
    return v


def _float(name: str, value: object, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise PacketError(f"{name}: expected float, got {_wire_type(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise PacketError(f"{name}: expected a finite float, got {v}")
    if not lo <= v <= hi:
        raise PacketError(f"{name}: {v} outside [{lo}, {hi}]")
    return v


def _str(name: str, value: object, allow_empty: bool = False) -> str:
    if not isinstance(value, str):
        raise PacketError(f"{name}: expected str, got {_wire_type(value)}")
    if not value and not allow_empty:
        raise PacketError(f"{name}: must not be empty")
    if len(value.encode("utf-8", "surrogatepass")) > MAX_STR_LEN:
        raise PacketError(f"{name}: longer than {MAX_STR_LEN} bytes")
    return value


def _bytes(name: str, value: object) -> bytes:
    if not isinstance(value, (bytes, bytearray, memoryview)):
        raise PacketError(f"{name}: expected bin, got {_wire_type(value)}")
    return bytes(value)


def _image(name: str, value: object, codec: str | None = None) -> bytes:
    """An encoded image whose header is valid and within the size limits (or empty).

    Only the header is read (:func:`facewire.protocol.images.check_image`): a peer cannot make the
    decoder spend more than that, and a receiver that decodes the pixels later knows the
    image is at most MAX_IMAGE_SIDE on a side. ``codec`` ("jpeg", "png") is the one required.
    """
    data = _bytes(name, value)
    if not data:
        return data
    try:
        found, _, _ = check_image(data, name)
    except ImageError as exc:
        raise PacketError(str(exc)) from None
    if codec is not None and found != codec:
        raise PacketError(f"{name}: a {found} image, expected {codec}")
    return data


def _map(name: str, value: object) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise PacketError(f"{name}: expected map, got {_wire_type(value)}")
    if len(value) > MAX_MAP_LEN:
        raise PacketError(f"{name}: more than {MAX_MAP_LEN} entries")
    return value


def _float_map(name: str, value: object, lo: float = -math.inf) -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in _map(name, value).items():
        key = _str(f"{name} key", k)
        out[key] = _float(f"{name}[{key!r}]", v)
        if out[key] <= lo:
            raise PacketError(f"{name}[{key!r}]: must be > {lo}, got {out[key]}")
    return out


def _same(a: object, b: object) -> bool:
    """Equality that understands numpy arrays (same dtype, shape and values) inside maps."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and np.array_equal(a, b)
        )
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    return a == b


class _Packet:
    """Shared behaviour: framing, parse, equality. Subclasses are frozen dataclasses."""

    KIND: ClassVar[Kind]
    CHANNEL: ClassVar[str] = CHANNEL_CONTROL
    #: Number of msgpack fields after the header byte (at most, when the last ones are
    #: optional: MIN_FIELDS at least).
    N_FIELDS: ClassVar[int]
    MIN_FIELDS: ClassVar[int | None] = None

    def _to_fields(self) -> list[Any]:
        """Wire fields after the header byte; by default the dataclass fields in order."""
        return [getattr(self, f.name) for f in dataclasses.fields(self)]  # type: ignore[arg-type]

    @classmethod
    def _from_fields(cls, fields: list[Any]) -> Self:
        """Build from decoded wire fields; the constructor validates them."""
        return cls(*fields)

    def _body(self) -> bytes:
        data: bytes = msgpack.packb(self._to_fields(), use_bin_type=True)
        return data

    @classmethod
    def _from_body(cls, body: bytes) -> Self:
        fields = _unpack(body)
        if not isinstance(fields, list):
            raise PacketError(f"{cls.__name__}: expected a msgpack array, got {_wire_type(fields)}")
        least = cls.N_FIELDS if cls.MIN_FIELDS is None else cls.MIN_FIELDS
        if not least <= len(fields) <= cls.N_FIELDS:
            wanted = f"{least} to {cls.N_FIELDS}" if least < cls.N_FIELDS else f"{cls.N_FIELDS}"
            raise PacketError(f"{cls.__name__} needs {wanted} fields, got {len(fields)}")
        return cls._from_fields(fields)

    def __bytes__(self) -> bytes:
        data = bytes([header_byte(self.KIND)]) + self._body()
        if len(data) > MAX_PACKET_BYTES:
            raise PacketError(
                f"packet of {len(data)} bytes exceeds the limit of {MAX_PACKET_BYTES} bytes"
            )
        return data

    @classmethod
    def parse(cls, data: bytes) -> Self:
        """Decode ``data`` and check that it is a packet of this class."""
        packet = decode(data)
        if not isinstance(packet, cls):
            raise PacketError(f"expected {cls.__name__} packet, got {type(packet).__name__}")
        return packet

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(
            _same(getattr(self, f.name), getattr(other, f.name))
            for f in dataclasses.fields(self)  # type: ignore[arg-type]
        )

    __hash__ = None  # type: ignore[assignment]


def header_byte(kind: Kind) -> int:
    """The first byte of every packet: the version in the high nibble, the kind in the low."""
    return (PROTOCOL_VERSION << 4) | int(kind)


def _set(obj: object, name: str, value: object) -> None:
    object.__setattr__(obj, name, value)


# --- packet kinds ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Snapshot(_Packet):
    """The session: person-specific mesh, texture, background, camera and channel table.

    session_id : uint32, new each time a sender starts
    seq : the first frame number the snapshot is valid for
    vertices : (n, 3) float, cm, model space; vertex i is landmark i of the canonical mesh.
        Sent coded against the canonical mesh where ``meta["vertex_step"]`` gives the step in
        cm (protocol/mesh_code.py: about 1 KB at 0.1 mm), else as float16 when given as
        float16, otherwise as float32.
    texture, background : JPEG, PNG or WebP bytes (may be empty); the header must be valid
        and state at most MAX_IMAGE_SIDE pixels on a side
    channels : ``(name, size, step)`` of every frame channel, in coding order
        (protocol.channels.ChannelSpec)
    rig_hash : SHA-256 (hex) of the rig data both ends must share (models.rig.rig_hash)
    keyframe_interval : frames between keyframes
    reference : the quantised channel values of the snapshot frame itself, one tuple of ints
        per channel in table order (where the head was in the background image)
    """

    KIND: ClassVar[Kind] = Kind.SNAPSHOT
    CHANNEL: ClassVar[str] = CHANNEL_SNAPSHOT
    N_FIELDS: ClassVar[int] = 14

    session_id: int
    seq: int
    width: int
    height: int
    fps: float
    vertices: NDArray[np.floating[Any]] = field(repr=False)
    texture: bytes = field(repr=False)
    background: bytes = field(repr=False)
    channels: Sequence[tuple[str, int, float]]
    rig_hash: str
    keyframe_interval: int
    reference: Sequence[Sequence[int]]
    meta: Mapping[str, str | int | float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "session_id", _int("Snapshot.session_id", self.session_id, 0, UINT32_MAX))
        _set(self, "seq", _int("Snapshot.seq", self.seq, 0, UINT32_MAX))
        _set(self, "width", _int("Snapshot.width", self.width, 1, MAX_IMAGE_SIDE))
        _set(self, "height", _int("Snapshot.height", self.height, 1, MAX_IMAGE_SIDE))
        _set(self, "fps", _float("Snapshot.fps", self.fps, MIN_FPS, MAX_FPS))
        v = self.vertices
        if not isinstance(v, np.ndarray) or v.ndim != 2 or v.shape[1] != 3:
            got = f"shape {v.shape}" if isinstance(v, np.ndarray) else _wire_type(v)
            raise PacketError(f"Snapshot.vertices: expected (n, 3) float array, got {got}")
        if not np.issubdtype(v.dtype, np.floating):
            raise PacketError(f"Snapshot.vertices: expected a float array, got {v.dtype}")
        if not 1 <= len(v) <= MAX_VERTICES:
            raise PacketError(f"Snapshot.vertices: {len(v)} vertices outside [1, {MAX_VERTICES}]")
        verts = v.astype(np.float16 if v.dtype == np.float16 else np.float32)  # a copy
        if not np.all(np.isfinite(verts)):
            raise PacketError("Snapshot.vertices: non-finite coordinates")
        verts.flags.writeable = False
        _set(self, "vertices", verts)
        _set(self, "texture", _image("Snapshot.texture", self.texture))
        _set(self, "background", _image("Snapshot.background", self.background))
        _set(self, "channels", _channel_table("Snapshot.channels", self.channels))
        rig_hash = _str("Snapshot.rig_hash", self.rig_hash)
        if len(rig_hash) != 64 or any(c not in "0123456789abcdef" for c in rig_hash):
            raise PacketError("Snapshot.rig_hash: expected 64 lowercase hex digits (SHA-256)")
        _set(self, "rig_hash", rig_hash)
        _set(
            self,
            "keyframe_interval",
            _int("Snapshot.keyframe_interval", self.keyframe_interval, 1, 65535),
        )
        _set(self, "reference", _reference("Snapshot.reference", self.reference, self.channels))
        meta: dict[str, str | int | float] = {}
        for k, val in _map("Snapshot.meta", self.meta).items():
            key = _str("Snapshot.meta key", k)
            name = f"Snapshot.meta[{key!r}]"
            if isinstance(val, str):
                meta[key] = _str(name, val, allow_empty=True)
            elif isinstance(val, numbers.Integral) and not isinstance(val, bool):
                meta[key] = _int(name, val, INT64_MIN, INT64_MAX)
            elif isinstance(val, numbers.Real) and not isinstance(val, bool):
                meta[key] = _float(name, val)
            else:
                raise PacketError(f"{name}: expected str, int or float, got {_wire_type(val)}")
        _set(self, "meta", meta)
        if mesh_code.VERTEX_STEP in meta:
            step = meta[mesh_code.VERTEX_STEP]
            if not isinstance(step, float) or not 0 < step <= 1:
                raise PacketError(f"Snapshot.meta[{mesh_code.VERTEX_STEP!r}]: {step!r} cm")
            if len(verts) != mesh_code.vertex_count():
                raise PacketError(
                    f"Snapshot.vertices: {len(verts)} vertices coded against the canonical "
                    f"mesh's {mesh_code.vertex_count()}"
                )

    def vertex_bytes(self) -> bytes:
        """Field 7 as sent: the vertices coded (meta["vertex_step"]) or as floats."""
        step = self.meta.get(mesh_code.VERTEX_STEP)
        if isinstance(step, float):
            try:
                return mesh_code.encode(self.vertices, step)
            except mesh_code.MeshCodeError as exc:
                raise PacketError(f"Snapshot.vertices: {exc}") from None
        return self.vertices.astype("<f2" if self.vertices.dtype == np.float16 else "<f4").tobytes()

    def _to_fields(self) -> list[Any]:
        return [
            self.session_id,
            self.seq,
            self.width,
            self.height,
            self.fps,
            len(self.vertices),
            self.vertex_bytes(),
            self.texture,
            self.background,
            [list(entry) for entry in self.channels],
            self.rig_hash,
            self.keyframe_interval,
            dict(self.meta),
            [list(values) for values in self.reference],
        ]

    @classmethod
    def _from_fields(cls, f: list[Any]) -> Self:
        n = _int("Snapshot.n_vertices", f[5], 1, MAX_VERTICES)
        raw = _bytes("Snapshot.vertices", f[6])
        step = f[12].get(mesh_code.VERTEX_STEP) if isinstance(f[12], dict) else None
        if step is not None:
            step = _float(f"Snapshot.meta[{mesh_code.VERTEX_STEP!r}]", step)
            if not 0 < step <= 1 or n != mesh_code.vertex_count():
                raise PacketError(
                    f"Snapshot.vertices: {n} vertices at {step} cm steps: the code needs the "
                    f"canonical mesh's {mesh_code.vertex_count()} and a step in (0, 1]"
                )
            try:
                coded = mesh_code.decode(raw, step)
            except mesh_code.MeshCodeError as exc:
                raise PacketError(f"Snapshot.vertices: {exc}") from None
            return cls(
                f[0], f[1], f[2], f[3], f[4], coded, f[7], f[8], f[9], f[10], f[11], f[13], f[12]
            )
        if len(raw) not in (6 * n, 12 * n):
            raise PacketError(
                f"Snapshot.vertices: {len(raw)} bytes for {n} vertices "
                f"(expected {6 * n} as float16 or {12 * n} as float32)"
            )
        vertices = np.frombuffer(raw, dtype="<f2" if len(raw) == 6 * n else "<f4").reshape(n, 3)
        return cls(
            f[0], f[1], f[2], f[3], f[4], vertices, f[7], f[8], f[9], f[10], f[11], f[13], f[12]
        )


def _channel_table(name: str, value: object) -> tuple[tuple[str, int, float], ...]:
    if not isinstance(value, Sequence) or isinstance(value, (str, bytes)):
        raise PacketError(f"{name}: expected array, got {_wire_type(value)}")
    if not 1 <= len(value) <= MAX_CHANNELS:
        raise PacketError(f"{name}: {len(value)} channels outside [1, {MAX_CHANNELS}]")
    table = []
    for i, entry in enumerate(value):
        if not isinstance(entry, (list, tuple)) or len(entry) != 3:
            raise PacketError(f"{name}[{i}]: expected [name, size, step]")
        step = _float(f"{name}[{i}] step", entry[2])
        if step <= 0:
            raise PacketError(f"{name}[{i}] step: must be > 0, got {step}")
        table.append(
            (
                _str(f"{name}[{i}] name", entry[0]),
                _int(f"{name}[{i}] size", entry[1], 1, MAX_PARAMS),
                step,
            )
        )
    names = [t[0] for t in table]
    if len(set(names)) != len(names):
        raise PacketError(f"{name}: duplicate channel names")
    return tuple(table)


def _reference(
    name: str, value: object, channels: Sequence[tuple[str, int, float]]
) -> tuple[tuple[int, ...], ...]:
    if not isinstance(value, Sequence) or isinstance(value, (str, bytes)):
        raise PacketError(f"{name}: expected array, got {_wire_type(value)}")
    if len(value) != len(channels):
        raise PacketError(f"{name}: {len(value)} channels, the table has {len(channels)}")
    out = []
    for values, (channel, size, _) in zip(value, channels, strict=True):
        if not isinstance(values, Sequence) or isinstance(values, (str, bytes)):
            raise PacketError(f"{name}[{channel!r}]: expected array, got {_wire_type(values)}")
        if len(values) != size:
            raise PacketError(f"{name}[{channel!r}]: {len(values)} values, expected {size}")
        out.append(
            tuple(
                _int(f"{name}[{channel!r}]", v, -MAX_CHANNEL_VALUE, MAX_CHANNEL_VALUE)
                for v in values
            )
        )
    return tuple(out)


_KEY_HEAD = struct.Struct("<BIIq")  # counter, session_id, seq, capture_us


@dataclass(frozen=True, eq=False)
class KeyFrame(_Packet):
    """A self-contained frame: absolute channel values, coding contexts reset.

    counter : uint8, +1 (mod 256) per frame packet of the session
    session_id : uint32, the session it belongs to
    seq : uint32 frame number; capture_us : int64, sender clock, microseconds
    body : range-coded channel values (protocol.channels)
    """

    KIND: ClassVar[Kind] = Kind.KEY_FRAME
    CHANNEL: ClassVar[str] = CHANNEL_GEOMETRY

    counter: int
    session_id: int
    seq: int
    capture_us: int
    body: bytes = field(repr=False)

    def __post_init__(self) -> None:
        _set(self, "counter", _int("KeyFrame.counter", self.counter, 0, 255))
        _set(self, "session_id", _int("KeyFrame.session_id", self.session_id, 0, UINT32_MAX))
        _set(self, "seq", _int("KeyFrame.seq", self.seq, 0, UINT32_MAX))
        _set(self, "capture_us", _int("KeyFrame.capture_us", self.capture_us, INT64_MIN, INT64_MAX))
        _set(self, "body", _frame_body("KeyFrame.body", self.body))

    def _body(self) -> bytes:
        head = _KEY_HEAD.pack(self.counter, self.session_id, self.seq, self.capture_us)
        return head + self.body

    @classmethod
    def _from_body(cls, body: bytes) -> Self:
        if len(body) < _KEY_HEAD.size:
            raise _truncated("KeyFrame", len(body) + 1, _KEY_HEAD.size + 1)
        counter, session_id, seq, capture_us = _KEY_HEAD.unpack_from(body)
        return cls(counter, session_id, seq, capture_us, body[_KEY_HEAD.size :])


@dataclass(frozen=True, eq=False)
class DeltaFrame(_Packet):
    """A frame predicted from the one before: needs every packet since the last keyframe.

    counter : uint8, +1 (mod 256) per frame packet; a gap means a lost packet
    body : range-coded frame step, capture-time residual and value residuals
    """

    KIND: ClassVar[Kind] = Kind.DELTA_FRAME
    CHANNEL: ClassVar[str] = CHANNEL_GEOMETRY

    counter: int
    body: bytes = field(repr=False)

    def __post_init__(self) -> None:
        _set(self, "counter", _int("DeltaFrame.counter", self.counter, 0, 255))
        _set(self, "body", _frame_body("DeltaFrame.body", self.body))

    def _body(self) -> bytes:
        return bytes([self.counter]) + self.body

    @classmethod
    def _from_body(cls, body: bytes) -> Self:
        if not body:
            raise _truncated("DeltaFrame", 1, 2)
        return cls(body[0], body[1:])


def _truncated(kind: str, length: int, least: int) -> PacketError:
    """A binary packet cut short of its fixed fields (its body declares no length)."""
    return PacketError(
        f"truncated {kind}: {length} byte{'' if length == 1 else 's'}, needs at least {least}"
    )


def _frame_body(name: str, value: object) -> bytes:
    data = _bytes(name, value)
    if len(data) > MAX_FRAME_BODY:
        raise PacketError(f"{name}: {len(data)} bytes exceeds {MAX_FRAME_BODY}")
    return data


_AUDIO_HEAD = struct.Struct("<Iq")  # seq, capture_us


@dataclass(frozen=True, eq=False)
class AudioFrame(_Packet):
    """20 ms of sound: one Opus packet (48 kHz, mono; docs/protocol.md, AudioFrame).

    seq : uint32, the frame's place in the sender's sound, in 20 ms steps from 0; a step
        of more than one is a lost packet or silence the encoder left out (DTX), and the
        receiver conceals both the same way
    capture_us : int64, when the frame's first sample was captured, on the clock of the
        video frames' capture_us (lip sync)
    data : the Opus packet, 1 to MAX_AUDIO_BYTES bytes
    """

    KIND: ClassVar[Kind] = Kind.AUDIO_FRAME
    CHANNEL: ClassVar[str] = CHANNEL_AUDIO

    seq: int
    capture_us: int
    data: bytes = field(repr=False)

    def __post_init__(self) -> None:
        _set(self, "seq", _int("AudioFrame.seq", self.seq, 0, UINT32_MAX))
        _set(
            self, "capture_us", _int("AudioFrame.capture_us", self.capture_us, INT64_MIN, INT64_MAX)
        )
        data = _bytes("AudioFrame.data", self.data)
        if not 1 <= len(data) <= MAX_AUDIO_BYTES:
            raise PacketError(f"AudioFrame.data: {len(data)} bytes outside [1, {MAX_AUDIO_BYTES}]")
        _set(self, "data", data)

    def _body(self) -> bytes:
        return _AUDIO_HEAD.pack(self.seq, self.capture_us) + self.data

    @classmethod
    def _from_body(cls, body: bytes) -> Self:
        if len(body) < _AUDIO_HEAD.size + 1:
            raise _truncated("AudioFrame", len(body) + 1, _AUDIO_HEAD.size + 2)
        seq, capture_us = _AUDIO_HEAD.unpack_from(body)
        return cls(seq, capture_us, body[_AUDIO_HEAD.size :])


_REM_HEAD = struct.Struct("<BBIHHH")  # region, codec, seq, h_peak, s_mean, v_mean (steps)


@dataclass(frozen=True, eq=False)
class RemPatch(_Packet):
    """A region-effective-for-merging patch (e.g. the eyes) in texture (UV) space.

    seq : the frame it belongs to (drawn with that frame)
    region : REM region name, one of REM_REGIONS (models.rem lays them out)
    codec : "jpeg", "png" or "webp", data the encoded image (header valid, within
        MAX_IMAGE_SIDE); or "ref", data 4 bytes: the uint32 (little-endian, at most ``seq``)
        frame number of an earlier patch of the region whose image to show again (the
        snapshot's own frame number: the snapshot's texture), see :attr:`reference`
    h_peak : hue histogram peak, degrees [0, 360]; s_mean, v_mean : mean saturation and value
        in [0, 1] (HSV colour adaptation, seed 003 Eq. 2; s_mean or v_mean 0: none measured).
        They travel as u16 steps (REM_HUE_STEP, 1 / REM_UNIT_STEPS) and are rounded to them
        when the packet is made.

    Binary, as the frame packets: up to ten a second on a thin link, where msgpack's field
    names and float32 tags made a reference 38-45 bytes instead of 17.
    """

    KIND: ClassVar[Kind] = Kind.REM_PATCH
    CHANNEL: ClassVar[str] = CHANNEL_REM

    seq: int
    region: str
    codec: str
    data: bytes = field(repr=False)
    h_peak: float
    s_mean: float
    v_mean: float

    def __post_init__(self) -> None:
        _set(self, "seq", _int("RemPatch.seq", self.seq, 0, UINT32_MAX))
        if self.region not in REM_REGIONS:
            raise PacketError(f"RemPatch.region: unknown region {self.region!r}")
        codec = self.codec
        if codec == REM_REFERENCE:
            data = _bytes("RemPatch.data", self.data)
            if len(data) != 4:
                raise PacketError(f"RemPatch.data: a reference is 4 bytes, got {len(data)}")
            if struct.unpack("<I", data)[0] > self.seq:
                raise PacketError("RemPatch.data: a reference to a later frame than its own")
        elif codec in REM_CODECS:
            data = _image("RemPatch.data", self.data, codec)
            if not data:
                raise PacketError("RemPatch.data: must not be empty")
        else:
            raise PacketError(f"RemPatch.codec: unknown codec {codec!r} (known: {REM_CODES})")
        _set(self, "data", data)
        hue = _float("RemPatch.h_peak", self.h_peak, 0.0, 360.0)
        _set(self, "h_peak", round(hue / REM_HUE_STEP) * REM_HUE_STEP)
        for name in ("s_mean", "v_mean"):
            value = _float(f"RemPatch.{name}", getattr(self, name), 0.0, 1.0)
            _set(self, name, round(value * REM_UNIT_STEPS) / REM_UNIT_STEPS)

    @classmethod
    def referring(
        cls, seq: int, region: str, key: int, h_peak: float, s_mean: float, v_mean: float
    ) -> RemPatch:
        """A patch that shows region's image of the patch of frame ``key`` again."""
        return cls(seq, region, REM_REFERENCE, struct.pack("<I", key), h_peak, s_mean, v_mean)

    @property
    def reference(self) -> int | None:
        """The frame number a "ref" patch refers to (None for an image)."""
        if self.codec != REM_REFERENCE:
            return None
        return int(struct.unpack("<I", self.data)[0])

    def _body(self) -> bytes:
        head = _REM_HEAD.pack(
            REM_REGIONS.index(self.region), REM_CODES.index(self.codec), self.seq,
            round(self.h_peak / REM_HUE_STEP), round(self.s_mean * REM_UNIT_STEPS),
            round(self.v_mean * REM_UNIT_STEPS),
        )  # fmt: skip
        return head + self.data

    @classmethod
    def _from_body(cls, body: bytes) -> Self:
        if len(body) < _REM_HEAD.size + 1:
            raise _truncated("RemPatch", len(body) + 1, _REM_HEAD.size + 2)
        region, codec, seq, hue, s, v = _REM_HEAD.unpack_from(body)
        if region >= len(REM_REGIONS):
            raise PacketError(f"RemPatch.region: unknown region {region}")
        if codec >= len(REM_CODES):
            raise PacketError(f"RemPatch.codec: unknown codec {codec}")
        return cls(
            seq, REM_REGIONS[region], REM_CODES[codec], body[_REM_HEAD.size :],
            hue * REM_HUE_STEP, s / REM_UNIT_STEPS, v / REM_UNIT_STEPS,
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class Refresh(_Packet):
    """A part of the camera's picture that the model does not show (a hand raised, an object,
    the scene uncovered), shown over the receiver's picture from frame ``seq`` on.

    x, y, width, height : the area of the frame it covers, pixels (x, y its top-left corner)
    codec : "jpeg", "png" or "webp", data the image (any size: it is scaled to the area); or
        codec "" and data empty: the area shows the model's picture again
    over : 1 to show it over the drawn face too (a hand in front of the face), 0 under it; on
        the wire only when 1 (an eighth field)
    """

    KIND: ClassVar[Kind] = Kind.REFRESH
    CHANNEL: ClassVar[str] = CHANNEL_REM
    N_FIELDS: ClassVar[int] = 8
    MIN_FIELDS: ClassVar[int | None] = 7

    seq: int
    x: int
    y: int
    width: int
    height: int
    codec: str
    data: bytes = field(repr=False)
    over: int = 0

    def __post_init__(self) -> None:
        _set(self, "seq", _int("Refresh.seq", self.seq, 0, UINT32_MAX))
        _set(self, "over", _int("Refresh.over", self.over, 0, 1))
        _set(self, "x", _int("Refresh.x", self.x, 0, MAX_REFRESH_SIDE - 1))
        _set(self, "y", _int("Refresh.y", self.y, 0, MAX_REFRESH_SIDE - 1))
        _set(self, "width", _int("Refresh.width", self.width, 1, MAX_REFRESH_SIDE))
        _set(self, "height", _int("Refresh.height", self.height, 1, MAX_REFRESH_SIDE))
        codec = _str("Refresh.codec", self.codec, allow_empty=True)
        if codec:
            if codec not in REM_CODECS:
                raise PacketError(f"Refresh.codec: unknown codec {codec!r} (known: {REM_CODECS})")
            data = _image("Refresh.data", self.data, codec)
            if not data:
                raise PacketError("Refresh.data: must not be empty")
        else:
            data = _bytes("Refresh.data", self.data)
            if data:
                raise PacketError("Refresh.data: an image needs a codec")
        _set(self, "data", data)

    @property
    def clears(self) -> bool:
        """Whether it gives its area back to the model's picture."""
        return not self.codec

    def _to_fields(self) -> list[Any]:
        fields = super()._to_fields()
        return fields if self.over else fields[:-1]  # seven fields, as before ``over``


@dataclass(frozen=True, eq=False)
class KeyframeRequest(_Packet):
    """Receiver -> sender: please send a keyframe; seq is the last frame decoded (or 0)."""

    KIND: ClassVar[Kind] = Kind.KEYFRAME_REQUEST
    N_FIELDS: ClassVar[int] = 1

    seq: int

    def __post_init__(self) -> None:
        _set(self, "seq", _int("KeyframeRequest.seq", self.seq, 0, UINT32_MAX))


@dataclass(frozen=True, eq=False)
class Heartbeat(_Packet):
    """Liveness. Published by the sender when idle; sent upstream by a receiver as a probe.

    session_id : the sender's session (a receiver's probe carries the one it joined, or 0)
    seq : last frame sequence number published (sender) or received (receiver)
    sent_us : int64, sender's clock, microseconds
    """

    KIND: ClassVar[Kind] = Kind.HEARTBEAT
    N_FIELDS: ClassVar[int] = 3

    session_id: int
    seq: int
    sent_us: int

    def __post_init__(self) -> None:
        _set(self, "session_id", _int("Heartbeat.session_id", self.session_id, 0, UINT32_MAX))
        _set(self, "seq", _int("Heartbeat.seq", self.seq, 0, UINT32_MAX))
        _set(self, "sent_us", _int("Heartbeat.sent_us", self.sent_us, INT64_MIN, INT64_MAX))


@dataclass(frozen=True, eq=False)
class ReceiverStats(_Packet):
    """Receiver -> sender: named statistics (e.g. "fps", "latency_ms_p50"), finite floats."""

    KIND: ClassVar[Kind] = Kind.RECEIVER_STATS
    N_FIELDS: ClassVar[int] = 1

    values: Mapping[str, float]

    def __post_init__(self) -> None:
        _set(self, "values", _float_map("ReceiverStats.values", self.values))


@dataclass(frozen=True, eq=False)
class Bye(_Packet):
    """The sender ends the session after frame ``seq``."""

    KIND: ClassVar[Kind] = Kind.BYE
    N_FIELDS: ClassVar[int] = 1

    seq: int

    def __post_init__(self) -> None:
        _set(self, "seq", _int("Bye.seq", self.seq, 0, UINT32_MAX))


@dataclass(frozen=True, eq=False)
class SnapshotRequest(_Packet):
    """Receiver -> sender: send me the current Snapshot (the transport's handshake)."""

    KIND: ClassVar[Kind] = Kind.SNAPSHOT_REQUEST
    N_FIELDS: ClassVar[int] = 0


@dataclass(frozen=True, eq=False)
class MediaKey(_Packet):
    """Sender -> receiver, just before the Snapshot: the secret of the media datagrams.

    key_id : 0-255, byte 1 of every datagram sealed with it (protocol/datagram.py)
    secret : 32 bytes; HKDF makes each direction's key and salt from it
    udp : 1 if the sender takes datagrams (it may send the media as datagrams), 0 if not
    """

    KIND: ClassVar[Kind] = Kind.MEDIA_KEY
    N_FIELDS: ClassVar[int] = 3

    key_id: int
    secret: bytes
    udp: int

    def __post_init__(self) -> None:
        _set(self, "key_id", _int("MediaKey.key_id", self.key_id, 0, 255))
        secret = _bytes("MediaKey.secret", self.secret)
        if len(secret) != 32:
            raise PacketError(f"MediaKey.secret: expected 32 bytes, got {len(secret)}")
        _set(self, "secret", secret)
        _set(self, "udp", _int("MediaKey.udp", self.udp, 0, 1))


Packet: TypeAlias = (
    Snapshot
    | KeyFrame
    | DeltaFrame
    | RemPatch
    | KeyframeRequest
    | Heartbeat
    | ReceiverStats
    | Bye
    | SnapshotRequest
    | AudioFrame
    | MediaKey
    | Refresh
)

_BY_KIND: dict[int, type[_Packet]] = {
    int(c.KIND): c
    for c in (
        Snapshot,
        KeyFrame,
        DeltaFrame,
        RemPatch,
        KeyframeRequest,
        Heartbeat,
        ReceiverStats,
        Bye,
        SnapshotRequest,
        AudioFrame,
        MediaKey,
        Refresh,
    )
}


def _pairs(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    """msgpack map hook: keys must be unique strings."""
    out: dict[Any, Any] = {}
    for k, v in pairs:
        if not isinstance(k, str):
            raise PacketError(f"map key must be str, got {_wire_type(k)}")
        if k in out:
            raise PacketError(f"duplicate map key {k!r}")
        out[k] = v
    return out


def _unpack(data: bytes) -> Any:
    """One strict msgpack value (limits on every length, no ext types, str keys only)."""
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            object_pairs_hook=_pairs,
            max_bin_len=MAX_PACKET_BYTES,
            max_str_len=MAX_STR_LEN,
            max_array_len=MAX_ARRAY_LEN,
            max_map_len=MAX_MAP_LEN,
            max_ext_len=0,
        )
    except PacketError:
        raise
    except msgpack.ExtraData as exc:
        raise PacketError(f"{len(exc.extra)} trailing bytes after the packet") from None
    except msgpack.exceptions.StackError:
        raise PacketError("malformed msgpack: nesting too deep") from None
    except msgpack.FormatError:
        raise PacketError("malformed msgpack: invalid type byte") from None
    except ValueError as exc:  # msgpack limits, invalid UTF-8, incomplete input
        if "incomplete input" in str(exc):
            raise PacketError(f"truncated packet ({len(data) + 1} bytes)") from None
        raise PacketError(f"malformed msgpack: {exc}") from None
    except Exception as exc:  # anything else msgpack may raise on hostile input
        raise PacketError(f"malformed msgpack: {type(exc).__name__}") from None


def decode(data: bytes) -> Packet:
    """Decode one packet; the only entry point for received bytes.

    Raises :class:`PacketError` with a precise message for empty, oversized, truncated,
    malformed, wrong-version, unknown-kind or badly typed input.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise PacketError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    n = len(data)
    if n == 0:
        raise PacketError("empty packet")
    if n > MAX_PACKET_BYTES:
        raise PacketError(f"packet of {n} bytes exceeds the limit of {MAX_PACKET_BYTES} bytes")
    version, kind = data[0] >> 4, data[0] & 0x0F
    if 0x90 <= data[0] <= 0x9F and n > 1 and data[1] == 1:
        # A msgpack array whose first element is 1: the version-1 framing.
        raise PacketError(f"unsupported protocol version 1 (this peer speaks {PROTOCOL_VERSION})")
    if version != PROTOCOL_VERSION:
        raise PacketError(
            f"unsupported protocol version {version} (header byte 0x{data[0]:02x}; "
            f"this peer speaks {PROTOCOL_VERSION})"
        )
    if kind not in _BY_KIND:
        raise PacketError(f"unknown packet kind {kind}")
    return _BY_KIND[kind]._from_body(data[1:])  # type: ignore[return-value]
