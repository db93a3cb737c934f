"""Media datagrams (protocol v3): sealing, the SRTP index estimate, the replay window, forgeries."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facewire.protocol.bundle import pack
from facewire.protocol.datagram import (
    DATAGRAM_HEADER,
    OVERHEAD,
    RECEIVER_TO_SENDER,
    REPLAY_WINDOW,
    SENDER_TO_RECEIVER,
    DatagramError,
    DirectionKeys,
    Opener,
    ReplayWindow,
    Sealer,
    key_id_of,
    new_secret,
)
from facewire.protocol.packets import Heartbeat

SEQ_MOD = 1 << 16
FORGED = "authentication failed (forged, altered or another key)"
SECRET = bytes(range(32))


def pair(
    key_id: int = 7, start: int = 1000, secret: bytes = SECRET, label: bytes = SENDER_TO_RECEIVER
) -> tuple[Sealer, Opener]:
    """A sealer numbering from ``start`` and the opener of its datagrams."""
    sealer = Sealer(secret, label, key_id)
    sealer.index = start
    return sealer, Opener(secret, label, key_id)


def refusal(opener: Opener, datagram: bytes) -> str:
    """Why ``opener`` refuses ``datagram`` (it must)."""
    with pytest.raises(DatagramError) as info:
        opener.open(datagram)
    return str(info.value)


def stamp(i: int) -> bytes:
    """A bundle that tells which datagram it was."""
    return i.to_bytes(4, "big")


# --- sealing -----------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.binary(max_size=1188), min_size=1, max_size=5),
    st.integers(0, 255),
    st.integers(0, SEQ_MOD - 1),
)
def test_seal_open_round_trip(bundles: list[bytes], key_id: int, start: int) -> None:
    sealer, opener = pair(key_id, start, new_secret())
    for i, bundle in enumerate(bundles):
        datagram = sealer.seal(bundle)
        assert len(datagram) == len(bundle) + OVERHEAD
        assert opener.open(datagram) == (start + i, bundle)
    assert sealer.index == start + len(bundles)


def test_overhead_is_twelve_bytes() -> None:
    assert OVERHEAD == 12
    sealer, _ = pair()
    for n in (0, 1, 13, 500, 1188):
        assert len(sealer.seal(bytes(n))) == n + 12


def test_header_bytes() -> None:
    sealer, _ = pair(key_id=0xA5, start=3 * SEQ_MOD + 0x1234)
    datagram = sealer.seal(b"hello")
    assert DATAGRAM_HEADER == 0x30
    # version 3 (low nibble reserved), key id, the low 16 bits of the index big-endian
    assert datagram[:4] == bytes([0x30, 0xA5, 0x12, 0x34])
    assert key_id_of(datagram) == 0xA5
    assert sealer.seal(b"")[:4] == bytes([0x30, 0xA5, 0x12, 0x35])


def test_known_datagram() -> None:
    """docs/protocol.md 8.8: a Heartbeat sealed with the secret 0..31, key id 7, index 0x1234."""
    sealer, opener = pair(key_id=7, start=0x1234)
    bundle = pack([bytes(Heartbeat(3050556106, 42, 1_000_000))])
    datagram = sealer.seal(bundle)
    assert datagram == bytes.fromhex(
        "30071234" "8c902901e995f739d0c439082ba5" "0abe2c67db981e09"
    )  # fmt: skip
    assert opener.open(datagram) == (0x1234, bundle)


def test_seq_starts_at_random() -> None:
    starts = {Sealer(SECRET, SENDER_TO_RECEIVER, 1).index for _ in range(20)}
    assert len(starts) > 1
    assert all(0 <= s < SEQ_MOD for s in starts)


def test_directions_never_share_key_or_nonce() -> None:
    down = DirectionKeys.derive(SECRET, SENDER_TO_RECEIVER)
    up = DirectionKeys.derive(SECRET, RECEIVER_TO_SENDER)
    assert down.salt != up.salt
    assert down.nonce(5) != up.nonce(5)
    assert len(down.nonce(5)) == 13
    a, _ = pair(label=SENDER_TO_RECEIVER)
    b, _ = pair(label=RECEIVER_TO_SENDER)
    assert a.seal(b"same") != b.seal(b"same")


def test_bad_secret_and_key_id() -> None:
    with pytest.raises(ValueError, match=r"^media secret: expected 32 bytes, got 31$"):
        Sealer(bytes(31), SENDER_TO_RECEIVER, 1)
    with pytest.raises(ValueError, match=r"^media secret: expected 32 bytes, got 33$"):
        Opener(bytes(33), SENDER_TO_RECEIVER, 1)
    with pytest.raises(ValueError, match=r"^key id 256 outside \[0, 255\]$"):
        Sealer(SECRET, SENDER_TO_RECEIVER, 256)
    with pytest.raises(ValueError, match=r"^key id -1 outside \[0, 255\]$"):
        Sealer(SECRET, SENDER_TO_RECEIVER, -1)


def test_packet_index_exhausted() -> None:
    sealer, _ = pair(start=(1 << 48) - 1)
    sealer.seal(b"last")
    with pytest.raises(DatagramError, match=r"^packet index exhausted: a new secret is needed$"):
        sealer.seal(b"one too many")


def test_key_id_of() -> None:
    sealer, _ = pair(key_id=200)
    datagram = sealer.seal(b"")
    assert key_id_of(datagram) == 200
    assert key_id_of(datagram[:11]) is None
    assert key_id_of(b"\x20" + datagram[1:]) is None


# --- opening: what is refused ------------------------------------------------------------------


def test_truncated_datagram() -> None:
    sealer, opener = pair()
    datagram = sealer.seal(b"some bundle")
    for n in range(len(datagram)):
        if n < OVERHEAD:
            assert refusal(opener, datagram[:n]) == f"{n}-byte datagram is shorter than its header"
        else:  # the header is whole, the tag is cut
            assert refusal(opener, datagram[:n]) == FORGED
    assert opener.open(datagram) == (1000, b"some bundle")


def test_empty_bundle_is_a_valid_datagram() -> None:
    sealer, opener = pair()
    datagram = sealer.seal(b"")
    assert len(datagram) == OVERHEAD
    assert opener.open(datagram) == (1000, b"")


def test_every_flipped_bit_is_refused() -> None:
    """Byte 0 and the key id are checked first; any other bit (seq, ciphertext, tag) fails the
    tag. Nothing refused moves the window: the genuine datagram opens afterwards."""
    sealer, opener = pair(key_id=7, start=0x1234)
    datagram = sealer.seal(b"a bundle of twenty b")
    for i in range(len(datagram) * 8):
        altered = bytearray(datagram)
        altered[i // 8] ^= 1 << (i % 8)
        why = refusal(opener, bytes(altered))
        if i < 8:
            assert why == f"not a version-3 datagram (byte 0 is 0x{altered[0]:02x})"
        elif i < 16:
            assert why == f"key id {altered[1]}, expected 7"
        else:
            assert why == FORGED, i
    assert opener.open(datagram) == (0x1234, b"a bundle of twenty b")


def test_flipped_bits_refused_in_a_running_stream() -> None:
    sealer, opener = pair(start=SEQ_MOD - 3)
    for i in range(10):
        opener.open(sealer.seal(stamp(i)))
    datagram = sealer.seal(stamp(10))
    for i in range(32, len(datagram) * 8):  # seq, ciphertext and tag
        altered = bytearray(datagram)
        altered[i // 8] ^= 1 << (i % 8)
        why = refusal(opener, bytes(altered))
        # A flipped seq bit may also name an index already seen or left behind.
        assert why == FORGED or why.startswith("replayed"), (i, why)
    assert opener.open(datagram) == (SEQ_MOD + 7, stamp(10))


def test_other_direction_cannot_open() -> None:
    down, _ = pair(label=SENDER_TO_RECEIVER)
    up, _ = pair(label=RECEIVER_TO_SENDER)
    assert refusal(Opener(SECRET, RECEIVER_TO_SENDER, 7), down.seal(b"to the receiver")) == FORGED
    assert refusal(Opener(SECRET, SENDER_TO_RECEIVER, 7), up.seal(b"to the sender")) == FORGED


def test_other_secret_cannot_open() -> None:
    sealer, _ = pair()
    assert refusal(Opener(new_secret(), SENDER_TO_RECEIVER, 7), sealer.seal(b"x")) == FORGED


def test_other_key_id_is_refused() -> None:
    sealer, _ = pair(key_id=8)
    assert (
        refusal(Opener(SECRET, SENDER_TO_RECEIVER, 7), sealer.seal(b"x")) == "key id 8, expected 7"
    )
    # A key id rewritten to the expected one fails the tag: it is associated data.
    datagram = bytearray(sealer.seal(b"x"))
    datagram[1] = 7
    assert refusal(Opener(SECRET, SENDER_TO_RECEIVER, 7), bytes(datagram)) == FORGED


def test_other_version_is_refused() -> None:
    sealer, opener = pair()
    datagram = sealer.seal(b"x")
    assert refusal(opener, b"\x20" + datagram[1:]) == "not a version-3 datagram (byte 0 is 0x20)"
    assert refusal(opener, b"\x31" + datagram[1:]) == "not a version-3 datagram (byte 0 is 0x31)"


# --- the replay window -------------------------------------------------------------------------


def test_datagram_opened_twice_is_a_replay() -> None:
    sealer, opener = pair()
    datagram = sealer.seal(b"once")
    assert opener.open(datagram) == (1000, b"once")
    with pytest.raises(DatagramError, match=r"^replayed \(index already received\)$"):
        opener.open(datagram)
    # Still a replay after newer ones came, while it is inside the window.
    for i in range(REPLAY_WINDOW - 1):
        opener.open(sealer.seal(stamp(i)))
    with pytest.raises(DatagramError, match=r"^replayed \(index already received\)$"):
        opener.open(datagram)
    # Then too old.
    opener.open(sealer.seal(b"one more"))
    with pytest.raises(
        DatagramError, match=r"^replayed or too old \(index 64 behind the newest\)$"
    ):
        opener.open(datagram)


def test_older_than_the_window_is_refused() -> None:
    sealer, opener = pair()
    sent = [sealer.seal(stamp(i)) for i in range(REPLAY_WINDOW + 2)]  # indices 1000..1065
    assert opener.open(sent[-1]) == (1065, stamp(65))
    with pytest.raises(
        DatagramError, match=r"^replayed or too old \(index 65 behind the newest\)$"
    ):
        opener.open(sent[0])
    with pytest.raises(
        DatagramError, match=r"^replayed or too old \(index 64 behind the newest\)$"
    ):
        opener.open(sent[1])
    assert opener.open(sent[2]) == (1002, stamp(2))  # 63 behind: inside the window
    assert opener.open(sent[-2]) == (1064, stamp(64))


def test_out_of_order_within_the_window_accepted_once_each() -> None:
    sealer, opener = pair(start=SEQ_MOD - 30)  # across a wrap of seq too
    sent = [(sealer.index, sealer.seal(stamp(i))) for i in range(REPLAY_WINDOW)]
    order = list(range(REPLAY_WINDOW))
    random.Random(5).shuffle(order)
    for i in order:
        assert opener.open(sent[i][1]) == (sent[i][0], stamp(i))
    for i in order:
        with pytest.raises(DatagramError, match=r"^replayed"):
            opener.open(sent[i][1])


def test_forgery_does_not_move_the_window() -> None:
    """A datagram with a seq far ahead but a bad tag leaves the window where it was."""
    sealer, opener = pair(start=500)
    first = sealer.seal(b"first")
    second = sealer.seal(b"second")
    opener.open(first)
    ahead = bytearray(second)
    ahead[2:4] = (500 + 20_000).to_bytes(2, "big")
    assert refusal(opener, bytes(ahead)) == FORGED
    assert opener.window.highest == 500
    assert opener.open(second) == (501, b"second")


def test_before_the_first_packet() -> None:
    """Just after the start, a seq more than half a wrap ahead stands for an index before 0."""
    sealer, opener = pair(start=5)
    opener.open(sealer.seal(b""))
    other, _ = pair(start=60_000)
    with pytest.raises(DatagramError, match=r"^index before the first packet$"):
        opener.open(other.seal(b""))


@pytest.mark.parametrize(
    "highest, seq, index",
    [
        (None, 0x1234, 0x1234),  # the first datagram: roc 0
        (100, 101, 101),
        (100, 99, 99),
        (SEQ_MOD - 1, 0, SEQ_MOD),  # seq wrapped
        (SEQ_MOD - 10, 20, SEQ_MOD + 20),
        (SEQ_MOD, SEQ_MOD - 1, SEQ_MOD - 1),  # late, from before the wrap
        (5 * SEQ_MOD + 10, SEQ_MOD - 10, 5 * SEQ_MOD - 10),
        (5 * SEQ_MOD + 40_000, 100, 6 * SEQ_MOD + 100),
        (5 * SEQ_MOD + 40_000, 10_000, 5 * SEQ_MOD + 10_000),
        (5 * SEQ_MOD + 32_768, 0, 5 * SEQ_MOD),  # s_l - 32768 > seq is false at equality
    ],
)
def test_index_estimate(highest: int | None, seq: int, index: int) -> None:
    window = ReplayWindow()
    if highest is not None:
        window.accept(highest)
    assert window.estimate(seq) == index


def test_seq_wraps_many_times_with_loss_and_reordering() -> None:
    """200,000 datagrams from 1000 before a wrap of seq: every one opens to its own index, those
    reordered (by up to 40) or lost (1 in 10) near each wrap too, and those after an outage of
    30,000 that spans a wrap (less than half of one: the estimate still finds the roc)."""
    sealer, opener = pair(start=SEQ_MOD - 1000)
    rng = random.Random(11)
    opened = 0
    outage = False
    for i in range(0, 200_000, 40):
        if not outage and sealer.index >= 2 * SEQ_MOD + 50_000:
            sealer.index += 30_000
            outage = True
        near_wrap = not 200 <= sealer.index % SEQ_MOD <= SEQ_MOD - 200
        batch = [(sealer.index, stamp(i + j), sealer.seal(stamp(i + j))) for j in range(40)]
        if near_wrap:
            rng.shuffle(batch)
        for index, bundle, datagram in batch:
            if near_wrap and rng.random() < 0.1:
                continue
            assert opener.open(datagram) == (index, bundle)
            opened += 1
    assert outage
    assert sealer.index > 4 * SEQ_MOD
    assert opened > 195_000
