"""SFrame (RFC 9605) as protocol/sframe.py does it: the RFC's vectors, tamper, replay, keys."""

from __future__ import annotations

import pytest

from facewire.protocol.sframe import (
    REPLAY_WINDOW,
    Header,
    Opener,
    ReplayError,
    RoomKey,
    Sealer,
    SFrameError,
    derive_key_salt,
    kid_is_of,
    new_kid,
    seal,
)

# RFC 9605 Appendix C.3, cipher suite 0x0004 (AES_128_GCM_SHA256_128).
BASE_KEY = bytes(range(16))
KID, CTR = 0x123, 0x4567
METADATA = bytes.fromhex("4945544620534672616d65205747")  # "IETF SFrame WG"
PT = bytes.fromhex("64726166742d696574662d736672616d652d656e63")  # "draft-ietf-sframe-enc"
CT = bytes.fromhex(
    "9901234567b7412c2513a1b66dbb48841bbaf17f598751176ad847681a69c6d0b091c07018ce4adb34eb"
)


def test_rfc_key_derivation() -> None:
    key, salt = derive_key_salt(BASE_KEY, KID)
    assert key.hex() == "d34f547f4ca4f9a7447006fe7fcbf768"
    assert salt.hex() == "75234edefe07819026751816"


def test_rfc_encryption_and_back() -> None:
    assert seal(BASE_KEY, KID, CTR, METADATA, PT) == CT
    opener = Opener()
    opener.add_key(KID, BASE_KEY)
    assert opener.open(CT, METADATA) == PT


@pytest.mark.parametrize(
    "kid, ctr, wire",
    [
        (0, 0, "00"),
        (7, 7, "77"),
        (0, 8, "0808"),
        (8, 0, "8008"),
        (0x123, 0x4567, "9901234567"),
        (0xFFFFFFFFFFFFFFFF, 0xFFFFFFFFFFFFFFFF, "ff" + "ff" * 16),
    ],
)
def test_header_encodings(kid: int, ctr: int, wire: str) -> None:
    assert bytes(Header(kid, ctr)).hex() == wire
    assert Header.parse(bytes.fromhex(wire)) == (Header(kid, ctr), len(wire) // 2)


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "empty message: no SFrame header"),
        (bytes.fromhex("9901"), "SFrame header needs 3 bytes, got 2"),
        (bytes.fromhex("0f" + "00" * 7), "SFrame header needs 9 bytes, got 8"),
    ],
)
def test_truncated_header(data: bytes, message: str) -> None:
    with pytest.raises(SFrameError, match=f"^{message}$"):
        Header.parse(data)


def _pair() -> tuple[Sealer, Opener]:
    sealer = Sealer(BASE_KEY, KID)
    opener = Opener()
    opener.add_key(KID, BASE_KEY)
    return sealer, opener


def test_every_altered_byte_is_refused() -> None:
    sealer, opener = _pair()
    message = sealer.seal(b"a bundle of packets", b"meta")
    for i in range(len(message)):
        bad = bytearray(message)
        bad[i] ^= 0x01
        with pytest.raises(SFrameError):
            opener.open(bytes(bad), b"meta")
    with pytest.raises(SFrameError, match="does not authenticate"):
        opener.open(message, b"other meta")  # moved to another sender or room
    assert opener.open(message, b"meta") == b"a bundle of packets"


def test_short_message_is_refused() -> None:
    _, opener = _pair()
    with pytest.raises(SFrameError, match="shorter than its tag"):
        opener.open(bytes(Header(KID, 1)) + bytes(15))


def test_replay_is_refused_and_reordering_within_the_window_is_not() -> None:
    sealer, opener = _pair()
    messages = [sealer.seal(bytes([i])) for i in range(REPLAY_WINDOW + 10)]
    assert opener.open(messages[5]) == b"\x05"
    with pytest.raises(ReplayError, match="counter 5 seen before"):
        opener.open(messages[5])
    assert opener.open(messages[3]) == b"\x03"  # late, not seen: taken
    assert opener.open(messages[-1]) == bytes([REPLAY_WINDOW + 9])
    with pytest.raises(ReplayError):
        opener.open(messages[3])  # seen, and now also outside the window
    with pytest.raises(ReplayError):
        opener.open(messages[4])  # never seen, but older than the window
    assert opener.open(messages[-2]) == bytes([REPLAY_WINDOW + 8])
    # A snapshot may be read again: no replay check asked, none made.
    assert opener.open(messages[-1], replay=False) == bytes([REPLAY_WINDOW + 9])


def test_a_forged_message_does_not_move_the_window() -> None:
    sealer, opener = _pair()
    first = sealer.seal(b"x")
    forged = bytes(Header(KID, 1000)) + bytes(20)
    with pytest.raises(SFrameError, match="does not authenticate"):
        opener.open(forged)
    assert opener.open(first) == b"x"  # counter 0 still fresh: the forgery did not count


def test_wrong_room_key_and_unknown_kid() -> None:
    room = RoomKey.generate("standup")
    other = RoomKey.generate("standup")
    kid = new_kid("alice")
    sealer = Sealer(room.base_key("alice"), kid)
    message = sealer.seal(b"face", room.metadata("alice", b"m"))
    wrong = Opener()
    wrong.add_key(kid, other.base_key("alice"))
    with pytest.raises(SFrameError, match="does not authenticate"):
        wrong.open(message, room.metadata("alice", b"m"))
    with pytest.raises(SFrameError, match="no key for KID"):
        Opener().open(message)
    right = Opener()
    right.add_key(kid, room.base_key("alice"))
    assert right.open(message, room.metadata("alice", b"m")) == b"face"


def test_kids_name_their_sender_and_differ_per_run() -> None:
    a, b = new_kid("alice"), new_kid("alice")
    assert a != b and kid_is_of(a, "alice") and not kid_is_of(a, "bob")
    room = RoomKey.generate("r")
    assert room.base_key("alice") != room.base_key("bob")


def test_room_key_file(tmp_path) -> None:
    room = RoomKey.generate("standup")
    path = tmp_path / "standup.room"
    room.write(path)
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    assert RoomKey.load(path) == room
    with pytest.raises(ValueError, match="exists"):
        room.write(path)
    (tmp_path / "bad").write_text("hello\n")
    with pytest.raises(ValueError, match="not a facewire room key"):
        RoomKey.load(tmp_path / "bad")
    with pytest.raises(ValueError, match="cannot read room key"):
        RoomKey.load(tmp_path / "missing")
