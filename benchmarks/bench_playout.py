"""What the playout's jitter buffer costs in latency and buys in even motion, across a network.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_playout.py [--frames N] [--runs N]
       [--delays 0,auto,40,80] [--loss 0.05] [--loopback]

``facewire receive`` and ``facewire send`` (CURVE keys, the bundled clip at 30 fps) run as
separate processes in two network namespaces joined by a link with netem's delay 40 ms ± 10 ms
and 5% loss each way (tests/netns_pair.py: ``tc netem`` where the kernel has it, else TUN
devices and tests/link_emulator.py applying the same model), once per playout delay:
``0`` draws each frame as it arrives (the receiver before the jitter buffer), ``auto`` adapts
the delay to the jitter seen, a number fixes it. Same link seed for every delay, so each meets
the same network. Both namespaces share CLOCK_MONOTONIC, so glass-to-glass latency (capture
to rendered picture) is measured directly.

Per delay it prints: capture to arrival of the fastest frame and how much later the others
came (the spread the buffer has to cover); latency p50 / p99 (issue 6 asks at most the link's
delay + 40 ms and + 80 ms); the delay the buffer aimed at and how long frames waited in it; and
how the pictures reached the screen (receiver/smoothness.py): the spread of the intervals
between pictures, the motion jitter (spread of time between two pictures minus time between
the instants they show: 0 when motion plays at its captured pace), and on a screen refreshing
at 30 Hz the refreshes that repeat the previous picture and the pictures never seen, plus
frames decoded but not shown (late) and freezes. Needs root for the namespaces.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the call helpers

from cli_call import Facewire, free_ports, run_facewire  # noqa: E402
from netns_pair import ADDRESS_B, Netem, TwoHosts, unavailable  # noqa: E402


def call(folder: Path, frames: int, hosts: TwoHosts | None, delay: str) -> dict:
    keys = folder / "keys"
    if not keys.exists():
        keys.mkdir()
        for name in ("alice", "bob"):
            assert run_facewire("keys", "--out", str(keys), "--name", name).returncode == 0
    stats = folder / "stats.json"
    if hosts is None:
        address, rx, tx = f"tcp://127.0.0.1:{free_ports(2)}", [], []
    else:
        address = f"tcp://{ADDRESS_B}:5555"
        rx, tx = hosts.command(hosts.b), hosts.command(hosts.a)
    receiver = Facewire(
        "receive", "--bind", address, "--once", "--stats", str(stats),
        "--playout-delay", delay,
        "--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key"),
        prefix=rx,
    )  # fmt: skip
    sender = Facewire(
        "send", "--connect", address, "--frames", str(frames),
        "--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key"),
        prefix=tx,
    )  # fmt: skip
    try:
        if sender.wait(300) != 0 or receiver.wait(60) != 0:
            raise SystemExit(sender.output() + "\n" + receiver.output())
    finally:
        sender.kill()
        receiver.kill()
    return json.loads(stats.read_text())


def show(delay: str, r: dict) -> str:
    lat, playout = r["latency_ms"], r["playout"]
    screen, arrival = playout["display"], playout["arrival_ms"]
    freezes = [length for _, length in r["freezes"]]
    spread = " / ".join(f"{arrival[q] - arrival['min']:.0f}" for q in ("p50", "p90", "p95", "p99"))
    return (
        f"| {delay} | {arrival['min']:.1f} | {spread} "
        f"| {lat['p50']:.1f} | {lat['p99']:.1f} | {lat['max']:.1f} "
        f"| {playout['delay_ms']:.1f} | {playout['buffer_ms']['p50']:.1f} / "
        f"{playout['buffer_ms']['p99']:.1f} "
        f"| {screen['interval_ms']['std']:.1f} | {screen['motion_jitter_ms']:.1f} "
        f"| {screen['repeated']} / {screen['skipped']} | {r['frames_skipped']} "
        f"| {len(freezes)} ({max(freezes, default=0)}) | {screen['pictures']} |"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--delays", default="0,auto,40,80", help="playout delays, comma-separated")
    p.add_argument("--delay-ms", type=float, default=40.0, help="the link's delay each way")
    p.add_argument("--jitter-ms", type=float, default=10.0)
    p.add_argument("--loss", type=float, default=0.05)
    p.add_argument("--loopback", action="store_true", help="127.0.0.1 instead of the link")
    args = p.parse_args()
    netem = Netem(args.delay_ms, args.jitter_ms, args.loss)
    reason = None if args.loopback else unavailable()
    if reason is not None:
        print(f"skipped: {reason}")
        return 0
    link = "127.0.0.1" if args.loopback else f"netem {netem} each way"
    print(f"link: {link}; {args.frames} frames of the bundled clip at 30 fps")
    print(
        "| playout delay | capture to arrival, fastest | later than it: p50 / p90 / p95 / p99 "
        "| latency p50 | p99 | max | buffer aims at | waited p50 / p99 "
        "| interval std | motion jitter | repeated / unseen (30 Hz) | dropped late "
        "| freezes (longest) | pictures |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(args.runs):
            for delay in args.delays.split(","):
                if args.loopback:
                    result, how = call(Path(tmp), args.frames, None, delay), "loopback"
                else:
                    with TwoHosts(netem, seed=run + 1) as hosts:
                        result = call(Path(tmp), args.frames, hosts, delay)
                    how = hosts.how
                print(show(delay, result) + f" run {run + 1}, {how}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
