"""What a call costs on the wire, counted on a real link: no model (facewire.wire has that).

:func:`measure_call` runs ``facewire receive`` and ``facewire send`` as a user runs them, in
two network namespaces joined by a veth pair (the sender at 10.77.0.1, the receiver at
10.77.0.2), and reads the veth's own counters: every byte and packet that crossed, each
way, with every header the kernel put on it. Needs root (``ip netns``); :func:`unavailable`
says why it cannot run here.

How the link is made, so that its counters are the wire's:

- IPv6 is off in both namespaces (no router solicitations or MLD reports on the link); what
  is left beside the call is ARP, a 28-byte request and reply now and then.
- ``gso_max_segs 1`` on both ends: TCP hands the device one segment per packet, as on a
  real NIC's wire. Left at the default, a veth takes 64 KB GSO bursts as one "packet" (1 MB
  through a fresh pair counted 30 packets instead of 695), and the snapshot's packets, and
  their headers, would go uncounted.
- Optionally a rate in both directions, ``tc qdisc add dev DEV root tbf rate {R}kbit burst
  1600 latency 400ms`` on each end's egress. ``burst 1600`` (bytes): the bucket holds one
  full-size frame (1514 bytes with its Ethernet header) and little more, so the link sends
  at its rate, a frame at a time, like a serial link; a smaller bucket would drop full-size
  frames, a larger one would let bursts through faster than the rate. ``latency 400ms``:
  the queue holds what the rate sends in 400 ms plus the bucket (tc's limit): 4.0 KB at
  48 kbit/s, 2.8 KB at 24; what comes with the queue full is dropped, as by a thin uplink's
  modem. (A drop in the sender's own namespace is seen by its TCP at once and sent again
  without counting as a retransmission.)
  tbf counts each frame's 14-byte Ethernet header against the rate, so a 48 kbit/s link
  carries a little less than 48 kbit/s of IP.

Rates are reported counting IP headers but not Ethernet's: ``bytes - 14 * packets``. Both
directions are read from the sender's end of the pair (its tx is "up", its rx "down"); the
receiver's end is read too, and over the whole call it must agree.

The figures come in two spans: ``steady``, a window of ``seconds`` that starts ``settle_s``
after the receiver has its whole snapshot (joining, the snapshot and the first frames are left
out), and ``call``, everything from before the receiver starts to after both have ended
(joining, the snapshot, the Bye). Beside them: the qdisc's drops (a shaped link), the TCP
segments each end sent and resent (/proc/net/snmp of each namespace), and both ends' own
``--stats``.

"Its whole snapshot": where the sender serves a draft of its snapshot first (over TCP) and
sends the full one paced in the datagrams behind the media (docs/protocol.md 8), the window
starts ``settle_s`` after the receiver took the full one, not the draft; it would otherwise
count several KB of snapshot as the call's steady rate. Both ends run with ``-v`` so that
their log says when: the sender's "served the snapshot (its draft)", the receiver's "the
snapshot's full images came". A full snapshot that does not come within REFINE_WAIT_S (a thin
link) is noted and the window starts anyway.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

SEND_ADDRESS = "10.77.0.1"
RECEIVE_ADDRESS = "10.77.0.2"
PORT = 5555
#: Bytes of Ethernet header on each frame the veth counts (no preamble, FCS or gap).
ETHERNET_HEADER = 14
#: The smallest packet on the link: an ARP request (28 bytes); IPv4 with TCP is 40 or more.
MIN_PACKET = 28
#: tbf's bucket, bytes: one full-size Ethernet frame (1514) and a little more.
TBF_BURST = 1600
#: tbf's queue, in time at the link's rate.
TBF_LATENCY_MS = 400
#: How long the receiver has to say it listens, and each end to end once told to.
START_TIMEOUT_S = 60.0
END_TIMEOUT_S = 30.0
#: How long the window waits, after the draft, for the receiver to take the full snapshot.
REFINE_WAIT_S = 20.0
#: What the ends log (with -v) when a draft is served and when the full snapshot is taken.
DRAFT_SERVED = "served the snapshot (its draft)"
FULL_SNAPSHOT_TAKEN = "the snapshot's full images came"

_count = itertools.count(1)
_REPO = Path(__file__).resolve().parent.parent


def tbf_args(rate_kbit: float) -> list[str]:
    """tc's words for the link's shaping at ``rate_kbit`` (after ``tc qdisc add dev DEV root``)."""
    return ["tbf", "rate", f"{rate_kbit:g}kbit", "burst", str(TBF_BURST),
            "latency", f"{TBF_LATENCY_MS}ms"]  # fmt: skip


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, check=check, timeout=30)


def unavailable(shaping: bool = False) -> str | None:
    """Why the link cannot be made on this machine (with ``shaping``: or shaped), or None."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    for tool in ("ip",) + (("tc",) if shaping else ()):
        if shutil.which(tool) is None:
            return f"no `{tool}` command (Debian package iproute2)"
    name = f"fwprobe{os.getpid() % 100000}x{next(_count)}"
    made = _run("ip", "netns", "add", name, check=False)
    if made.returncode != 0:
        return f"cannot make a network namespace: {made.stderr.strip()}"
    try:
        pair = _run("ip", "-n", name, "link", "add", "p0", "type", "veth", "peer", "name", "p1",
                    check=False)  # fmt: skip
        if pair.returncode != 0:
            return f"cannot make a veth pair: {pair.stderr.strip()}"
        if shaping:
            shaped = _run("tc", "-n", name, "qdisc", "add", "dev", "p0", "root", *tbf_args(48),
                          check=False)  # fmt: skip
            if shaped.returncode != 0:
                return f"cannot shape a veth with tc tbf: {shaped.stderr.strip()}"
    finally:
        _run("ip", "netns", "del", name, check=False)
    return None


