"""``facewire keys``: make a CURVE keypair for one end of a call.

Writes ``NAME.key`` (public: give it to the other end) and ``NAME.key_secret`` (secret, mode
0600: keep it) in ZeroMQ's certificate format. The sender admits the receivers whose public
keys it is given; a receiver needs the sender's public key.
"""

from __future__ import annotations

import argparse
import logging

from protocol.keys import write_keypair

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
    p.add_argument("--out", metavar="DIR", required=True, help="folder to write the files to")
    p.add_argument("--name", default="facewire", help="file name stem (default: facewire)")
    p.add_argument("--force", action="store_true", help="replace existing key files")

    def run(args: argparse.Namespace) -> int:
        public, secret = write_keypair(args.out, args.name, force=args.force)
        print(f"wrote {public} (public) and {secret} (secret, keep it private)")
        return 0

    p.set_defaults(func=run)
