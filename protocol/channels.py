"""Channel coding of frame parameters: prediction, keyframes, adaptive entropy coding.

Every group of per-frame parameters is a *channel*: a name, a number of integer values and a
quantisation step, listed in the session's snapshot (:class:`ChannelSpec`). Pose, wire basis
coefficients and any later group (GDEs, lips, REM appearance) travel through the same code
path, so a new channel costs one table entry.

Per frame the sender hands integer values to :class:`ChannelEncoder`, which makes

- a :class:`~facewire.protocol.packets.KeyFrame` every ``keyframe_interval`` frames and on request:
  absolute values, all coding contexts reset, decodable on its own;
- otherwise a :class:`~facewire.protocol.packets.DeltaFrame`: each value predicted by the previous
  frame's, the residuals coded with adaptive contexts that live from one keyframe to the next;
- or nothing, when no value changed (the receiver keeps showing the last frame), for at most
  ``MAX_SEQ_STEP - 1`` frames in a row.

:class:`ChannelDecoder` mirrors it. A delta frame is decodable only if every packet since the
last keyframe arrived: the one-byte packet counter tells, and a gap raises :class:`ChainBroken`
until the next keyframe. docs/protocol.md section 5 specifies the body bit for bit.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from facewire.protocol.constants import (
    INT64_MAX,
    INT64_MIN,
    MAX_CHANNEL_VALUE,
    MAX_SEQ_STEP,
    MAX_TIME_RESIDUAL_MS,
    UINT32_MAX,
)
from facewire.protocol.packets import DeltaFrame, KeyFrame, PacketError
from facewire.protocol.rangecoder import (
    Decoder,
    Encoder,
    IntContexts,
    decode_sint,
    decode_uint,
    encode_sint,
    encode_uint,
)

logger = logging.getLogger(__name__)

COUNTER_MOD = 256


class ChainBroken(Exception):
    """A delta frame whose predecessor never arrived: wait for (and ask for) a keyframe."""


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: ``size`` integers, each meaning ``value * step`` in the channel's units."""

    name: str
    size: int
    step: float

    def __post_init__(self) -> None:
        if not self.name or self.size < 1 or not (np.isfinite(self.step) and self.step > 0):
            raise ValueError(f"invalid channel {self.name!r}: size {self.size}, step {self.step}")


@dataclass(frozen=True, eq=False)
class FrameValues:
    """One frame's quantised channel values, as both ends see them.

    seq : frame sequence number; capture_us : capture time, sender clock, microseconds
    values : channel name -> (size,) int64, in the order of the session's channel table
    key : True when it came in a keyframe
    """

    seq: int
    capture_us: int
    values: Mapping[str, NDArray[np.int64]]
    key: bool = False

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FrameValues):
            return NotImplemented
        return (
            (self.seq, self.capture_us, self.key) == (other.seq, other.capture_us, other.key)
            and list(self.values) == list(other.values)
            and all(np.array_equal(self.values[k], other.values[k]) for k in self.values)
        )

    __hash__ = None  # type: ignore[assignment]


class _Contexts:
    """All adaptive contexts of one session between two keyframes."""

    def __init__(self, specs: Sequence[ChannelSpec]) -> None:
        self.seq_step = IntContexts()
        self.time = IntContexts()
        # Keyframes: one context set per channel (values differ, their statistics are alike);
        # deltas: one per value (each coefficient moves in its own way).
        self.key = {s.name: IntContexts() for s in specs}
        self.delta = {s.name: [IntContexts() for _ in range(s.size)] for s in specs}


class _Codec:
    def __init__(self, specs: Sequence[ChannelSpec], frame_us: int) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names) or not specs:
            raise ValueError(f"channel names must be unique and at least one: {names}")
        if frame_us < 1:
            raise ValueError(f"frame interval must be >= 1 us, got {frame_us}")
        self.specs = tuple(specs)
        self.frame_us = int(frame_us)
        self._ctx = _Contexts(self.specs)
        self.last: FrameValues | None = None
        self._counter = 0

    def _reset(self) -> None:
        self._ctx = _Contexts(self.specs)


