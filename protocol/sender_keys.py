"""A room's keys from the CURVE keypairs its participants already have (``facewire keys``).

RFC 9605 leaves the distribution of SFrame keys to the application (section 9); this is its
"sender keys" arrangement. Each run of a participant takes a random SFrame base key and a new
KID, and seals (KID, base key) to each peer it names with ``--peer NAME.key``: a box as NaCl's
``crypto_box`` makes one from two Curve25519 keypairs (the kind ZeroMQ's CURVE uses), built
from ``cryptography``'s primitives: X25519 of the sender's secret key and the recipient's public
key, HKDF-SHA256 (RFC 5869) over it and both names, AES-128-GCM with a random nonce. Only that
sender and that recipient can compute the box's key, so the box both hides the base key and
proves who sealed it. The boxes lie in the room's bucket, ``SENDER.to.RECIPIENT``; the relay
learns who may hear whom, not a key.

A peer is known by the stem of its public key file (``keys/alice.key`` is alice). Static
keys: no forward secrecy beyond a run (a stolen secret key opens the boxes that were sealed
to it while they are kept, and with them the recorded media of those runs).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from facewire.protocol.keys import (
    PUBLIC_SUFFIX,
    load_keypair,
    load_public_key,
    public_key_files,
)
from facewire.protocol.sframe import NK, SFrameError, metadata, new_kid
from facewire.protocol.subjects import check_name

BOX_INFO = b"facewire room sender key box 1"
NONCE_BYTES = 12
KID_BYTES = 8
BOX_BYTES = NONCE_BYTES + KID_BYTES + NK + 16  # nonce, KID, base key, GCM tag


class KeyUnavailable(SFrameError):
    """A sender's key that this participant does not have (said once, in one line)."""


def _raw(z85: bytes) -> bytes:
    from zmq.utils import z85 as codec

    return bytes(codec.decode(z85))


def _box(my_secret: bytes, their_public: bytes, room: str, sender: str, recipient: str) -> AESGCM:
    shared = X25519PrivateKey.from_private_bytes(my_secret).exchange(
        X25519PublicKey.from_public_bytes(their_public)
    )
    info = b"\0".join([BOX_INFO, room.encode(), sender.encode(), recipient.encode()])
    return AESGCM(HKDF(hashes.SHA256(), NK, salt=None, info=info).derive(shared))


def box_name(sender: str, recipient: str) -> str:
    """The bucket's key for the box ``sender`` sealed to ``recipient``."""
    return f"{sender}.to.{recipient}"


def seal_sender_key(my_secret: bytes, their_public: bytes, room: str, sender: str,
                    recipient: str, kid: int, base_key: bytes) -> bytes:  # fmt: skip
    """``sender``'s (KID, base key) for ``recipient`` (raw 32-byte X25519 keys)."""
    nonce = secrets.token_bytes(NONCE_BYTES)
    box = _box(my_secret, their_public, room, sender, recipient)
    return nonce + box.encrypt(nonce, kid.to_bytes(KID_BYTES, "big") + base_key, None)


def open_sender_key(my_secret: bytes, their_public: bytes, room: str, sender: str,
                    recipient: str, sealed: bytes) -> tuple[int, bytes]:  # fmt: skip
    """(KID, base key) from a box ``sender`` sealed to ``recipient``; SFrameError when it
    is not one (another sender's, room's or recipient's, or altered)."""
    if len(sealed) != BOX_BYTES:
        raise SFrameError(f"{sender}'s key box is {len(sealed)} bytes, expected {BOX_BYTES}")
    box = _box(my_secret, their_public, room, sender, recipient)
    try:
        plain = box.decrypt(sealed[:NONCE_BYTES], sealed[NONCE_BYTES:], None)
    except InvalidTag:
        raise KeyUnavailable(
            f"{sender}'s key box does not open: not sealed by the key in {sender}{PUBLIC_SUFFIX} "
            f"for {recipient}'s ({sender} stays hidden)"
        ) from None
    return int.from_bytes(plain[:KID_BYTES], "big"), plain[KID_BYTES:]


def load_peers(sources: list[str]) -> dict[str, bytes]:
    """Peer name -> raw public key, from ``NAME.key`` files or folders of them."""
    peers: dict[str, bytes] = {}
    for file in public_key_files(sources):
        name = file.name.removesuffix(PUBLIC_SUFFIX)
        check_name(name, f"peer (from {file})")
        peers[name] = _raw(load_public_key(file))
    return peers


class SenderKeys:
    """This participant's own run key and the boxes its peers sealed to it.

    The same interface as :class:`RoomKey` where a room uses one (``room``, ``base_key``,
    ``metadata``); ``fetch(box_name)`` reads a box from the room's bucket (None: not there).
    """

    def __init__(self, room: str, name: str, secret_key_file: str | os.PathLike[str],
                 peers: dict[str, bytes]) -> None:  # fmt: skip
        pair = load_keypair(secret_key_file)
        self.room = room
        self.name = name
        self._secret = _raw(pair.secret)
        self.public = _raw(pair.public)
        self.peers = {n: key for n, key in peers.items() if n != name}
        self.kid = new_kid(name)
        self.own_key = secrets.token_bytes(NK)
        self.fetch: Callable[[str], bytes | None] = lambda _: None
        self._known: dict[tuple[str, int], bytes] = {}

    def boxes(self) -> dict[str, bytes]:
        """This run's key sealed to each peer, by the bucket's key for it."""
        return {
            box_name(self.name, peer): seal_sender_key(
                self._secret, public, self.room, self.name, peer, self.kid, self.own_key
            )
            for peer, public in self.peers.items()
        }

    def base_key(self, name: str, kid: int | None = None) -> bytes:
        """``name``'s base key for run ``kid``, from the box it sealed to this participant;
        KeyUnavailable (one line saying why) when there is none to open."""
        if name == self.name and kid in (None, self.kid):
            return self.own_key
        if kid is not None and (name, kid) in self._known:
            return self._known[(name, kid)]
        public = self.peers.get(name)
        if public is None:
            raise KeyUnavailable(
                f"{name} is not among {self.name}'s --peer keys ({name} stays hidden)"
            )
        sealed = self.fetch(box_name(name, self.name))
        if sealed is None:
            raise KeyUnavailable(
                f"{name} sealed no key to {self.name}: is {self.name}'s public key among "
                f"{name}'s --peer keys? ({name} stays hidden)"
            )
        box_kid, key = open_sender_key(self._secret, public, self.room, name, self.name, sealed)
        if kid is not None and box_kid != kid:
            raise SFrameError(f"{name}'s key box is for another run (KID {box_kid:#x})")
        self._known[(name, box_kid)] = key
        return key

    def metadata(self, name: str, kind: bytes) -> bytes:
        return metadata(self.room, name, kind)
