"""Adaptive binary range coder: the entropy coder of version-2 frame packets.

A byte-oriented binary arithmetic coder in the family of LZMA's range coder, specified in full
in docs/protocol.md section 5 so that a peer can be written from the document alone.

- 32-bit ``range``, 12-bit probabilities: a context holds ``p0``, the probability that the
  next bit is 0, in 1/4096 units (starts at 2048). After coding a bit the context adapts by a
  shift that starts fast and settles: 1, 2, 3 for its first three bits, then ``ADAPT_SHIFT``
  = 4 (p0 += (4096 - p0) >> shift on a 0, p0 -= p0 >> shift on a 1). Contexts are reset at
  every keyframe, so learning fast matters: it saves about 3 % of the geometry bit rate
  against a fixed shift of 4 (docs/what-we-tried.md, "Coding the geometry").
- "Bypass" bits are coded at p0 = 2048 with no adaptation.
- The encoder keeps ``low`` as an unbounded integer and propagates a carry into the bytes it
  has already written, so no byte is ever held back.
- The stream ends with the shortest flush: the value in the final interval with the most
  trailing zero bytes, and trailing zero bytes are dropped (the decoder reads zeros past the
  end). A packet whose symbols are all highly probable can therefore be empty.

Why not `constriction`: its range and ANS coders emit 32-bit words, which costs about 16 bits
per packet on 30-60-bit frame packets (measured: a 42-bit message takes 64 bits), half the
geometry budget at 30 packets/s; and its model quantisation is not specified as a format a
peer could reproduce byte for byte.

Integers are binarised (see :func:`encode_uint`, :func:`encode_sint`) into adaptive bits;
which context codes which bit is the caller's choice, carried by :class:`IntContexts`.
"""

from __future__ import annotations

import logging
import math

logger = logging.getLogger(__name__)

PROB_BITS = 12
PROB_ONE = 1 << PROB_BITS  # 4096
PROB_INIT = PROB_ONE // 2
ADAPT_SHIFT = 4
TOP = 1 << 24  # renormalise (shift a byte) while range < TOP
RANGE_INIT = 0xFFFFFFFF
#: Longest unary prefix of an integer's bit length: values are below 2**MAX_INT_BITS.
MAX_INT_BITS = 32


class Context:
    """One adaptive binary probability (p0 in 1/4096 units) and how many bits it has coded
    (counted up to ``ADAPT_SHIFT - 1``, which sets its next adaptation shift)."""

    __slots__ = ("p0", "count")

    def __init__(self) -> None:
        self.p0 = PROB_INIT
        self.count = 0

    def update(self, bit: int) -> None:
        shift = self.count + 1  # 1, 2, 3, then ADAPT_SHIFT for good
        if self.count < ADAPT_SHIFT - 1:
            self.count += 1
        if bit:
            self.p0 -= self.p0 >> shift
        else:
            self.p0 += (PROB_ONE - self.p0) >> shift


class Encoder:
    """Codes bits into bytes; call :meth:`finish` once for the coded bytes."""

    def __init__(self) -> None:
        self._low = 0
        self._range = RANGE_INIT
        self._out = bytearray()

    def _bit(self, bit: int, p0: int) -> None:
        bound = (self._range >> PROB_BITS) * p0
        if bit:
            self._low += bound
            self._range -= bound
        else:
            self._range = bound
        while self._range < TOP:
            self._shift()

    def _shift(self) -> None:
        if self._low >= 1 << 32:  # carry into the bytes already written
            self._carry()
            self._low -= 1 << 32
        self._out.append(self._low >> 24)
        self._low = (self._low & 0xFFFFFF) << 8
        self._range <<= 8

    def _carry(self) -> None:
        i = len(self._out) - 1
        while self._out[i] == 0xFF:  # cannot run off the front: low < 2**32 after a carry
            self._out[i] = 0
            i -= 1
        self._out[i] += 1

    @property
    def bits(self) -> float:
        """Information coded so far, in bits (-log2 of the probability of every symbol):
        bytes written plus what the interval has narrowed since. For measuring only; the
        finished body rounds it up to whole bytes."""
        return 8 * len(self._out) + 32 - math.log2(self._range)

    def encode_bit(self, bit: int, ctx: Context) -> None:
        """Code ``bit`` with the adaptive probability of ``ctx``, then adapt it."""
        b = 1 if bit else 0
        self._bit(b, ctx.p0)
        ctx.update(b)

    def encode_bypass(self, value: int, nbits: int) -> None:
        """Code the ``nbits`` low bits of ``value``, most significant first, at p = 1/2."""
        for i in range(nbits - 1, -1, -1):
            self._bit((value >> i) & 1, PROB_INIT)

    def finish(self) -> bytes:
        """The coded bytes: the shortest flush, trailing zero bytes removed."""
        # Any value in [low, low + range) decodes the same; take the one with the most
        # trailing zero bits, then write it out byte by byte.
        low, high = self._low, self._low + self._range - 1
        shift = 32
        while shift > 0 and (high >> shift) << shift < low:
            shift -= 1
        value = ((high >> shift) << shift) if shift else low
        while value:
            self._low = value
            if self._low >= 1 << 32:
                self._carry()
                self._low -= 1 << 32
            self._out.append(self._low >> 24)
            value = (self._low & 0xFFFFFF) << 8
        out = bytes(self._out).rstrip(b"\x00")
        self._out = bytearray()
        return out