@dataclass(frozen=True)
class Counters:
    """One end of the pair at one instant: what it sent (tx) and received (rx)."""

    at: float  # time.monotonic(), s
    tx_bytes: int
    tx_packets: int
    rx_bytes: int
    rx_packets: int


def _direction(octets: int, packets: int, seconds: float) -> dict[str, Any]:
    """One direction over a span: bytes as counted (with Ethernet headers), IP bytes
    (without), kbit/s of IP, packets a second and the mean IP packet."""
    ip = octets - ETHERNET_HEADER * packets
    return {
        "bytes": octets,
        "packets": packets,
        "ip_bytes": ip,
        "kbps": ip * 8 / 1000 / seconds if seconds > 0 else 0.0,
        "kbps_ethernet": octets * 8 / 1000 / seconds if seconds > 0 else 0.0,
        "pps": packets / seconds if seconds > 0 else 0.0,
        "mean_packet": ip / packets if packets else 0.0,
    }


def span(first: Counters, last: Counters) -> dict[str, Any]:
    """The link between two readings of the sender's end: ``up`` (its tx), ``down`` (its
    rx) and ``total``; kbit/s count IP headers, not Ethernet's."""
    seconds = last.at - first.at
    tx = (last.tx_bytes - first.tx_bytes, last.tx_packets - first.tx_packets)
    rx = (last.rx_bytes - first.rx_bytes, last.rx_packets - first.rx_packets)
    up, down = _direction(*tx, seconds), _direction(*rx, seconds)
    total = _direction(tx[0] + rx[0], tx[1] + rx[1], seconds)
    return {"seconds": seconds, "up": up, "down": down, "total": total}


