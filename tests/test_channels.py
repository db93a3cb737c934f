"""Channel coding: key and delta frames round trip exactly, gaps break the chain until a
keyframe, nothing is sent when nothing changed, hostile bodies raise PacketError only."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facewire.protocol.channels import ChainBroken, ChannelDecoder, ChannelEncoder, ChannelSpec
from facewire.protocol.constants import (
    INT64_MAX,
    INT64_MIN,
    MAX_SEQ_STEP,
    MAX_TIME_RESIDUAL_MS,
    UINT32_MAX,
)
from facewire.protocol.packets import DeltaFrame, KeyFrame, PacketError, decode
from facewire.protocol.rangecoder import Encoder, IntContexts, encode_sint, encode_uint

SPECS = [ChannelSpec("pose", 3, 0.01), ChannelSpec("wire", 8, 0.02)]
FRAME_US = 33_333


def stream(n: int, seed: int = 0, still: float = 0.3) -> list[tuple[int, int, dict]]:
    """A random walk of integer channel values with still stretches and jittered times."""
    rng = np.random.default_rng(seed)
    values = {"pose": np.zeros(3, np.int64), "wire": np.zeros(8, np.int64)}
    out = []
    for seq in range(n):
        if rng.random() > still:
            values = {k: v + rng.integers(-3, 4, v.shape) for k, v in values.items()}
        out.append((seq, seq * FRAME_US + int(rng.integers(-4000, 4000)), dict(values)))
    return out


def encoder(interval: int = 60) -> ChannelEncoder:
    return ChannelEncoder(SPECS, FRAME_US, session_id=7, keyframe_interval=interval)


def test_round_trip_through_bytes_is_exact() -> None:
    enc, dec = encoder(), ChannelDecoder(SPECS, FRAME_US)
    shown = None
    for seq, t, values in stream(300):
        packet, sent = enc.encode(seq, t, values)
        for name in values:  # the receiver rebuilds exactly the values given
            assert np.array_equal(sent.values[name], values[name])
        if packet is None:
            assert shown is not None and all(
                np.array_equal(shown.values[k], values[k]) for k in values
            )
            continue
        assert abs(sent.capture_us - t) <= 500  # millisecond residuals
        shown = dec.decode(decode(bytes(packet)))  # type: ignore[arg-type]
        assert shown == sent


def test_coded_bits_account_for_the_bodies() -> None:
    # What the encoder reports per channel adds up to the bodies it wrote, less their
    # rounding to whole bytes (under a byte a packet).
    enc = encoder(interval=50)
    body_bits, packets = 0, 0
    for seq, t, values in stream(200):
        packet, _ = enc.encode(seq, t, values)
        if packet is not None:
            body_bits += 8 * len(packet.body)
            packets += 1
    coded = enc.coded_bits
    assert set(coded) == {"keyframes", "step and time", "pose", "wire"}
    assert coded["wire"] > coded["pose"] > 0  # 8 values against 3, moving alike
    assert -packets <= body_bits - sum(coded.values()) <= 8 * packets


def test_keyframes_on_interval_and_request() -> None:
    enc = encoder(interval=10)
    kinds = []
    for seq, t, values in stream(40, still=0.0):
        if seq == 25:
            enc.request_keyframe()
        packet, _ = enc.encode(seq, t, values)
        kinds.append(type(packet).__name__[0])
    assert [i for i, k in enumerate(kinds) if k == "K"] == [0, 10, 20, 25, 35]


def test_nothing_changed_sends_nothing_but_at_least_every_max_step() -> None:
    enc = encoder(interval=1000)
    values = {"pose": np.zeros(3, np.int64), "wire": np.zeros(8, np.int64)}
    sent = [enc.encode(seq, seq * FRAME_US, values)[0] is not None for seq in range(100)]
    assert sent[0] and not any(sent[1:MAX_SEQ_STEP])
    assert [i for i, s in enumerate(sent) if s] == list(range(0, 100, MAX_SEQ_STEP))


def test_a_lost_packet_breaks_the_chain_until_the_next_keyframe() -> None:
    enc, dec = encoder(interval=20), ChannelDecoder(SPECS, FRAME_US)
    decoded, broken = [], []
    for seq, t, values in stream(60, still=0.0):
        packet, sent = enc.encode(seq, t, values)
        assert packet is not None
        if seq == 5:  # lost
            continue
        try:
            assert dec.decode(packet) == sent
            decoded.append(seq)
        except ChainBroken:
            broken.append(seq)
    assert broken == list(range(6, 20))
    assert decoded == [0, 1, 2, 3, 4, *range(20, 60)]
    assert dec.intact


def test_a_delta_before_any_keyframe_is_refused() -> None:
    dec = ChannelDecoder(SPECS, FRAME_US)
    with pytest.raises(ChainBroken):
        dec.decode(DeltaFrame(1, b"\x00"))


def test_counter_wraps() -> None:
    enc, dec = encoder(interval=10_000), ChannelDecoder(SPECS, FRAME_US)
    for seq, t, values in stream(600, still=0.0):
        packet, sent = enc.encode(seq, t, values)
        assert packet is not None and dec.decode(packet) == sent


def test_steps_beyond_the_limit_force_a_keyframe() -> None:
    enc = encoder()
    values = {"pose": np.zeros(3, np.int64), "wire": np.zeros(8, np.int64)}
    enc.encode(0, 0, values)
    packet, _ = enc.encode(MAX_SEQ_STEP + 5, (MAX_SEQ_STEP + 5) * FRAME_US, values)
    assert isinstance(packet, KeyFrame)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40), st.integers(0, 255))
def test_garbage_bodies_raise_only_packet_error(body: bytes, counter: int) -> None:
    enc, dec = encoder(), ChannelDecoder(SPECS, FRAME_US)
    key, _ = enc.encode(0, 0, {"pose": np.zeros(3, np.int64), "wire": np.zeros(8, np.int64)})
    assert key is not None
    dec.decode(key)
    for packet in (DeltaFrame((key.counter + 1) % 256, body), KeyFrame(counter, 7, 1, 0, body)):
        try:
            dec.decode(packet)
        except (PacketError, ChainBroken):
            pass


def test_values_out_of_range_are_refused_on_both_ends() -> None:
    enc = encoder()
    with pytest.raises(ValueError, match="values beyond"):
        enc.encode(0, 0, {"pose": np.full(3, 2**25), "wire": np.zeros(8, np.int64)})
    with pytest.raises(ValueError, match=r"expected \(8,\) integers"):
        enc.encode(0, 0, {"pose": np.zeros(3, np.int64), "wire": np.zeros(7, np.int64)})
    # A hostile keyframe whose first value is 2**30: coded by hand, refused on decoding.
    coder = Encoder()
    encode_sint(coder, 2**30, IntContexts())
    dec = ChannelDecoder(SPECS, FRAME_US)
    with pytest.raises(PacketError, match=r"channel 'pose': value beyond \+-16777216"):
        dec.decode(KeyFrame(0, 7, 0, 0, coder.finish()))


def delta_body(step: int, residual_ms: int = 0, n_values: int = 11) -> bytes:
    """A delta body coded by hand (every element's contexts fresh, as after a keyframe)."""
    coder = Encoder()
    encode_uint(coder, step - 1, IntContexts())
    encode_sint(coder, residual_ms, IntContexts())
    for _ in range(n_values):
        encode_sint(coder, 0, IntContexts())
    return coder.finish()


ZEROS = {"pose": np.zeros(3, np.int64), "wire": np.zeros(8, np.int64)}


@given(
    st.integers(0, UINT32_MAX),
    st.integers(1, MAX_SEQ_STEP),
    st.one_of(st.integers(INT64_MIN, INT64_MAX), st.integers(INT64_MAX - 10**9, INT64_MAX)),
    st.integers(-MAX_TIME_RESIDUAL_MS, MAX_TIME_RESIDUAL_MS),
)
def test_a_delta_past_the_frame_number_or_clock_range_is_refused(
    seq: int, step: int, capture_us: int, residual_ms: int
) -> None:
    """A delta's frame number and capture time follow from the chain; beyond uint32 and
    int64 (what a keyframe could carry) they are a PacketError, not a silent overflow."""
    dec = ChannelDecoder(SPECS, FRAME_US)
    dec.decode(KeyFrame(0, 7, seq, capture_us, b""))
    delta = DeltaFrame(1, delta_body(step, residual_ms))
    next_seq, next_us = seq + step, capture_us + step * FRAME_US + 1000 * residual_ms
    if next_seq <= UINT32_MAX and INT64_MIN <= next_us <= INT64_MAX:
        got = dec.decode(delta)
        assert (got.seq, got.capture_us) == (next_seq, next_us)
        return
    with pytest.raises(PacketError, match="DeltaFrame body: (frame|capture time) .* beyond"):
        dec.decode(delta)
    assert not dec.intact  # the chain waits for a keyframe


def test_the_encoder_keeps_to_the_ranges_the_decoder_accepts() -> None:
    with pytest.raises(ValueError, match="seq is uint32"):
        encoder().encode(UINT32_MAX + 1, 0, ZEROS)
    with pytest.raises(ValueError, match="the time int64"):
        encoder().encode(0, INT64_MAX + 1, ZEROS)


@given(st.integers(MAX_TIME_RESIDUAL_MS - 2, 10**9), st.sampled_from([1, -1]))
def test_a_clock_jump_beyond_the_residual_range_sends_a_keyframe(jump_ms: int, sign: int) -> None:
    """The capture time a receiver rebuilds is never clipped: past the delta's residual range
    it travels, exactly, in a keyframe."""
    enc, dec = encoder(interval=1000), ChannelDecoder(SPECS, FRAME_US)
    moved = {"pose": np.ones(3, np.int64), "wire": np.zeros(8, np.int64)}
    for seq, capture_us, values in ((0, 10**12, ZEROS), (1, 10**12 + FRAME_US, moved)):
        packet, sent = enc.encode(seq, capture_us + sign * 1000 * jump_ms * seq, values)
        assert packet is not None
        assert dec.decode(decode(bytes(packet))) == sent  # type: ignore[arg-type]
    assert isinstance(packet, KeyFrame) == (jump_ms > MAX_TIME_RESIDUAL_MS)
    assert abs(sent.capture_us - (10**12 + FRAME_US + sign * 1000 * jump_ms)) <= 500