class ChannelEncoder(_Codec):
    """The sender's half: integer channel values in, frame packets out.

    ``session_id`` goes into keyframes; ``frame_us`` is the nominal frame interval that
    predicts capture times. :attr:`coded_bits` adds up, for measuring, the information coded
    in frame bodies: per channel in delta frames, ``"step and time"`` of delta frames, and
    ``"keyframes"`` (whole keyframe bodies), in bits before rounding to bytes.
    """

    def __init__(
        self,
        specs: Sequence[ChannelSpec],
        frame_us: int,
        session_id: int,
        keyframe_interval: int,
    ) -> None:
        super().__init__(specs, frame_us)
        if keyframe_interval < 1:
            raise ValueError(f"keyframe interval must be >= 1, got {keyframe_interval}")
        self.session_id = session_id
        self.keyframe_interval = keyframe_interval
        self._key_requested = True
        self._last_key_seq = 0
        self.coded_bits: dict[str, float] = {}

    def _count(self, what: str, bits: float) -> None:
        self.coded_bits[what] = self.coded_bits.get(what, 0.0) + bits

    def request_keyframe(self) -> None:
        """Make the next frame a keyframe (a receiver asked, or a new one joined)."""
        self._key_requested = True

    def keyframe_due(self, seq: int) -> bool:
        """Whether frame ``seq`` would go as a keyframe (the first, one asked for, the
        periodic one, or one after a step too long for a delta frame)."""
        last = self.last
        return (
            last is None
            or self._key_requested
            or seq - self._last_key_seq >= self.keyframe_interval
            or not 0 < seq - last.seq <= MAX_SEQ_STEP
        )

    def _check(self, values: Mapping[str, NDArray[np.integer]]) -> dict[str, NDArray[np.int64]]:
        out = {}
        for spec in self.specs:
            if spec.name not in values:
                raise ValueError(f"missing channel {spec.name!r}")
            v = np.asarray(values[spec.name])
            if v.shape != (spec.size,) or not np.issubdtype(v.dtype, np.integer):
                raise ValueError(
                    f"channel {spec.name!r}: expected ({spec.size},) integers, "
                    f"got {v.dtype} array of shape {v.shape}"
                )
            if np.any(np.abs(v) > MAX_CHANNEL_VALUE):
                raise ValueError(f"channel {spec.name!r}: values beyond +-{MAX_CHANNEL_VALUE}")
            out[spec.name] = v.astype(np.int64)
        if set(values) - set(out):
            raise ValueError(f"unknown channels {sorted(set(values) - set(out))}")
        return out

    def encode(
        self,
        seq: int,
        capture_us: int,
        values: Mapping[str, NDArray[np.integer]],
        force: bool = False,
    ) -> tuple[KeyFrame | DeltaFrame | None, FrameValues]:
        """The packet for frame ``seq`` (None: nothing changed) and what the receiver rebuilds.

        With ``force`` there is a packet even when nothing changed (the frame has to be
        drawn: a REM patch goes with it).

        Frame numbers must increase (up to 2^32 - 1). The capture time the receiver rebuilds
        is rounded to the millisecond against its prediction from the previous frame; one
        further than MAX_TIME_RESIDUAL_MS from it goes in a keyframe, exactly.
        """
        if not 0 <= seq <= UINT32_MAX or not INT64_MIN <= capture_us <= INT64_MAX:
            raise ValueError(f"frame {seq} at {capture_us} us: seq is uint32, the time int64")
        vals = self._check(values)
        last = self.last
        if last is None or self.keyframe_due(seq):
            return self._keyframe(seq, capture_us, vals)
        step = seq - last.seq
        residuals = {n: vals[n] - last.values[n] for n in vals}
        if step < MAX_SEQ_STEP and not force and not any(r.any() for r in residuals.values()):
            return None, FrameValues(seq, last.capture_us + step * self.frame_us, last.values)
        predicted = last.capture_us + step * self.frame_us
        residual_ms = round((capture_us - predicted) / 1000)
        if abs(residual_ms) > MAX_TIME_RESIDUAL_MS:  # the clock jumped: send the time itself
            return self._keyframe(seq, capture_us, vals)
        enc = Encoder()
        encode_uint(enc, step - 1, self._ctx.seq_step)
        encode_sint(enc, residual_ms, self._ctx.time)
        self._count("step and time", enc.bits)
        for spec in self.specs:
            ctx = self._ctx.delta[spec.name]
            start = enc.bits
            for i, r in enumerate(residuals[spec.name].tolist()):
                encode_sint(enc, r, ctx[i])
            self._count(spec.name, enc.bits - start)
        self._counter = (self._counter + 1) % COUNTER_MOD
        packet = DeltaFrame(self._counter, enc.finish())
        self.last = FrameValues(seq, predicted + 1000 * residual_ms, vals)
        return packet, self.last

    def _keyframe(
        self, seq: int, capture_us: int, vals: dict[str, NDArray[np.int64]]
    ) -> tuple[KeyFrame, FrameValues]:
        self._reset()
        enc = Encoder()
        for spec in self.specs:
            ctx = self._ctx.key[spec.name]
            for v in vals[spec.name].tolist():
                encode_sint(enc, v, ctx)
        self._count("keyframes", enc.bits)
        self._counter = (self._counter + 1) % COUNTER_MOD
        packet = KeyFrame(self._counter, self.session_id, seq, capture_us, enc.finish())
        self._key_requested = False
        self._last_key_seq = seq
        self.last = FrameValues(seq, capture_us, vals, key=True)
        return packet, self.last