class Link:
    """Namespaces for the sender (10.77.0.1) and the receiver (10.77.0.2) joined by a veth
    pair, shaped both ways with tbf at ``rate_kbit`` (None: as fast as the machine goes).

    A context manager: everything it made is deleted on leaving, also after a failure.
    Names are unique per process and use.
    """

    def __init__(self, rate_kbit: float | None = None) -> None:
        if rate_kbit is not None and not rate_kbit > 0:
            raise ValueError(f"expected a rate above 0 kbit/s, got {rate_kbit!r}")
        n = f"{os.getpid() % 100000}x{next(_count)}"
        self.send_ns, self.receive_ns = f"fwls{n}", f"fwlr{n}"
        self.send_dev, self.receive_dev = f"{self.send_ns}v", f"{self.receive_ns}v"
        self.rate_kbit = rate_kbit
        self.how = ""

    def __enter__(self) -> Link:
        try:
            self._make()
        except BaseException:
            self.close()
            raise
        return self

    def _make(self) -> None:
        for ns in (self.send_ns, self.receive_ns):
            _run("ip", "netns", "add", ns)
            _run("ip", "-n", ns, "link", "set", "lo", "up")
            _run("ip", "netns", "exec", ns, "sysctl", "-qw", "net.ipv6.conf.all.disable_ipv6=1",
                 "net.ipv6.conf.default.disable_ipv6=1", check=False)  # fmt: skip
        _run("ip", "link", "add", self.send_dev, "netns", self.send_ns, "type", "veth",
             "peer", "name", self.receive_dev, "netns", self.receive_ns)  # fmt: skip
        ends = ((self.send_ns, self.send_dev, SEND_ADDRESS),
                (self.receive_ns, self.receive_dev, RECEIVE_ADDRESS))  # fmt: skip
        for ns, dev, address in ends:
            _run("ip", "-n", ns, "link", "set", dev, "gso_max_segs", "1")
            _run("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", dev)
            _run("ip", "-n", ns, "link", "set", dev, "up")
            if self.rate_kbit is not None:
                _run("tc", "-n", ns, "qdisc", "add", "dev", dev, "root", *tbf_args(self.rate_kbit))
        self.how = (
            "veth, " + (f"tc {' '.join(tbf_args(self.rate_kbit))} each way"
                        if self.rate_kbit is not None else "unshaped")
        )  # fmt: skip

    def in_send(self, *cmd: str) -> list[str]:
        """``cmd`` run in the sender's namespace."""
        return ["ip", "netns", "exec", self.send_ns, *cmd]

    def in_receive(self, *cmd: str) -> list[str]:
        """``cmd`` run in the receiver's namespace."""
        return ["ip", "netns", "exec", self.receive_ns, *cmd]

    def counters(self, receiving_end: bool = False) -> Counters:
        """The sender's end of the pair now (or the receiver's)."""
        ns, dev = (
            (self.receive_ns, self.receive_dev) if receiving_end else (self.send_ns, self.send_dev)
        )
        before = time.monotonic()
        shown = _run("ip", "-n", ns, "-s", "-j", "link", "show", "dev", dev)
        at = (before + time.monotonic()) / 2
        stats = json.loads(shown.stdout)[0]["stats64"]
        return Counters(
            at, stats["tx"]["bytes"], stats["tx"]["packets"],
            stats["rx"]["bytes"], stats["rx"]["packets"],
        )  # fmt: skip

    def qdisc(self, receiving_end: bool = False) -> dict[str, Any]:
        """The root qdisc's counts on one end's egress: sent, dropped, over the rate."""
        ns, dev = (
            (self.receive_ns, self.receive_dev) if receiving_end else (self.send_ns, self.send_dev)
        )
        shown = _run("tc", "-n", ns, "-s", "-j", "qdisc", "show", "dev", dev, check=False)
        try:
            root = json.loads(shown.stdout)[0]
        except (ValueError, IndexError):
            return {}
        keys = ("kind", "bytes", "packets", "drops", "overlimits", "requeues", "backlog", "qlen")
        return {k: root[k] for k in keys if k in root}

    def tcp(self, receiving_end: bool = False) -> dict[str, int]:
        """TCP's counts in one namespace (/proc/net/snmp): segments out, in and resent."""
        ns = self.receive_ns if receiving_end else self.send_ns
        text = _run("ip", "netns", "exec", ns, "cat", "/proc/net/snmp").stdout
        rows = [line.split()[1:] for line in text.splitlines() if line.startswith("Tcp:")]
        if len(rows) != 2:
            return {}
        values = dict(zip(rows[0], rows[1], strict=True))
        return {k: int(values[k]) for k in ("OutSegs", "InSegs", "RetransSegs") if k in values}

    def close(self) -> None:
        for ns in (self.send_ns, self.receive_ns):
            _run("ip", "netns", "del", ns, check=False)  # takes its devices with it

    def __exit__(self, *exc: object) -> None:
        self.close()


def _environment() -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(_REPO), os.environ.get("PYTHONPATH", "")) if p
    )
    return env


