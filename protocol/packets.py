"""Wire packets: small frozen dataclasses, msgpack framing, one strict decoder.

Every packet is one msgpack array ``[version, kind, field, ...]`` (see docs/protocol.md for the
layout of each kind). Each class has ``parse(data)`` and ``__bytes__``; :func:`decode` is the
one dispatch point that turns any received bytes into a packet or raises :class:`PacketError`
with a precise message. Constructors validate their fields the same way, so a packet that can
be built can be encoded and decoded again, and ``decode(bytes(p)) == p``.

Arrays are stored as read-only numpy arrays (int16 parameters, float32 vertices) and travel as
little-endian bytes. Nothing is ever unpickled.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self, TypeAlias

import msgpack
import numpy as np
from numpy.typing import NDArray

from protocol.constants import (
    CHANNEL_CONTROL,
    CHANNEL_GEOMETRY,
    CHANNEL_REM,
    CHANNEL_SNAPSHOT,
    INT64_MAX,
    INT64_MIN,
    JPEG_MAGIC,
    MAX_ARRAY_LEN,
    MAX_CTRL,
    MAX_IMAGE_SIDE,
    MAX_MAP_LEN,
    MAX_PACKET_BYTES,
    MAX_PARAMS,
    MAX_STR_LEN,
    MAX_VERTICES,
    PNG_MAGIC,
    PROTOCOL_VERSION,
    REM_CODECS,
    UINT32_MAX,
    Kind,
)

logger = logging.getLogger(__name__)

POSE_LEN = 8  # [qx, qy, qz, qw, s, tx, ty, tz], see protocol.quant


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


def _image(name: str, value: object) -> bytes:
    data = _bytes(name, value)
    if data and not (data.startswith(JPEG_MAGIC) or data.startswith(PNG_MAGIC)):
        raise PacketError(f"{name}: neither JPEG nor PNG (starts with {data[:8].hex()})")
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


def _int16_array(name: str, value: object, shape: tuple[int, ...] | None = None) -> NDArray[Any]:
    if not isinstance(value, np.ndarray) or value.dtype != np.int16 or value.ndim != 1:
        got = (
            f"{value.dtype} array of shape {value.shape}"
            if isinstance(value, np.ndarray)
            else _wire_type(value)
        )
        raise PacketError(f"{name}: expected 1-D int16 array, got {got}")
    if shape is not None and value.shape != shape:
        raise PacketError(f"{name}: expected shape {shape}, got {value.shape}")
    if value.size > MAX_PARAMS:
        raise PacketError(f"{name}: more than {MAX_PARAMS} values")
    out = value.copy()
    out.flags.writeable = False
    return out


def _int16_from_wire(name: str, value: object) -> NDArray[np.int16]:
    data = _bytes(name, value)
    if len(data) % 2:
        raise PacketError(f"{name}: odd length {len(data)} for int16 data")
    return np.frombuffer(data, dtype="<i2").astype(np.int16)


def _int16_to_wire(array: NDArray[Any]) -> bytes:
    return array.astype("<i2").tobytes()


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
    #: Number of wire fields after ``[version, kind]``.
    N_FIELDS: ClassVar[int]

    def _to_fields(self) -> list[Any]:
        """Wire fields after [version, kind]; by default the dataclass fields in order."""
        return [getattr(self, f.name) for f in dataclasses.fields(self)]  # type: ignore[arg-type]

    @classmethod
    def _from_fields(cls, fields: list[Any]) -> Self:
        """Build from decoded wire fields; the constructor validates them."""
        return cls(*fields)

    def __bytes__(self) -> bytes:
        data: bytes = msgpack.packb(
            [PROTOCOL_VERSION, int(self.KIND), *self._to_fields()], use_bin_type=True
        )
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


def _set(obj: object, name: str, value: object) -> None:
    object.__setattr__(obj, name, value)


# --- packet kinds ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Snapshot(_Packet):
    """The session: person-specific mesh, texture, background, camera and quantisation tables.

    vertices : (n, 3) float, cm, model space (stored and sent as float32); vertex i is
        landmark i of the canonical mesh
    texture, background : JPEG or PNG bytes (may be empty)
    quant : parameter group name -> quantisation step (see protocol.constants.QUANT_*)
    wire_layout : (curve name, number of control points) in the order of Frame.params
    """

    KIND: ClassVar[Kind] = Kind.SNAPSHOT
    CHANNEL: ClassVar[str] = CHANNEL_SNAPSHOT
    N_FIELDS: ClassVar[int] = 13

    session_id: int
    seq: int
    width: int
    height: int
    fps: float
    vertices: NDArray[np.floating[Any]] = field(repr=False)
    texture: bytes = field(repr=False)
    background: bytes = field(repr=False)
    quant: Mapping[str, float]
    wire_layout: Sequence[tuple[str, int]]
    rig_version: int
    meta: Mapping[str, str | int | float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "session_id", _int("Snapshot.session_id", self.session_id, 0, INT64_MAX))
        _set(self, "seq", _int("Snapshot.seq", self.seq, 0, UINT32_MAX))
        _set(self, "width", _int("Snapshot.width", self.width, 1, MAX_IMAGE_SIDE))
        _set(self, "height", _int("Snapshot.height", self.height, 1, MAX_IMAGE_SIDE))
        fps = _float("Snapshot.fps", self.fps)
        if fps <= 0:
            raise PacketError(f"Snapshot.fps: must be > 0, got {fps}")
        _set(self, "fps", fps)
        v = self.vertices
        if not isinstance(v, np.ndarray) or v.ndim != 2 or v.shape[1] != 3:
            got = f"shape {v.shape}" if isinstance(v, np.ndarray) else _wire_type(v)
            raise PacketError(f"Snapshot.vertices: expected (n, 3) float array, got {got}")
        if not np.issubdtype(v.dtype, np.floating):
            raise PacketError(f"Snapshot.vertices: expected a float array, got {v.dtype}")
        if not 1 <= len(v) <= MAX_VERTICES:
            raise PacketError(f"Snapshot.vertices: {len(v)} vertices outside [1, {MAX_VERTICES}]")
        verts = v.astype(np.float32)  # always a copy
        if not np.all(np.isfinite(verts)):
            raise PacketError("Snapshot.vertices: non-finite coordinates")
        verts.flags.writeable = False
        _set(self, "vertices", verts)
        _set(self, "texture", _image("Snapshot.texture", self.texture))
        _set(self, "background", _image("Snapshot.background", self.background))
        _set(self, "quant", _float_map("Snapshot.quant", self.quant, lo=0.0))
        if not isinstance(self.wire_layout, Sequence) or isinstance(self.wire_layout, str):
            raise PacketError(
                f"Snapshot.wire_layout: expected array, got {_wire_type(self.wire_layout)}"
            )
        layout = []
        for i, entry in enumerate(self.wire_layout):
            if not isinstance(entry, (list, tuple)) or len(entry) != 2:
                raise PacketError(f"Snapshot.wire_layout[{i}]: expected [name, n_ctrl]")
            layout.append(
                (
                    _str(f"Snapshot.wire_layout[{i}] name", entry[0]),
                    _int(f"Snapshot.wire_layout[{i}] n_ctrl", entry[1], 1, MAX_CTRL),
                )
            )
        _set(self, "wire_layout", tuple(layout))
        _set(self, "rig_version", _int("Snapshot.rig_version", self.rig_version, 0, UINT32_MAX))
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

    def _to_fields(self) -> list[Any]:
        return [
            self.session_id,
            self.seq,
            self.width,
            self.height,
            self.fps,
            len(self.vertices),
            self.vertices.astype("<f4").tobytes(),
            self.texture,
            self.background,
            dict(self.quant),
            [list(entry) for entry in self.wire_layout],
            self.rig_version,
            dict(self.meta),
        ]

    @classmethod
    def _from_fields(cls, f: list[Any]) -> Self:
        n = _int("Snapshot.n_vertices", f[5], 1, MAX_VERTICES)
        raw = _bytes("Snapshot.vertices", f[6])
        if len(raw) != 12 * n:
            raise PacketError(
                f"Snapshot.vertices: {len(raw)} bytes for {n} vertices (expected {12 * n})"
            )
        vertices = np.frombuffer(raw, dtype="<f4").reshape(n, 3)
        return cls(f[0], f[1], f[2], f[3], f[4], vertices, f[7], f[8], f[9], f[10], f[11], f[12])


@dataclass(frozen=True, eq=False)
class Frame(_Packet):
    """One video frame's parameters.

    seq : uint32 frame sequence number
    capture_us : int64, sender clock, microseconds
    key : True for a keyframe (self-contained), False for a delta frame
    pose : (8,) int16 ``[qx, qy, qz, qw, s, tx, ty, tz]`` (protocol.quant.encode_pose)
    params : (m,) int16 quantised wire parameters, in Snapshot.wire_layout order
    channels : later parameter groups (e.g. "gde", "mouth"), name -> (k,) int16
    """

    KIND: ClassVar[Kind] = Kind.FRAME
    CHANNEL: ClassVar[str] = CHANNEL_GEOMETRY
    N_FIELDS: ClassVar[int] = 6

    seq: int
    capture_us: int
    key: bool
    pose: NDArray[np.int16]
    params: NDArray[np.int16]
    channels: Mapping[str, NDArray[np.int16]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "seq", _int("Frame.seq", self.seq, 0, UINT32_MAX))
        _set(self, "capture_us", _int("Frame.capture_us", self.capture_us, INT64_MIN, INT64_MAX))
        if not isinstance(self.key, (bool, np.bool_)):
            raise PacketError(f"Frame.key: expected bool, got {_wire_type(self.key)}")
        _set(self, "key", bool(self.key))
        _set(self, "pose", _int16_array("Frame.pose", self.pose, (POSE_LEN,)))
        _set(self, "params", _int16_array("Frame.params", self.params))
        channels = {}
        for k, v in _map("Frame.channels", self.channels).items():
            key = _str("Frame.channels key", k)
            channels[key] = _int16_array(f"Frame.channels[{key!r}]", v)
        _set(self, "channels", channels)

    def _to_fields(self) -> list[Any]:
        return [
            self.seq,
            self.capture_us,
            self.key,
            _int16_to_wire(self.pose),
            _int16_to_wire(self.params),
            {k: _int16_to_wire(v) for k, v in self.channels.items()},
        ]

    @classmethod
    def _from_fields(cls, f: list[Any]) -> Self:
        channels = {
            k: _int16_from_wire(f"Frame.channels[{k!r}]", v)
            for k, v in _map("Frame.channels", f[5]).items()
        }
        return cls(
            f[0],
            f[1],
            f[2],
            _int16_from_wire("Frame.pose", f[3]),
            _int16_from_wire("Frame.params", f[4]),
            channels,
        )


@dataclass(frozen=True, eq=False)
class RemPatch(_Packet):
    """A region-effective-for-merging patch (e.g. the eyes) in texture (UV) space.

    region : REM region name from the rig
    codec : "jpeg" or "png"; data : the encoded image
    h_peak : hue histogram peak, degrees [0, 360]; s_mean, v_mean : mean saturation and value
    in [0, 1] (HSV colour adaptation, seed 003 Eq. 2)
    """

    KIND: ClassVar[Kind] = Kind.REM_PATCH
    CHANNEL: ClassVar[str] = CHANNEL_REM
    N_FIELDS: ClassVar[int] = 7

    seq: int
    region: str
    codec: str
    data: bytes = field(repr=False)
    h_peak: float
    s_mean: float
    v_mean: float

    def __post_init__(self) -> None:
        _set(self, "seq", _int("RemPatch.seq", self.seq, 0, UINT32_MAX))
        _set(self, "region", _str("RemPatch.region", self.region))
        codec = _str("RemPatch.codec", self.codec)
        if codec not in REM_CODECS:
            raise PacketError(f"RemPatch.codec: unknown codec {codec!r} (known: {REM_CODECS})")
        data = _bytes("RemPatch.data", self.data)
        magic = JPEG_MAGIC if codec == "jpeg" else PNG_MAGIC
        if not data.startswith(magic):
            raise PacketError(f"RemPatch.data: not a {codec} image")
        _set(self, "data", data)
        _set(self, "h_peak", _float("RemPatch.h_peak", self.h_peak, 0.0, 360.0))
        _set(self, "s_mean", _float("RemPatch.s_mean", self.s_mean, 0.0, 1.0))
        _set(self, "v_mean", _float("RemPatch.v_mean", self.v_mean, 0.0, 1.0))


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

    seq : last frame sequence number published (sender) or received (receiver)
    sent_us : int64, sender's clock, microseconds
    """

    KIND: ClassVar[Kind] = Kind.HEARTBEAT
    N_FIELDS: ClassVar[int] = 2

    seq: int
    sent_us: int

    def __post_init__(self) -> None:
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