class ChannelDecoder(_Codec):
    """The receiver's half: frame packets in, channel values out."""

    def __init__(self, specs: Sequence[ChannelSpec], frame_us: int) -> None:
        super().__init__(specs, frame_us)
        self._intact = False

    @property
    def intact(self) -> bool:
        """True when the next delta frame can be decoded (no gap since the last keyframe)."""
        return self._intact

    def decode(self, packet: KeyFrame | DeltaFrame) -> FrameValues:
        """Values of ``packet``.

        Raises :class:`ChainBroken` for a delta frame after a gap (until the next keyframe),
        and :class:`~facewire.protocol.packets.PacketError` for a body that does not decode; either
        way the chain stays broken until a keyframe arrives.
        """
        expected = (self._counter + 1) % COUNTER_MOD
        self._counter = packet.counter
        if isinstance(packet, KeyFrame):
            self._intact = False
            self._reset()
            self.last = self._decode_key(packet)
            self._intact = True
            return self.last
        if not self._intact or packet.counter != expected or self.last is None:
            self._intact = False
            raise ChainBroken(f"delta frame {packet.counter} after a gap (expected {expected})")
        self._intact = False
        self.last = self._decode_delta(packet, self.last)
        self._intact = True
        return self.last

    def _decode_key(self, packet: KeyFrame) -> FrameValues:
        dec = Decoder(packet.body)
        vals = {}
        for spec in self.specs:
            ctx = self._ctx.key[spec.name]
            vals[spec.name] = _checked(
                spec, np.array([decode_sint(dec, ctx) for _ in range(spec.size)], np.int64)
            )
        return FrameValues(packet.seq, packet.capture_us, vals, key=True)

    def _decode_delta(self, packet: DeltaFrame, last: FrameValues) -> FrameValues:
        # The coder reads zeros past the end, so any body decodes: only the values are checked.
        dec = Decoder(packet.body)
        step = decode_uint(dec, self._ctx.seq_step) + 1
        if step > MAX_SEQ_STEP:
            raise PacketError(f"DeltaFrame body: frame step {step} beyond {MAX_SEQ_STEP}")
        residual_ms = decode_sint(dec, self._ctx.time)
        if abs(residual_ms) > MAX_TIME_RESIDUAL_MS:
            raise PacketError(f"DeltaFrame body: time residual {residual_ms} ms out of range")
        seq = last.seq + step
        capture_us = last.capture_us + step * self.frame_us + 1000 * residual_ms
        if seq > UINT32_MAX:
            raise PacketError(f"DeltaFrame body: frame {seq} beyond 2^32 - 1")
        if not INT64_MIN <= capture_us <= INT64_MAX:
            raise PacketError(f"DeltaFrame body: capture time {capture_us} us beyond int64")
        vals = {}
        for spec in self.specs:
            ctx = self._ctx.delta[spec.name]
            r = np.array([decode_sint(dec, ctx[i]) for i in range(spec.size)], np.int64)
            vals[spec.name] = _checked(spec, last.values[spec.name] + r)
        return FrameValues(seq, capture_us, vals)


def _checked(spec: ChannelSpec, values: NDArray[np.int64]) -> NDArray[np.int64]:
    if np.any(np.abs(values) > MAX_CHANNEL_VALUE):
        raise PacketError(f"channel {spec.name!r}: value beyond +-{MAX_CHANNEL_VALUE}")
    values.flags.writeable = False
    return values
