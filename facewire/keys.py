"""``facewire keys``: make a CURVE keypair for one end of a call, or a room's secret.

Writes ``NAME.key`` (public: give it to the other end) and ``NAME.key_secret`` (secret, mode
0600: keep it) in ZeroMQ's certificate format. The sender admits the receivers whose public
keys it is given; a receiver needs the sender's public key.

``--room NAME`` writes ``NAME.room`` instead (mode 0600): the secret every participant of
room NAME passes as ``facewire room --key``; it never goes to the relay (protocol/sframe.py).

``--tls-for HOST`` writes ``HOST.crt`` and ``HOST.key`` (mode 0600): a self-signed TLS
certificate for a relay on HOST (``facewire relay --tls-cert``), which its participants trust
with ``facewire room --tls-ca HOST.crt`` (facewire/tls.py).
"""

from __future__ import annotations

import argparse
import logging

from facewire.protocol.keys import write_keypair

logger = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``keys`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "keys",
        help="make a CURVE keypair (NAME.key public, NAME.key_secret secret)",
        description="Makes a CURVE keypair for one end of a call: NAME.key (public: give it "
        "to the other end) and NAME.key_secret (secret, mode 0600: keep it). A folder that "
        "does not exist is made, readable by you alone.",
    )
    p.add_argument("--out", metavar="DIR", help="folder to write the files to (--room: default .)")
    p.add_argument("--room", metavar="NAME", help="make room NAME's secret, NAME.room")
    p.add_argument(
        "--tls-for", metavar="HOST",
        help="make a self-signed TLS certificate for a relay on HOST (a name or an IP address): "
        "HOST.crt, and HOST.key (mode 0600)",
    )  # fmt: skip
    p.add_argument("--name", default="facewire", help="file name stem (default: facewire)")
    p.add_argument("--force", action="store_true", help="replace existing key files")

    def run(args: argparse.Namespace) -> int:
        if args.room is not None and args.tls_for is not None:
            raise ValueError("--room and --tls-for make different files: one at a time")
        if args.room is not None:
            return _room_key(args.room, args.out or ".", args.force)
        if args.tls_for is not None:
            from facewire.tls import write_self_signed

            cert, key = write_self_signed(args.tls_for, args.out or ".", force=args.force)
            print(
                f"wrote {cert} (the relay's certificate: give it to its participants, "
                f"--tls-ca) and {key} (its key, keep it private)"
            )
            return 0
        if args.out is None:
            raise ValueError(
                "keys needs --out DIR (or --room NAME for a room's secret, or --tls-for HOST)"
            )
        public, secret = write_keypair(args.out, args.name, force=args.force)
        print(f"wrote {public} (public) and {secret} (secret, keep it private)")
        return 0

    p.set_defaults(func=run)


def _room_key(room: str, out: str, force: bool) -> int:
    from pathlib import Path

    from facewire.protocol.sframe import RoomKey
    from facewire.protocol.subjects import check_name

    check_name(room, "room")
    path = Path(out) / f"{room}.room"
    path.parent.mkdir(parents=True, exist_ok=True)
    RoomKey.generate(room).write(path, force=force)
    print(f"wrote {path} (room {room}'s secret: give it to its participants only)")
    return 0
