"""The media datagram (protocol version 3): sealed with an AEAD, guarded by a replay window.

Layout (docs/protocol.md, section 7)::

    0      1      2      4                         n-8      n
    +------+------+------+-------------------------+--------+
    | 0x30 |key id| seq  | ciphertext of the bundle|  tag   |
    +------+------+------+-------------------------+--------+

- byte 0: the version (3) in the high nibble, 0 in the low (reserved).
- key id: which receiver's keys sealed it (the sender names each receiver's keys when it
  hands them over, :class:`MediaKey`), so a sender can tell its receivers apart before it
  knows their addresses.
- seq: 16 bits, big-endian, one step per datagram. With a rollover counter kept by each end it
  makes a 48-bit packet index, estimated as SRTP does (RFC 3711, section 3.3.1).
- The rest is AES-128-CCM with an 8-byte tag (the COSE algorithm AES-CCM-16-64-128 that OSCORE,
  RFC 8613, uses on constrained links): the 4 header bytes are its associated data, the nonce is
  the direction's 13-byte salt XOR the packet index.

Keys: one 32-byte secret per receiver, made by the sender and handed over on the CURVE-secured
ZeroMQ connection (so it never travels in clear unless the call is ``--plain``). HKDF-SHA256
(RFC 5869) expands it into a key and a salt for each direction, so the two directions never
share a nonce.

A datagram is accepted only once: after its tag checks, its index must be newer than the
highest seen or inside the 64-packet window behind it and not seen yet (RFC 3711, 3.3.2).

Overhead: 12 bytes a datagram, against SRTP's 22 (a 12-byte RTP header and a 10-byte tag).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.ciphers.aead import AESCCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

#: Byte 0 of every datagram: version 3, low nibble reserved (0).
DATAGRAM_HEADER: int = 0x30
HEADER_BYTES = 4
TAG_BYTES = 8
#: Bytes a datagram adds to its bundle.
OVERHEAD = HEADER_BYTES + TAG_BYTES
#: IPv4 and UDP headers, paid by every datagram on the wire.
IP_UDP_BYTES = 28
SECRET_BYTES = 32
_KEY_BYTES = 16
_SALT_BYTES = 13  # CCM's longest nonce: 2-byte length field, so a datagram up to 64 KiB
REPLAY_WINDOW = 64
_SEQ_MOD = 1 << 16
_MAX_INDEX = (1 << 48) - 1
_HEADER = struct.Struct(">BBH")

#: The direction labels fed to HKDF.
SENDER_TO_RECEIVER = b"facewire v3 media sender to receiver"
RECEIVER_TO_SENDER = b"facewire v3 media receiver to sender"


class DatagramError(ValueError):
    """A datagram that is not ours, was forged or altered, or came before (a replay)."""


def new_secret() -> bytes:
    """A fresh 32-byte secret for one receiver's media keys."""
    return os.urandom(SECRET_BYTES)


@dataclass(frozen=True)
class DirectionKeys:
    """The AEAD and nonce salt of one direction."""

    aead: AESCCM
    salt: int

    @classmethod
    def derive(cls, secret: bytes, label: bytes) -> DirectionKeys:
        if len(secret) != SECRET_BYTES:
            raise ValueError(f"media secret: expected {SECRET_BYTES} bytes, got {len(secret)}")
        okm = HKDF(
            algorithm=hashes.SHA256(), length=_KEY_BYTES + _SALT_BYTES, salt=None, info=label
        ).derive(secret)
        aead = AESCCM(okm[:_KEY_BYTES], tag_length=TAG_BYTES)
        return cls(aead, int.from_bytes(okm[_KEY_BYTES:], "big"))

    def nonce(self, index: int) -> bytes:
        return (self.salt ^ index).to_bytes(_SALT_BYTES, "big")


