"""Where the other end of a call is, and how to trust it: addresses and key options.

An address is ``tcp://HOST:PORT``. The side that binds names its own interface (``*``: all of
them); the side that connects names the other machine. One address stands for consecutive
ports: PORT carries the updates (PUB/SUB), PORT+1 the snapshot and back channel
(ROUTER/DEALER); a two-way call uses PORT+2 and PORT+3 for the other direction
(docs/protocol.md, section 3.1).

Keys: ``--key NAME.key_secret`` is this end's own keypair (``facewire keys`` makes it) and
``--peer NAME.key`` the other end's public key. The same two options serve both ends and both
directions: a sender admits receivers whose public key is among its ``--peer`` files (several,
or a folder of them), a receiver believes only the sender whose public key is its ``--peer``.
``--plain`` asks for an unencrypted call instead.
"""

from __future__ import annotations

import argparse
import logging
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facewire.protocol.keys import load_keypair, load_public_key, public_key_files

logger = logging.getLogger(__name__)

_ADDRESS = re.compile(r"^tcp://(?P<host>\*|[A-Za-z0-9_.\-]+):(?P<port>[0-9]{1,5})$")
_EXAMPLES = "e.g. tcp://*:5555 to bind, tcp://192.168.1.20:5555 to connect"


@dataclass(frozen=True)
class Address:
    """One end's address: ``bind`` on ``host`` (an interface, ``*`` for all) or connect to it."""

    host: str
    port: int
    bind: bool

    def ports(self, offset: int = 0) -> tuple[int, int]:
        """(updates, snapshot and back channel) ports, ``offset`` ports on from PORT."""
        return self.port + offset, self.port + offset + 1

    def describe(self, offset: int = 0) -> str:
        updates, snapshots = self.ports(offset)
        how = "on" if self.bind else "at"
        return f"{how} tcp://{self.host}:{updates} (and :{snapshots})"


def parse_address(text: str, bind: bool, ports_used: int = 2) -> Address:
    """``tcp://HOST:PORT`` checked: ValueError with one line when it cannot work.

    ``ports_used`` consecutive ports from PORT must exist. A connect needs a real host name
    or address that resolves (libzmq would accept anything and never connect).
    """
    match = _ADDRESS.match(text.strip())
    if match is None:
        raise ValueError(f"invalid address {text!r}: expected tcp://HOST:PORT ({_EXAMPLES})")
    host, port = match["host"], int(match["port"])
    highest = 65536 - ports_used
    if not 1 <= port <= highest:
        raise ValueError(
            f"invalid address {text!r}: port {port} outside 1..{highest} "
            f"(ports {port}..{port + ports_used - 1} are used)"
        )
    if not bind:
        if host == "*":
            raise ValueError(f"invalid address {text!r}: '*' can only be bound ({_EXAMPLES})")
        try:
            socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError):
            raise ValueError(f"invalid address {text!r}: cannot resolve host {host!r}") from None
    return Address(host, port, bind)


def check_ports_free(address: Address, count: int) -> None:
    """A binding end's ports PORT..PORT+count-1, checked before anything starts: ValueError
    with one line when one is taken (``call`` would otherwise start sending before its
    receiving side found out)."""
    if not address.bind:
        return
    host = None if address.host == "*" else address.host
    for port in range(address.port, address.port + count):
        family, kind, proto, _, where = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        with socket.socket(family, kind, proto) as sock:
            # As libzmq binds: a port left in TIME_WAIT by an earlier call is free.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(where)
            except OSError as exc:
                reason = (exc.strerror or str(exc)).lower()
                raise ValueError(f"cannot bind tcp://{address.host}:{port}: {reason}") from None


def add_address_arguments(p: argparse.ArgumentParser, example_port: int = 5555) -> None:
    """``--bind`` or ``--connect`` (exactly one)."""
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--bind",
        metavar="tcp://*:PORT",
        help=f"wait for the other end on this port (e.g. tcp://*:{example_port})",
    )
    where.add_argument(
        "--connect",
        metavar="tcp://HOST:PORT",
        help="connect to the other end, which binds that port",
    )


def address_from(args: argparse.Namespace, ports_used: int = 2) -> Address:
    if args.bind is not None:
        return parse_address(args.bind, bind=True, ports_used=ports_used)
    return parse_address(args.connect, bind=False, ports_used=ports_used)


def add_key_arguments(p: argparse.ArgumentParser, peer_help: str) -> None:
    """``--key`` and ``--peer`` (CURVE), or ``--plain``."""
    p.add_argument(
        "--key", metavar="NAME.key_secret", help="this end's secret key file (facewire keys)"
    )
    p.add_argument("--peer", metavar="NAME.key", action="append", default=[], help=peer_help)
    p.add_argument(
        "--plain", action="store_true", help="no encryption or authentication (a trusted network)"
    )


def _check_key_options(args: argparse.Namespace) -> None:
    if args.plain:
        if args.key or args.peer:
            raise ValueError("--plain and --key/--peer exclude each other")
        return
    if not args.key or not args.peer:
        missing = " and ".join(n for n, v in (("--key", args.key), ("--peer", args.peer)) if not v)
        raise ValueError(
            f"an encrypted call needs --key (your .key_secret) and --peer (the other end's .key); "
            f"missing {missing} (or pass --plain for an unencrypted call)"
        )
    load_keypair(args.key)  # a missing or wrong file ends here, before anything starts


def _public_key_files(peers: list[str]) -> list[Path]:
    files = public_key_files(peers)
    for path in files:
        load_public_key(path)
    return files


def sender_keys(args: argparse.Namespace) -> dict[str, Any]:
    """SenderEndpoint options: this end's keypair and the receivers it admits."""
    _check_key_options(args)
    if args.plain:
        return {"plain": True}
    return {"secret_key_file": args.key, "allowed_keys": _public_key_files(args.peer)}


def receiver_keys(args: argparse.Namespace) -> dict[str, Any]:
    """ReceiverEndpoint options: this end's keypair and the one sender it believes."""
    _check_key_options(args)
    if args.plain:
        return {"plain": True}
    if len(args.peer) != 1 or Path(args.peer[0]).is_dir():
        raise ValueError("a receiver believes one sender: give one --peer file, its public .key")
    load_public_key(args.peer[0])
    return {"secret_key_file": args.key, "server_key_file": args.peer[0]}
