"""End-to-end encryption of a room's messages: SFrame (RFC 9605), cipher suite
AES_128_GCM_SHA256_128 (0x0004).

A sealed message is the SFrame header (a config byte, the key ID, the counter), then the
AEAD ciphertext with its 16-byte tag; the header and the caller's metadata are the AEAD's
associated data. The relay routes the message by its subject and learns nothing else: not
the face, not which packets a bundle holds.

Keys (docs/rooms.md): a room has one secret (``facewire keys --room NAME``). Each participant's
base key is derived from it and the participant's name; each run of a participant picks a new
key ID (the name's hash and 32 random bits), and RFC 9605's derivation turns (base key, KID)
into that run's AEAD key and salt. A participant who restarts therefore never reuses a
(key, nonce) pair, and a receiver derives any sender's key from the name the message comes
under and the KID in its header, with nothing exchanged in clear.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import os
import secrets
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes, hmac
from cryptography.hazmat.primitives.ciphers.aead import AESGCM

logger = logging.getLogger(__name__)

SUITE = 0x0004  # AES_128_GCM_SHA256_128
NK, NN, NT = 16, 12, 16  # key, nonce and tag bytes
MAX_COUNTER = (1 << 64) - 1
#: How far behind the newest counter a message may come (reordering) before it is refused.
REPLAY_WINDOW = 128
ROOM_KEY_MAGIC = "facewire-room-key 1"


class SFrameError(ValueError):
    """A message that is malformed, does not authenticate, or was seen before."""


class ReplayError(SFrameError):
    """An authentic message already received, or older than the replay window."""


@dataclass(frozen=True)
class Header:
    """The SFrame header (RFC 9605 4.3): KID and CTR, each in as few bytes as it takes."""

    kid: int
    ctr: int

    def __bytes__(self) -> bytes:
        config = 0
        tail = b""
        for value, shift in ((self.kid, 4), (self.ctr, 0)):
            if not 0 <= value <= MAX_COUNTER:
                raise ValueError(f"KID and CTR are 64-bit, got {value}")
            if value < 8:
                config |= value << shift  # the value itself, in the config byte
            else:
                n = (value.bit_length() + 7) // 8
                config |= (0x8 | (n - 1)) << shift  # X (or Y) set, the length minus one
                tail += value.to_bytes(n, "big")
        return bytes([config]) + tail

    @classmethod
    def parse(cls, data: bytes) -> tuple[Header, int]:
        """The header at the start of ``data`` and its length."""
        if not data:
            raise SFrameError("empty message: no SFrame header")
        config, at = data[0], 1
        values = []
        for nibble in (config >> 4, config & 0xF):
            if nibble & 0x8:
                n = (nibble & 0x7) + 1
                if at + n > len(data):
                    raise SFrameError(f"SFrame header needs {at + n} bytes, got {len(data)}")
                values.append(int.from_bytes(data[at : at + n], "big"))
                at += n
            else:
                values.append(nibble)
        return cls(values[0], values[1]), at


def _hkdf_extract(salt: bytes, ikm: bytes) -> bytes:
    h = hmac.HMAC(salt or bytes(32), hashes.SHA256())
    h.update(ikm)
    return h.finalize()


def _hkdf_expand(prk: bytes, info: bytes, length: int) -> bytes:
    out, block, i = b"", b"", 1
    while len(out) < length:
        h = hmac.HMAC(prk, hashes.SHA256())
        h.update(block + info + bytes([i]))
        block = h.finalize()
        out += block
        i += 1
    return out[:length]


def derive_key_salt(base_key: bytes, kid: int) -> tuple[bytes, bytes]:
    """RFC 9605 4.4.2: the AEAD key and salt of ``kid`` under ``base_key``."""
    secret = _hkdf_extract(b"", base_key)
    suffix = struct.pack(">QH", kid, SUITE)
    key = _hkdf_expand(secret, b"SFrame 1.0 Secret key " + suffix, NK)
    salt = _hkdf_expand(secret, b"SFrame 1.0 Secret salt " + suffix, NN)
    return key, salt


def _nonce(salt: bytes, ctr: int) -> bytes:
    return bytes(a ^ b for a, b in zip(salt, ctr.to_bytes(NN, "big"), strict=True))


class _KeyState:
    def __init__(self, base_key: bytes, kid: int) -> None:
        key, self.salt = derive_key_salt(base_key, kid)
        self.aead = AESGCM(key)


def seal(base_key: bytes, kid: int, ctr: int, metadata: bytes, plaintext: bytes) -> bytes:
    """One message (RFC 9605 4.4.3); prefer :class:`Sealer`, which keeps the counter."""
    return _seal(_KeyState(base_key, kid), kid, ctr, metadata, plaintext)


def _seal(state: _KeyState, kid: int, ctr: int, metadata: bytes, plaintext: bytes) -> bytes:
    header = bytes(Header(kid, ctr))
    return header + state.aead.encrypt(_nonce(state.salt, ctr), plaintext, header + metadata)


class Sealer:
    """One sender's messages under one KID: the counter goes up by one each message.

    Threads may share it (a participant's media and its keyframe requests): two messages
    under one counter would reuse a nonce, which GCM does not survive.
    """

    def __init__(self, base_key: bytes, kid: int) -> None:
        self.kid = kid
        self._state = _KeyState(base_key, kid)
        self.ctr = 0
        self._lock = threading.Lock()

    def seal(self, plaintext: bytes, metadata: bytes = b"") -> bytes:
        with self._lock:
            ctr = self.ctr
            if ctr > MAX_COUNTER:
                raise SFrameError("counter exhausted: this key must not seal more")
            self.ctr += 1
        return _seal(self._state, self.kid, ctr, metadata, plaintext)


class ReplayWindow:
    """The counters seen of one KID: the newest, and which of the REPLAY_WINDOW before it."""

    def __init__(self) -> None:
        self.top = -1
        self.bits = 0  # bit i: counter top - i was seen

    def fresh(self, ctr: int) -> bool:
        if ctr > self.top:
            return True
        behind = self.top - ctr
        return behind < REPLAY_WINDOW and not self.bits >> behind & 1

    def mark(self, ctr: int) -> None:
        if ctr > self.top:
            shift = ctr - self.top
            self.bits = (self.bits << shift | 1) & ((1 << REPLAY_WINDOW) - 1)
            self.top = ctr
        else:
            self.bits |= 1 << (self.top - ctr)


class Opener:
    """Opens messages of the KIDs it has keys for, each counter once."""

    def __init__(self) -> None:
        self._states: dict[int, _KeyState] = {}
        self._windows: dict[int, ReplayWindow] = {}

    def add_key(self, kid: int, base_key: bytes) -> None:
        if kid not in self._states:
            self._states[kid] = _KeyState(base_key, kid)
            self._windows[kid] = ReplayWindow()

    def knows(self, kid: int) -> bool:
        return kid in self._states

    def open(self, message: bytes, metadata: bytes = b"", replay: bool = True) -> bytes:
        """The plaintext of ``message``. SFrameError for a short message, an unknown KID or a
        failed tag; ReplayError for a counter seen before (``replay=False``: a message that
        may be read more than once, a snapshot kept by the relay)."""
        header, at = Header.parse(message)
        state = self._states.get(header.kid)
        if state is None:
            raise SFrameError(f"no key for KID {header.kid:#x}")
        if len(message) - at < NT:
            raise SFrameError(f"message of {len(message)} bytes is shorter than its tag")
        window = self._windows[header.kid]
        if replay and not window.fresh(header.ctr):
            raise ReplayError(f"KID {header.kid:#x} counter {header.ctr} seen before")
        try:
            plaintext = state.aead.decrypt(
                _nonce(state.salt, header.ctr), message[at:], message[:at] + metadata
            )
        except InvalidTag:
            raise SFrameError("message does not authenticate (wrong key, or altered)") from None
        if replay:
            window.mark(header.ctr)
        return plaintext


# --- a room's keys ---------------------------------------------------------------------------


def _name_tag(name: str) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "big")


def new_kid(name: str) -> int:
    """A KID for one run of participant ``name``: its name's tag, then 32 random bits."""
    return _name_tag(name) << 32 | secrets.randbits(32)


def kid_is_of(kid: int, name: str) -> bool:
    return kid >> 32 == _name_tag(name)


def metadata(room: str, name: str, kind: bytes) -> bytes:
    """The associated data of ``name``'s messages of ``kind``: a message cannot be moved to
    another room, sender or purpose by whoever routes it."""
    return b"facewire/" + room.encode() + b"/" + name.encode() + b"/" + kind


@dataclass(frozen=True)
class RoomKey:
    """A room's secret; every participant holds the same one."""

    room: str
    secret: bytes

    def base_key(self, name: str, kid: int | None = None) -> bytes:
        """Participant ``name``'s SFrame base key (the same for each of its runs, ``kid``)."""
        info = b"facewire room sender " + self.room.encode() + b"\0" + name.encode()
        return _hkdf_expand(_hkdf_extract(b"", self.secret), info, NK)

    def metadata(self, name: str, kind: bytes) -> bytes:
        return metadata(self.room, name, kind)

    @classmethod
    def generate(cls, room: str) -> RoomKey:
        return cls(room, secrets.token_bytes(32))

    def text(self) -> str:
        secret = base64.b64encode(self.secret).decode()
        return f"{ROOM_KEY_MAGIC}\nroom: {self.room}\nsecret: {secret}\n"

    @classmethod
    def parse(cls, text: str, where: str = "room key") -> RoomKey:
        lines = text.strip().splitlines()
        if not lines or lines[0].strip() != ROOM_KEY_MAGIC:
            raise ValueError(f"{where}: not a facewire room key (make one: facewire keys --room)")
        fields = dict(line.split(":", 1) for line in lines[1:] if ":" in line)
        try:
            secret = base64.b64decode(fields["secret"].strip(), validate=True)
            room = fields["room"].strip()
        except (KeyError, ValueError):
            raise ValueError(f"{where}: expected 'room:' and a base64 'secret:' line") from None
        if len(secret) < 16:
            raise ValueError(f"{where}: secret of {len(secret)} bytes, at least 16 needed")
        return cls(room, secret)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> RoomKey:
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ValueError(f"cannot read room key {path}: {exc.strerror}") from None
        return cls.parse(text, str(path))

    def write(self, path: str | os.PathLike[str], force: bool = False) -> None:
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
        try:
            fd = os.open(path, flags, 0o600)
        except FileExistsError:
            raise ValueError(f"{path} exists (--force replaces it)") from None
        with os.fdopen(fd, "w") as f:
            f.write(self.text())
