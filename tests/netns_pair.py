"""Two hosts on one machine: two network namespaces with their own addresses and a link
between them that delays, jitters and loses packets like ``tc netem``.

Where the kernel has netem, the link is a veth pair with ``tc qdisc add dev ... root netem
delay D J loss L`` on both ends. This project's machines run a kernel built without netem;
there the link is two TUN devices joined by tests/link_emulator.py, a user-space relay that
applies the same model (see its docstring). Either way the two namespaces share the machine's
CLOCK_MONOTONIC, so a capture time stamped in one can be subtracted in the other.

Names are unique per use (process id and a counter) and everything is removed on exit, also
after a failure. :func:`unavailable` says why namespaces cannot be made here (None if they can).
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ADDRESS_A = "10.77.0.1"
ADDRESS_B = "10.77.0.2"
_count = itertools.count(1)


@dataclass(frozen=True)
class Netem:
    """netem's ``delay DELAY_MS JITTER_MS loss LOSS%``, applied in each direction."""

    delay_ms: float = 40.0
    jitter_ms: float = 10.0
    loss: float = 0.05

    def tc_args(self) -> list[str]:
        return [
            "delay",
            f"{self.delay_ms:g}ms",
            f"{self.jitter_ms:g}ms",
            "loss",
            f"{self.loss * 100:g}%",
        ]

    def __str__(self) -> str:
        return " ".join(self.tc_args())


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, check=check, timeout=30)


def unavailable() -> str | None:
    """Why two namespaces cannot be made on this machine, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    if shutil.which("ip") is None:
        return "no `ip` command (Debian package iproute2)"
    name = f"fwprobe{os.getpid()}"
    made = _run("ip", "netns", "add", name, check=False)
    if made.returncode != 0:
        return f"cannot make a network namespace: {made.stderr.strip()}"
    _run("ip", "netns", "del", name, check=False)
    if not kernel_has_netem() and not os.path.exists("/dev/net/tun"):
        return "the kernel has neither netem (tc) nor TUN devices (/dev/net/tun) for the link"
    return None


def kernel_has_netem() -> bool:
    """True when ``tc ... netem`` works here (tried on a throwaway namespace's loopback)."""
    if shutil.which("tc") is None:
        return False
    name = f"fwnetem{os.getpid()}"
    if _run("ip", "netns", "add", name, check=False).returncode != 0:
        return False
    try:
        tried = _run("tc", "-n", name, "qdisc", "add", "dev", "lo", "root", "netem", "delay",
                     "1ms", check=False)  # fmt: skip
        return tried.returncode == 0
    finally:
        _run("ip", "netns", "del", name, check=False)


class TwoHosts:
    """Namespaces ``a`` (10.77.0.1) and ``b`` (10.77.0.2) joined by a link with ``netem``.

    Use as a context manager; :meth:`command` prefixes a command to run in a namespace.
    ``how`` says which link was made ("veth + tc netem" or "TUN + user-space netem").
    """

    def __init__(
        self, netem: Netem | None = None, seed: int = 1, block_udp_after: int | None = None
    ) -> None:
        """``block_udp_after``: a firewall on the link drops UDP once that many UDP packets
        have passed (the user-space link, whatever the kernel has)."""
        n = f"{os.getpid() % 100000}x{next(_count)}"
        self.a, self.b = f"fwa{n}", f"fwb{n}"
        self.netem = netem or Netem()
        self.seed = seed
        self.block_udp_after = block_udp_after
        self.how = ""
        self.relayed = ""  # the link emulator's packet counts, once closed
        self._relay: subprocess.Popen[str] | None = None

    def __enter__(self) -> TwoHosts:
        try:
            for ns in (self.a, self.b):
                _run("ip", "netns", "add", ns)
                _run("ip", "-n", ns, "link", "set", "lo", "up")
            if kernel_has_netem() and self.block_udp_after is None:
                self._veth()
            else:
                self._tun()
        except BaseException:
            self.close()
            raise
        return self

    def _veth(self) -> None:
        dev_a, dev_b = f"{self.a}v", f"{self.b}v"
        _run("ip", "link", "add", dev_a, "type", "veth", "peer", "name", dev_b)
        for ns, dev, address in ((self.a, dev_a, ADDRESS_A), (self.b, dev_b, ADDRESS_B)):
            _run("ip", "link", "set", dev, "netns", ns)
            _run("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", dev)
            _run("ip", "-n", ns, "link", "set", dev, "up")
            _run("tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "netem", *self.netem.tc_args())
        self.how = f"veth pair + tc netem {self.netem}"

    def _tun(self) -> None:
        netem = self.netem
        self._relay = subprocess.Popen(
            [
                sys.executable,
                str(HERE / "link_emulator.py"),
                *(self.a, f"{self.a}t", ADDRESS_A, self.b, f"{self.b}t", ADDRESS_B),
                *("--delay-ms", str(netem.delay_ms), "--jitter-ms", str(netem.jitter_ms)),
                *("--loss", str(netem.loss), "--seed", str(self.seed)),
                *(
                    ()
                    if self.block_udp_after is None
                    else ("--block-udp-after", str(self.block_udp_after))
                ),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self._relay.stdout is not None
        line = self._relay.stdout.readline().strip()
        if line != "ready":
            self._relay.kill()
            _, err = self._relay.communicate(timeout=10)
            raise RuntimeError(f"the link emulator did not start: {err.strip() or line}")
        self.how = f"TUN pair + user-space netem {netem} (this kernel has no netem)"

    def command(self, namespace: str, *cmd: str) -> list[str]:
        return ["ip", "netns", "exec", namespace, *cmd]

    def close(self) -> None:
        if self._relay is not None and self._relay.poll() is None:
            self._relay.terminate()
            try:
                out, _ = self._relay.communicate(timeout=10)
                self.relayed = out.strip()
            except subprocess.TimeoutExpired:
                self._relay.kill()
                self._relay.communicate()
        for ns in (self.a, self.b):
            _run("ip", "netns", "del", ns, check=False)  # takes its devices with it

    def __exit__(self, *exc: object) -> None:
        self.close()
