"""Glass-to-glass latency of a call between two hosts on this machine, through the commands.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_call_hosts.py [--frames N] [--runs N]
           [--lossy-only]

``facewire receive`` and ``facewire send`` (CURVE keys, the bundled clip at 30 fps) run as
separate processes, first on 127.0.0.1, then in two network namespaces joined by a link with
netem's delay 40 ms ± 10 ms each way, without and with 5% loss each way (tests/netns_pair.py:
``tc netem`` on a veth pair where the kernel has netem, else a TUN pair and a user-space
relay applying the same model). The namespaces share CLOCK_MONOTONIC, so the receiver's
latency (capture to rendered frame) is measured directly. Prints, per link, frames out, the
latency percentiles, freezes (runs of frames shown stale), the receiver's own frame rate and
the sound's frames played and concealed. Run ``n`` of a link seeds its loss and jitter with ``n``;
``--lossy-only`` runs the lossy link alone.
Needs root for the namespaces; prints why and measures loopback only otherwise.
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

from facewire.protocol.constants import LATE_FRAME_MS  # noqa: E402

FPS = 30.0  # the bundled clip's


def call(folder: Path, frames: int, hosts: TwoHosts | None) -> dict:
    keys = folder / "keys"
    if not keys.exists():
        keys.mkdir()
        for name in ("alice", "bob"):
            assert run_facewire("keys", "--out", str(keys), "--name", name).returncode == 0
    stats = folder / "stats.json"
    if hosts is None:
        address, rx, tx = f"tcp://127.0.0.1:{free_ports(2)}", (), ()
    else:
        address = f"tcp://{ADDRESS_B}:5555"
        rx, tx = hosts.command(hosts.b), hosts.command(hosts.a)
    receiver = Facewire(
        "receive", "--bind", address, "--once", "--stats", str(stats),
        "--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key"), prefix=rx,
    )  # fmt: skip
    sender = Facewire(
        "send", "--connect", address, "--frames", str(frames),
        "--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key"), prefix=tx,
    )  # fmt: skip
    try:
        if sender.wait(300) != 0 or receiver.wait(60) != 0:
            raise SystemExit(sender.output() + "\n" + receiver.output())
    finally:
        sender.kill()
        receiver.kill()
    return json.loads(stats.read_text())


def _kbps(run: dict, channel: str) -> float:
    """Payload kbit/s a run's receiver got on ``channel``, over the clip's duration."""
    return run["bytes_received"].get(channel, 0) * 8 / (run["frames_out"] / FPS) / 1000


def _sound(run: dict) -> str:
    """The sound's 20 ms frames played and concealed: concealment covers a lost or late
    packet, and also the first frames of each pause the sender's Opus left silent (DTX), so
    a lossy run is compared with the loopback run's count, not with its own sum."""
    audio = run.get("audio") or {}
    return f"sound {audio.get('played', 0)} frames played, {audio.get('concealed', 0)} concealed"


def show(name: str, runs: list[dict], relayed: list[str]) -> None:
    for i, r in enumerate(runs):
        lat = r["latency_ms"]
        freezes = [length for _, length in r["freezes"]]
        spare = r["second_path"]
        print(
            f"{name} run {i + 1}: {r['frames_out']} frames out ({r['ended_by']}), latency p50 "
            f"{lat['p50']:.1f} p90 {lat['p90']:.1f} p99 {lat['p99']:.1f} max {lat['max']:.1f} ms, "
            f"freezes {len(freezes)} (longest {max(freezes, default=0)} frames), "
            f"receiver {r['receiver_fps']:.0f} fps; second path: {spare['late_frames']} late "
            f"frames, {spare['saved']} frames it brought {LATE_FRAME_MS}+ ms sooner, "
            f"{_kbps(r, 'spare'):.2f} kbit/s of copies (geometry {_kbps(r, 'geometry'):.2f}); "
            f"{_sound(r)}" + (f"; link {relayed[i]}" if relayed and relayed[i] else "")
        )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--lossy-only", action="store_true", help="the 5%% loss link alone")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if not args.lossy_only:
            show("loopback", [call(folder, args.frames, None) for _ in range(args.runs)], [])
        reason = unavailable()
        if reason is not None:
            print(f"namespaces: skipped ({reason})")
            return 0
        links = (
            [Netem(40, 10, 0.05)] if args.lossy_only else [Netem(40, 10, 0.0), Netem(40, 10, 0.05)]
        )
        for netem in links:
            runs, relayed = [], []
            for run in range(args.runs):
                with TwoHosts(netem, seed=run + 1) as hosts:
                    runs.append(call(folder, args.frames, hosts))
                relayed.append(hosts.relayed)
            print(f"namespaces, {hosts.how}:")
            show(f"  netem {netem}", runs, relayed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
