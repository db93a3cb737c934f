"""A relay node dies under a sender: how long the others see its face freeze.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_room_failover.py [--runs 3]
       [--deaths killed,frozen] [--frames 600]

Each run starts a cluster of three nats-server processes with routes on loopback and three
participants sending the bundled clip at 176x144 (alice, bob, carol; each given every node,
each on a node of its own choosing), waits until each sees the other two, then ends the node
alice's stream goes through: ``killed`` (SIGKILL: its connections close), ``terminated``
(SIGTERM: nats-server's own shutdown) or ``frozen`` (SIGSTOP: it stops answering and its
connections stay open, as a machine that lost its power or its network). Printed per run:
how long alice took to say she had reconnected (from the kill, as this script reads her
output), and, as bob and carol saw her, the longest wait between two of her decoded frames
that overlaps the 5 s from the kill (their stats' ``freezes``: waits of 200 ms or more), her
sessions (1: no new snapshot) and who shared her node.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facewire.protocol.sframe import RoomKey  # noqa: E402
from facewire.relay import Relay, RelayConfig, free_port  # noqa: E402

SIGNALS = {"killed": signal.SIGKILL, "terminated": signal.SIGTERM, "frozen": signal.SIGSTOP}
WINDOW_S = 5.0


class Person:
    """``facewire room`` in a process of its own, its output lines timed as they come."""

    def __init__(self, cmd: list[str], env: dict[str, str]) -> None:
        self.process = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def said(self, text: str, after: float = 0.0) -> tuple[float, str] | None:
        return next(((t, x) for t, x in self.lines if text in x and t >= after), None)

    def wait_for(self, text: str, timeout_s: float = 120.0, after: float = 0.0) -> float:
        deadline = time.monotonic() + timeout_s
        while (found := self.said(text, after)) is None:
            if time.monotonic() > deadline or self.process.poll() is not None:
                raise RuntimeError(f"never said {text!r}: {[x for _, x in self.lines]}")
            time.sleep(0.02)
        return found[0]


def one_run(death: str, frames: int, work: Path) -> dict[str, object]:
    key = work / "bench.room"
    RoomKey.generate("bench").write(key)
    env = dict(os.environ, PYOPENGL_PLATFORM="egl", PYTHONUNBUFFERED="1")
    ports = [(free_port(), free_port()) for _ in range(3)]
    relays: list[Relay] = []
    people: dict[str, Person] = {}
    try:
        for port, route in ports:
            config = RelayConfig(port=port, token="bench-token", name=f"n{port}")
            config.cluster = ("127.0.0.1", route)
            config.routes = [f"nats-route://127.0.0.1:{r}" for p, r in ports if r != route]
            relays.append(Relay(config).start())
        servers = [a for r in relays for a in ("--server", r.config.client_url())]
        for name in ("alice", "bob", "carol"):
            cmd = [sys.executable, "-m", "facewire", "room", "--room", "bench", "--name", name,
                   "--key", str(key), *servers, "--max-size", "176x144", "--no-sound", "--loop",
                   "--frames", str(frames), "--stats", str(work / f"{name}.json")]  # fmt: skip
            people[name] = Person(cmd, env)
        for name, person in people.items():
            for other in people:
                if other != name:
                    person.wait_for(f"{other} joined")
        time.sleep(3.0)  # the joins' keyframes are past
        nodes = {}
        for name, person in people.items():
            line = person.said("joined room bench as")
            assert line is not None
            nodes[name] = int(re.search(r":(\d+)$", line[1]).group(1))  # type: ignore[union-attr]
        node = next(r for r in relays if r.config.port == nodes["alice"])
        assert node.process is not None
        killed_at = time.monotonic()
        node.process.send_signal(SIGNALS[death])
        back = people["alice"].wait_for("reconnected to the relay at", 30, after=killed_at)
        for person in people.values():
            person.process.wait(300)
        if death == "frozen":
            node.process.kill()
    finally:
        for person in people.values():
            if person.process.poll() is None:
                person.process.kill()
        for relay in relays:
            if relay.process is not None and relay.process.poll() is None:
                relay.process.kill()
            relay.close()
    row: dict[str, object] = {
        "reconnect_ms": round((back - killed_at) * 1000),
        "shared": [n for n in ("bob", "carol") if nodes[n] == nodes["alice"]],
    }
    window = (killed_at * 1e6, (killed_at + WINDOW_S) * 1e6)
    for name in ("bob", "carol"):
        seen = json.loads((work / f"{name}.json").read_text())["peers"]["alice"]
        overlapping = [
            ms
            for start, ms in seen["freezes"]
            if start < window[1] and start + ms * 1e3 > window[0]
        ]
        row[name] = (max(overlapping, default=0.0), seen["sessions"])
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--deaths", default="killed,frozen", help="killed, terminated, frozen")
    p.add_argument("--frames", type=int, default=600, help="each participant's (30 fps)")
    args = p.parse_args()
    deaths = args.deaths.split(",")
    if unknown := set(deaths) - set(SIGNALS):
        p.error(f"unknown --deaths {', '.join(sorted(unknown))}")
    print("death       run  alice reconnected ms  freeze bob ms  carol ms  sessions  on her node")
    for death in deaths:
        for run in range(args.runs):
            with tempfile.TemporaryDirectory(prefix="bench-failover-") as work:
                row = one_run(death, args.frames, Path(work))
            (bob, bob_sessions), (carol, carol_sessions) = row["bob"], row["carol"]  # type: ignore[misc]
            shared = ", ".join(row["shared"]) or "no one else"  # type: ignore[arg-type]
            print(f"{death:<10}  {run + 1:>3}  {row['reconnect_ms']:>20}  {bob:>13.0f}  "
                  f"{carol:>8.0f}  {bob_sessions}, {carol_sessions}      {shared}")  # fmt: skip
    print(f"(freeze: the longest wait between two of alice's decoded frames overlapping the "
          f"{WINDOW_S:g} s from the kill; 0: none of 200 ms or more)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