class Sealer:
    """Seals the bundles of one direction, numbering them from a random start (as RTP does)."""

    def __init__(self, secret: bytes, label: bytes, key_id: int) -> None:
        if not 0 <= key_id <= 255:
            raise ValueError(f"key id {key_id} outside [0, 255]")
        self._keys = DirectionKeys.derive(secret, label)
        self.key_id = key_id
        self.index = int.from_bytes(os.urandom(2), "big")  # the next datagram's

    def seal(self, bundle: bytes) -> bytes:
        if self.index > _MAX_INDEX:
            raise DatagramError("packet index exhausted: a new secret is needed")
        header = _HEADER.pack(DATAGRAM_HEADER, self.key_id, self.index % _SEQ_MOD)
        sealed = self._keys.aead.encrypt(self._keys.nonce(self.index), bundle, header)
        self.index += 1
        return header + sealed


class ReplayWindow:
    """RFC 3711's index estimate (3.3.1) and replay list (3.3.2), over a 64-packet window."""

    def __init__(self) -> None:
        self.highest: int | None = None  # the highest index accepted
        self._seen = 0  # bit i: index highest - i was accepted

    def estimate(self, seq: int) -> int:
        """The packet index a 16-bit ``seq`` most likely stands for."""
        if self.highest is None:
            return seq
        roc, s_l = divmod(self.highest, _SEQ_MOD)
        if s_l < _SEQ_MOD // 2:
            v = roc - 1 if seq - s_l > _SEQ_MOD // 2 else roc
        else:
            v = roc + 1 if s_l - _SEQ_MOD // 2 > seq else roc
        return v * _SEQ_MOD + seq

    def check(self, index: int) -> None:
        """Raise DatagramError when ``index`` was seen or fell behind the window."""
        if index < 0:
            raise DatagramError("index before the first packet")
        if self.highest is None or index > self.highest:
            return
        behind = self.highest - index
        if behind >= REPLAY_WINDOW:
            raise DatagramError(f"replayed or too old (index {behind} behind the newest)")
        if self._seen >> behind & 1:
            raise DatagramError("replayed (index already received)")

    def accept(self, index: int) -> None:
        """Record ``index`` (only after its tag checked)."""
        if self.highest is None:
            self.highest, self._seen = index, 1
        elif index > self.highest:
            shift = index - self.highest
            self._seen = ((self._seen << shift) | 1) & ((1 << REPLAY_WINDOW) - 1)
            self.highest = index
        else:
            self._seen |= 1 << (self.highest - index)


class Opener:
    """Opens the datagrams of one direction sealed by one peer's :class:`Sealer`."""

    def __init__(self, secret: bytes, label: bytes, key_id: int) -> None:
        self._keys = DirectionKeys.derive(secret, label)
        self.key_id = key_id
        self.window = ReplayWindow()

    def open(self, datagram: bytes) -> tuple[int, bytes]:
        """(packet index, bundle) of an authentic datagram seen for the first time.

        Raises DatagramError naming what is wrong: too short, another version or key, a tag
        that does not check (forged, altered or sealed with another key), a replay.
        """
        if len(datagram) < OVERHEAD:
            raise DatagramError(f"{len(datagram)}-byte datagram is shorter than its header")
        version, key_id, seq = _HEADER.unpack_from(datagram)
        if version != DATAGRAM_HEADER:
            raise DatagramError(f"not a version-3 datagram (byte 0 is 0x{version:02x})")
        if key_id != self.key_id:
            raise DatagramError(f"key id {key_id}, expected {self.key_id}")
        index = self.window.estimate(seq)
        self.window.check(index)
        try:
            bundle = self._keys.aead.decrypt(
                self._keys.nonce(index), datagram[HEADER_BYTES:], datagram[:HEADER_BYTES]
            )
        except InvalidTag:
            raise DatagramError("authentication failed (forged, altered or another key)") from None
        self.window.accept(index)
        return index, bundle


def key_id_of(datagram: bytes) -> int | None:
    """The key id of something that looks like a datagram, else None (read before opening)."""
    if len(datagram) < OVERHEAD or datagram[0] != DATAGRAM_HEADER:
        return None
    return datagram[1]