Packet: TypeAlias = (
    Snapshot
    | Frame
    | RemPatch
    | KeyframeRequest
    | Heartbeat
    | ReceiverStats
    | Bye
    | SnapshotRequest
)

_BY_KIND: dict[int, type[_Packet]] = {
    int(c.KIND): c
    for c in (
        Snapshot,
        Frame,
        RemPatch,
        KeyframeRequest,
        Heartbeat,
        ReceiverStats,
        Bye,
        SnapshotRequest,
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


def decode(data: bytes) -> Packet:
    """Decode one packet; the only entry point for received bytes.

    Raises :class:`PacketError` with a precise message for empty, oversized, truncated,
    malformed, wrong-version, unknown-kind or badly typed input.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise PacketError(f"expected bytes, got {type(data).__name__}")
    n = len(data)
    if n == 0:
        raise PacketError("empty packet")
    if n > MAX_PACKET_BYTES:
        raise PacketError(f"packet of {n} bytes exceeds the limit of {MAX_PACKET_BYTES} bytes")
    try:
        obj = msgpack.unpackb(
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
            raise PacketError(f"truncated packet ({n} bytes)") from None
        raise PacketError(f"malformed msgpack: {exc}") from None
    if not isinstance(obj, list):
        raise PacketError(f"packet must be a msgpack array, got {_wire_type(obj)}")
    if len(obj) < 2:
        raise PacketError(f"packet header needs [version, kind], got {len(obj)} element(s)")
    version, kind = obj[0], obj[1]
    if type(version) is not int:
        raise PacketError(f"protocol version must be an int, got {_wire_type(version)}")
    if version != PROTOCOL_VERSION:
        raise PacketError(
            f"unsupported protocol version {version} (this peer speaks {PROTOCOL_VERSION})"
        )
    if type(kind) is not int or kind not in _BY_KIND:
        raise PacketError(f"unknown packet kind {kind!r}")
    cls = _BY_KIND[kind]
    fields = obj[2:]
    if len(fields) != cls.N_FIELDS:
        raise PacketError(f"{cls.__name__} needs {cls.N_FIELDS} fields, got {len(fields)}")
    return cls._from_fields(fields)  # type: ignore[return-value]