class _Running:
    """A command in its own process, its output lines stamped as they come."""

    def __init__(self, name: str, cmd: Sequence[str], cwd: Path) -> None:
        self.name = name
        self.cmd = list(cmd)
        self.lines: list[tuple[float, str]] = []
        self.errors: list[str] = []
        self.logged: list[tuple[float, str]] = []  # stderr, stamped as it came
        self._new: queue.Queue[tuple[float, str] | None] = queue.Queue()
        self.process = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env=_environment(), cwd=cwd,
        )  # fmt: skip
        self._readers = [
            threading.Thread(target=self._read, args=(self.process.stdout, True), daemon=True),
            threading.Thread(target=self._read, args=(self.process.stderr, False), daemon=True),
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, stream: Any, is_stdout: bool) -> None:
        for line in stream:
            line = line.rstrip("\n")
            if is_stdout:
                stamped = (time.monotonic(), line)
                self.lines.append(stamped)
                self._new.put(stamped)
            else:
                self.errors.append(line)
                self.logged.append((time.monotonic(), line))
        if is_stdout:
            self._new.put(None)

    def said(self, text: str) -> float | None:
        """When it first said a line containing ``text`` (None: not yet)."""
        return next((at for at, line in self.lines if text in line), None)

    def logs(self, text: str) -> float | None:
        """When it first logged (stderr) a line containing ``text`` (None: not yet)."""
        return next((at for at, line in self.logged if text in line), None)

    def running(self) -> bool:
        return self.process.poll() is None

    def stop(self, timeout_s: float, sig: int = signal.SIGTERM) -> bool:
        """Signal it, wait up to ``timeout_s``; True when it ended by itself."""
        if self.running():
            self.process.send_signal(sig)
        return self.wait(timeout_s)

    def wait(self, timeout_s: float) -> bool:
        try:
            self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return False
        for reader in self._readers:
            reader.join(timeout=5)
        return True

    def kill(self) -> None:
        if self.running():
            self.process.kill()
            self.process.wait(timeout=10)

    def last(self) -> str:
        """``": "`` and its last line (stderr's if it failed), or nothing."""
        if not self.running():
            for reader in self._readers:
                reader.join(timeout=2)
        said = self.errors if self.process.returncode else [line for _, line in self.lines]
        return f": {said[-1]}" if said else ""

    def output(self, tail: int = 20) -> str:
        lines = [line for _, line in self.lines] + [f"stderr: {e}" for e in self.errors]
        return "\n".join([f"$ {' '.join(self.cmd)}", *lines[-tail:]])


def _hold(seconds: float, watched: Sequence[_Running]) -> str | None:
    """Wait ``seconds``, or less when a watched process ends: then which one."""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        for process in watched:
            if not process.running():
                return f"{process.name} ended (status {process.process.returncode}){process.last()}"
        time.sleep(min(0.1, left))
    return None


def _wait_for(
    process: _Running,
    text: str,
    timeout_s: float,
    watched: Sequence[_Running],
    logged: bool = False,
) -> str | None:
    """Until ``process`` says ``text`` (or logs it, ``logged``); a problem (None when it did)."""
    deadline = time.monotonic() + timeout_s
    while (process.logs(text) if logged else process.said(text)) is None:
        for other in watched:
            if not other.running():
                status = other.process.returncode
                return f"{other.name} ended (status {status}) before {text!r}{other.last()}"
        if time.monotonic() > deadline:
            return f"{process.name} did not say {text!r} within {timeout_s:g} s"
        time.sleep(0.05)
    return None


def _wait_for_full_snapshot(
    receiver: _Running, sender: _Running, both: Sequence[_Running], say: Callable[[str], None]
) -> str | None:
    """Where the sender served a draft, until the receiver has the full snapshot (at most
    REFINE_WAIT_S); a problem, or None."""
    if sender.logs(DRAFT_SERVED) is None:
        return None
    say("the receiver has the draft snapshot; waiting for the full one")
    problem = _wait_for(receiver, FULL_SNAPSHOT_TAKEN, REFINE_WAIT_S, both, logged=True)
    if problem is not None and all(p.running() for p in both):
        return (
            f"the receiver did not take the full snapshot within {REFINE_WAIT_S:g} s of its "
            "draft: the steady window holds its copies"
        )
    return problem


def _load(path: Path) -> dict[str, Any]:
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return {}


