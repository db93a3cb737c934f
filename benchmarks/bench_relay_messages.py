"""What one room message costs the relay: nats-server's CPU per message published and per
copy delivered, for messages the size of a room's sealed bundles.

Usage: python benchmarks/bench_relay_messages.py [--subscribers 10] [--messages 20000]
       [--size 62]

One publisher and N subscribers (nats-py, one process) on one relay on loopback; the relay's
CPU is read from /proc before and after. The Python clients are the bottleneck of the rate,
not the relay: the figure is the relay's CPU per message, not its ceiling.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facewire.relay import Relay, RelayConfig, free_port  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def _cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


async def _run(url: str, pid: int, subscribers: int, messages: int, size: int) -> None:
    import nats

    got = [0] * subscribers
    done = asyncio.Event()
    conns = []
    for i in range(subscribers):
        nc = await nats.connect(url)
        conns.append(nc)

        async def count(msg: object, i: int = i) -> None:
            got[i] += 1
            if all(n >= messages for n in got):
                done.set()

        await nc.subscribe("fw.bench.m.alice", cb=count)
        await nc.flush()
    pub = await nats.connect(url)
    payload = os.urandom(size)
    before, started = _cpu(pid), time.monotonic()
    for n in range(messages):
        await pub.publish("fw.bench.m.alice", payload)
        if n % 500 == 0:
            await pub.flush()
    await pub.flush()
    await asyncio.wait_for(done.wait(), 120)
    cpu, elapsed = _cpu(pid) - before, time.monotonic() - started
    deliveries = messages * subscribers
    print(f"{messages} messages of {size} bytes to {subscribers} subscribers in {elapsed:.1f} s "
          f"({deliveries / elapsed:.0f} deliveries/s, the clients' pace)")  # fmt: skip
    print(f"relay CPU {cpu:.2f} s: {1e6 * cpu / messages:.1f} us per message published, "
          f"{1e6 * cpu / deliveries:.2f} us per copy delivered")  # fmt: skip
    for nc in [pub, *conns]:
        await nc.close()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--subscribers", type=int, default=10)
    p.add_argument("--messages", type=int, default=20000)
    p.add_argument("--size", type=int, default=62, help="bytes (a room's mean sealed bundle)")
    args = p.parse_args()
    with Relay(RelayConfig(port=free_port())) as relay:
        assert relay.process is not None
        url = relay.config.client_url()
        asyncio.run(_run(url, relay.process.pid, args.subscribers, args.messages, args.size))
    return 0


if __name__ == "__main__":
    sys.exit(main())
