"""A network link between two namespaces with netem's delay, jitter and loss, in user space.

For kernels built without netem (``tc qdisc add ... netem`` answers "Specified qdisc kind is
unknown", as on this project's machines). Two TUN devices, one moved into each namespace,
carry every IP packet between them through this process, which holds each packet for
``delay`` plus a uniform jitter in ``[-jitter, +jitter]`` (netem's ``delay 40ms 10ms``: no
correlation, so packets may be reordered, as netem does) and drops a fraction ``loss`` of
them (netem's ``loss 5%``), in each direction independently. TCP above it sees real delay,
reordering and loss, and retransmits.

Run as a script by :class:`netns_pair.TwoHosts`::

    python link_emulator.py NS_A DEV_A ADDR_A NS_B DEV_B ADDR_B --delay-ms 40 --jitter-ms 10
        --loss 0.05 --seed 1

It prints ``ready`` once both devices are up in their namespaces, and relays until SIGTERM or
until a namespace disappears. Packets are counted and the counts printed at the end.

``--block-udp-after N`` makes it a firewall that closes UDP once it has relayed N UDP packets
(0: from the start): every IPv4 packet of protocol 17 is dropped from then on, TCP still
passes.
"""

from __future__ import annotations

import argparse
import fcntl
import heapq
import os
import random
import select
import signal
import struct
import subprocess
import sys
import time

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
MTU = 1500


def open_tun(name: str) -> int:
    """A new TUN device ``name`` (IP packets, no header) in this process's namespace."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    return fd


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def configure(namespace: str, device: str, address: str, peer: str) -> None:
    """Move ``device`` into ``namespace`` as a point-to-point link ``address`` <-> ``peer``."""
    ip("link", "set", device, "netns", namespace)
    ip("-n", namespace, "addr", "add", address, "peer", peer, "dev", device)
    ip("-n", namespace, "link", "set", device, "mtu", str(MTU), "up")


class Link:
    """Both directions of the emulated link."""

    def __init__(
        self, delay_s: float, jitter_s: float, loss: float, seed: int, udp_allowed: float
    ) -> None:
        self.delay_s, self.jitter_s, self.loss = delay_s, jitter_s, loss
        self.udp_allowed = udp_allowed  # UDP packets let through before the firewall closes
        self.blocked = 0
        self.rng = random.Random(seed)
        self.queue: list[tuple[float, int, int, bytes]] = []  # (due, order, out fd, packet)
        self.order = 0
        self.relayed = 0
        self.dropped = 0

    def take(self, packet: bytes, out: int, now: float) -> None:
        if len(packet) > 9 and packet[0] >> 4 == 4 and packet[9] == 17:
            if self.udp_allowed <= 0:
                self.blocked += 1
                return
            self.udp_allowed -= 1
        if self.rng.random() < self.loss:
            self.dropped += 1
            return
        due = now + self.delay_s + self.rng.uniform(-self.jitter_s, self.jitter_s)
        self.order += 1
        heapq.heappush(self.queue, (due, self.order, out, packet))

    def flush(self, now: float) -> float | None:
        """Write the packets that are due; seconds until the next one (None: none queued)."""
        while self.queue and self.queue[0][0] <= now:
            _, _, out, packet = heapq.heappop(self.queue)
            try:
                os.write(out, packet)
                self.relayed += 1
            except BlockingIOError:
                self.dropped += 1  # the device's queue is full: a real link drops too
        return max(0.0, self.queue[0][0] - now) if self.queue else None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for side in ("a", "b"):
        p.add_argument(f"ns_{side}")
        p.add_argument(f"dev_{side}")
        p.add_argument(f"addr_{side}")
    p.add_argument("--delay-ms", type=float, default=40.0)
    p.add_argument("--jitter-ms", type=float, default=10.0)
    p.add_argument("--loss", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--block-udp-after", type=int, default=None, metavar="N")
    args = p.parse_args()
    stopping = False

    def stop(signum: int, frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    fd_a, fd_b = open_tun(args.dev_a), open_tun(args.dev_b)
    configure(args.ns_a, args.dev_a, args.addr_a, args.addr_b)
    configure(args.ns_b, args.dev_b, args.addr_b, args.addr_a)
    block = args.block_udp_after
    allowed = float("inf") if block is None else block
    link = Link(args.delay_ms / 1000, args.jitter_ms / 1000, args.loss, args.seed, allowed)
    other = {fd_a: fd_b, fd_b: fd_a}
    print("ready", flush=True)
    wait: float | None = None
    while not stopping:
        try:
            readable, _, _ = select.select([fd_a, fd_b], [], [], 0.2 if wait is None else wait)
        except InterruptedError:
            continue
        now = time.monotonic()
        for fd in readable:
            while True:
                try:
                    packet = os.read(fd, 65536)
                except BlockingIOError:
                    break
                except OSError:  # the namespace (and its device) is gone
                    stopping = True
                    break
                link.take(packet, other[fd], now)
        wait = link.flush(time.monotonic())
    print(
        f"relayed {link.relayed} packets, dropped {link.dropped}, UDP blocked {link.blocked}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