class Decoder:
    """Reads bits back from the bytes an :class:`Encoder` wrote (zeros past the end)."""

    def __init__(self, data: bytes) -> None:
        self._data = bytes(data)
        self._pos = 0
        self._range = RANGE_INIT
        self._code = 0
        for _ in range(4):
            self._code = (self._code << 8) | self._next()

    def _next(self) -> int:
        if self._pos < len(self._data):
            b = self._data[self._pos]
        else:
            b = 0
        self._pos += 1
        return b

    def _bit(self, p0: int) -> int:
        bound = (self._range >> PROB_BITS) * p0
        if self._code < bound:
            self._range = bound
            bit = 0
        else:
            self._code -= bound
            self._range -= bound
            bit = 1
        while self._range < TOP:
            self._code = ((self._code << 8) | self._next()) & 0xFFFFFFFF
            self._range <<= 8
        return bit

    def decode_bit(self, ctx: Context) -> int:
        bit = self._bit(ctx.p0)
        ctx.update(bit)
        return bit

    def decode_bypass(self, nbits: int) -> int:
        value = 0
        for _ in range(nbits):
            value = (value << 1) | self._bit(PROB_INIT)
        return value

    @property
    def overrun(self) -> int:
        """Bytes read past the end of the data (beyond the 4 of the initial code window)."""
        return max(0, self._pos - 4 - len(self._data))


class IntContexts:
    """The adaptive contexts that code one integer element (see :func:`encode_uint`).

    ``zero``: is the value 0; ``sign``: is it negative; ``length[i]``: does the bit length
    of the magnitude exceed i + 1 (a unary code, one context per position).
    """

    __slots__ = ("zero", "sign", "length")

    def __init__(self) -> None:
        self.zero = Context()
        self.sign = Context()
        self.length = [Context() for _ in range(MAX_INT_BITS)]


def _encode_magnitude(enc: Encoder, m: int, ctx: IntContexts) -> None:
    """m >= 1: unary bit length (adaptive), then the bits below the leading 1 (bypass)."""
    n = m.bit_length()
    if n > MAX_INT_BITS:
        raise ValueError(f"value {m} needs more than {MAX_INT_BITS} bits")
    for i in range(n - 1):
        enc.encode_bit(1, ctx.length[i])
    if n < MAX_INT_BITS:
        enc.encode_bit(0, ctx.length[n - 1])
    enc.encode_bypass(m, n - 1)


def _decode_magnitude(dec: Decoder, ctx: IntContexts) -> int:
    n = 1
    while n < MAX_INT_BITS and dec.decode_bit(ctx.length[n - 1]):
        n += 1
    return (1 << (n - 1)) | dec.decode_bypass(n - 1)


def encode_uint(enc: Encoder, value: int, ctx: IntContexts) -> None:
    """Code an integer 0 <= value < 2**32: zero flag, then the magnitude."""
    if not 0 <= value < 1 << MAX_INT_BITS:
        raise ValueError(f"unsigned value {value} outside [0, 2**{MAX_INT_BITS})")
    enc.encode_bit(value == 0, ctx.zero)
    if value:
        _encode_magnitude(enc, value, ctx)


def decode_uint(dec: Decoder, ctx: IntContexts) -> int:
    if dec.decode_bit(ctx.zero):
        return 0
    return _decode_magnitude(dec, ctx)


def encode_sint(enc: Encoder, value: int, ctx: IntContexts) -> None:
    """Code an integer |value| < 2**32: zero flag, sign, then the magnitude."""
    if not -(1 << MAX_INT_BITS) < value < 1 << MAX_INT_BITS:
        raise ValueError(f"signed value {value} outside (-2**{MAX_INT_BITS}, 2**{MAX_INT_BITS})")
    enc.encode_bit(value == 0, ctx.zero)
    if value:
        enc.encode_bit(value < 0, ctx.sign)
        _encode_magnitude(enc, abs(value), ctx)


def decode_sint(dec: Decoder, ctx: IntContexts) -> int:
    if dec.decode_bit(ctx.zero):
        return 0
    negative = dec.decode_bit(ctx.sign)
    m = _decode_magnitude(dec, ctx)
    return -m if negative else m