def _timeline(
    started: float, receiver: _Running, sender: _Running | None, stats: dict[str, Any]
) -> dict[str, float | None]:
    """When the call got going, in seconds from the sender's launch (``started``).

    ``offered_s``: the sender has its snapshot and connects (its "waiting for a receiver");
    ``snapshot_s``: the receiver has the snapshot (its "session ..."); ``joined_s``: the
    receiver said it is ready and frames flow (the sender's "a receiver joined");
    ``picture_s``: the receiver's first picture (its stats' ``first_frame_s``, counted from
    its own "waiting for a sender"). ``first_picture_s``: offered to first picture, what
    joining costs on this link (connecting, the snapshot, the renderer, the first frame).
    ``full_snapshot_s``: the receiver took the full snapshot after its draft (None: no draft
    was served, or the full one did not come).
    """

    def since(at: float | None) -> float | None:
        return None if at is None or math.isnan(started) else at - started

    offered = sender.said("waiting for a receiver") if sender is not None else None
    waiting = receiver.said("waiting for a sender")
    first = stats.get("first_frame_s") or []
    picture = waiting + first[0] if first and waiting is not None else None
    return {
        "offered_s": since(offered),
        "snapshot_s": since(receiver.said("session ")),
        "joined_s": since(sender.said("a receiver joined") if sender is not None else None),
        "picture_s": since(picture),
        "full_snapshot_s": since(receiver.logs(FULL_SNAPSHOT_TAKEN)),
        "first_picture_s": None if picture is None or offered is None else picture - offered,
    }


def measure_call(
    clip: Path | None = None,
    seconds: float = 20.0,
    rate_kbit: float | None = None,
    sound: bool = False,
    extra_send_args: Sequence[str] = (),
    extra_receive_args: Sequence[str] = (),
    *,
    settle_s: float = 3.0,
    join_timeout_s: float = 120.0,
    encrypted: bool = True,
    facewire: Sequence[str] = (sys.executable, "-m", "facewire"),
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """One call across a link of its own; what it cost on the wire (module docstring).

    ``clip``: the sender's ``--input`` (None: the bundled clip), played with ``--loop``;
    ``seconds``: the steady window, which starts ``settle_s`` after the receiver has the
    snapshot (its ``session ...`` line), or its full version where a draft came first (module
    docstring); ``rate_kbit``: tbf on both ends (None: unshaped); ``sound``: leave out
    ``--no-sound``. Both ends run with ``-v``. The receiver runs ``--once`` with CURVE keys
    made for the call (``encrypted=False``: both ends ``--plain``). The sender is stopped with
    SIGTERM at the window's end and the receiver ends on its Bye (or is stopped too).
    ``join_timeout_s`` bounds the wait for the snapshot.

    Returns a dict: ``link`` (how it was made), ``steady`` and ``call`` (:func:`span`:
    ``seconds`` and ``up``/``down``/``total`` each with ``bytes``, ``packets``, ``ip_bytes``,
    ``kbps``, ``kbps_ethernet``, ``pps``, ``mean_packet``), ``receiving_end_call`` (the
    receiver's end over the whole call, a cross-check), ``qdisc`` (each direction's egress)
    and ``tcp`` (per end: segments out, in, resent) over the whole call, ``tcp_steady`` (the
    sender's, over the window); the times of :func:`_timeline` (``first_picture_s``: from
    the sender offering its snapshot to the receiver's first picture); ``load`` (the
    machine's 1-minute load average at the window's start and end: both ends share its
    cores with whatever else runs, and a busy machine makes late frames); ``frames_shown``
    (the receiver's frames out), ``frames_sent`` (the sender's frames in), ``latency_ms`` (the
    receiver's percentiles, capture to picture: the namespaces share a clock); ``receiver``
    and ``sender`` (their ``--stats``); ``commands``; ``notes`` (what went wrong, in order)
    and ``problem`` (the first of them, or None). A call that never showed a picture has no
    ``steady``. Raises only when the link cannot be made.
    """
    say = progress or (lambda line: logger.info("%s", line))
    clip = None if clip is None else Path(clip).resolve()  # the ends run in a folder of their own
    with tempfile.TemporaryDirectory(prefix="fwonlink") as tmp, Link(rate_kbit) as link:
        folder = Path(tmp)
        keys = folder / "keys"
        keys.mkdir()
        for name in ("alice", "bob") if encrypted else ():
            made = subprocess.run(
                [*facewire, "keys", "--out", str(keys), "--name", name],
                capture_output=True, text=True, env=_environment(), timeout=60,
            )  # fmt: skip
            if made.returncode != 0:
                raise RuntimeError(f"facewire keys failed: {made.stderr.strip()}")
        say(f"link: {link.how}")
        address = f"tcp://{RECEIVE_ADDRESS}:{PORT}"
        receive_keys = ["--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key")]
        send_keys = ["--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key")]
        receive_cmd = [
            *facewire, "-v", "receive", "--bind", address, "--once",
            "--stats", str(folder / "receiver.json"),
            *(receive_keys if encrypted else ["--plain"]), *extra_receive_args,
        ]  # fmt: skip
        send_cmd = [
            *facewire, "-v", "send", "--connect", address, "--loop",
            *(["--input", str(clip)] if clip is not None else []),
            *([] if sound else ["--no-sound"]),
            "--stats", str(folder / "sender.json"),
            *(send_keys if encrypted else ["--plain"]), *extra_send_args,
        ]  # fmt: skip
        result: dict[str, Any] = {
            "link": link.how,
            "rate_kbit": rate_kbit,
            "encrypted": encrypted,
            "clip": str(clip) if clip is not None else "bundled",
            "commands": {"receive": link.in_receive(*receive_cmd), "send": link.in_send(*send_cmd)},
            "problem": None,
        }
        tcp0 = (link.tcp(), link.tcp(receiving_end=True))
        first, first_b = link.counters(), link.counters(receiving_end=True)
        receiver = _Running("the receiver", link.in_receive(*receive_cmd), folder)
        sender: _Running | None = None
        started = math.nan
        notes: list[str] = []

        def note(problem: str | None) -> bool:
            """Keep ``problem``; True when there was none."""
            if problem is not None:
                notes.append(problem)
                say(f"problem: {problem}")
            return problem is None

        try:
            if note(_wait_for(receiver, "waiting for a sender", START_TIMEOUT_S, [receiver])):
                sender = _Running("the sender", link.in_send(*send_cmd), folder)
                started = time.monotonic()
                both = [receiver, sender]
                if note(_wait_for(receiver, "session ", join_timeout_s, both)):
                    note(_wait_for_full_snapshot(receiver, sender, both, say))
                    going = all(p.running() for p in both)  # a late full snapshot is noted only
                    if going:
                        say(f"the receiver has the snapshot; settling {settle_s:g} s")
                    if going and note(_hold(settle_s, both)):
                        start, tcp1 = link.counters(), link.tcp()
                        result["load"] = [os.getloadavg()[0]]
                        say(f"steady window: {seconds:g} s")
                        note(_hold(seconds, both))
                        end, tcp2 = link.counters(), link.tcp()
                        result["load"].append(os.getloadavg()[0])
                        result["steady"] = span(start, end)
                        result["tcp_steady"] = {k: tcp2[k] - tcp1[k] for k in tcp2 if k in tcp1}
            says_bye = sender is not None and sender.running()
            if sender is not None and not sender.stop(END_TIMEOUT_S):
                note("the sender did not end on SIGTERM")
            if not receiver.wait(END_TIMEOUT_S if says_bye else 0):
                if says_bye:  # the Bye did not get through
                    note("the receiver did not end on the sender's Bye")
                if not receiver.stop(END_TIMEOUT_S):
                    note("the receiver did not end on SIGTERM")
        finally:
            for process in (sender, receiver):
                if process is not None:
                    process.kill()
        last, last_b = link.counters(), link.counters(receiving_end=True)
        tcp3 = (link.tcp(), link.tcp(receiving_end=True))
        result["call"] = span(first, last)
        result["receiving_end_call"] = span(first_b, last_b)
        result["qdisc"] = {"up": link.qdisc(), "down": link.qdisc(receiving_end=True)}
        result["tcp"] = {
            end: {k: after[k] - before[k] for k in after if k in before}
            for end, before, after in zip(("sender", "receiver"), tcp0, tcp3, strict=True)
        }
        stats, sent = _load(folder / "receiver.json"), _load(folder / "sender.json")
        if not stats:
            note("the receiver wrote no stats")
        result["receiver"], result["sender"] = stats, sent
        result["frames_shown"] = stats.get("frames_out")
        result["frames_sent"] = sent.get("frames_in")
        result["latency_ms"] = stats.get("latency_ms")
        result.update(_timeline(started, receiver, sender, stats))
        result["problem"] = notes[0] if notes else None
        result["notes"] = notes
        if notes:
            result["output"] = {
                "receiver": receiver.output(),
                "sender": sender.output() if sender is not None else "",
            }
        return result
