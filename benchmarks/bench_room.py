"""A room on this machine: S participants sending clips, W only receiving (decoding, not
drawing), all through one relay (nats-server) on loopback.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_room.py [--senders 8] [--watchers 8]
       [--frames 300] [--clips DIR] [--live]

By default each clip is encoded once, up front, by the real encoder, and each sender replays
it (benchmarks/room_replay.py): the same bundles, sealed at publish time, paced at the clip's
frame rate, its keyframes restamped, while it decodes everyone else as ``facewire room``
does; the watchers are ``facewire room --receive-only``. The relay and the receivers are
measured, not S face encoders sharing the machine's cores. ``--live``: each sender is a
whole ``facewire room`` (camera-less, encoding its clip as it goes).

Prints, per participant, its downlink on the NATS connection (kbit/s over the clip's length,
the sum over the peers it received: sealed bundles and NATS's MSG lines, not TCP/IP; with
--live over each peer's span), the latency in ms from capture to its message's arrival at
the participant's link (the bundling and the relay) and to decoded (p50 of its peers' p50s,
worst p99), a replaying sender's CPU seconds from the clip's start; then a face's messages,
and the relay's CPU (seconds and share of one core while the clips play) and its largest
resident memory.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from room_replay import record, replay  # noqa: E402

from facewire.protocol.sframe import RoomKey  # noqa: E402
from facewire.relay import Relay, RelayConfig, free_port  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def _relay_usage(pid: int) -> tuple[float, int]:
    """(CPU seconds, resident bytes) of process ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / TICK  # utime, stime
    rss = int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    return cpu, rss


def _p50_p99(peers: Any, what: str) -> str:
    """The median of the peers' p50s of ``what`` and the worst p99, as two columns."""
    p50 = [p[what]["p50"] for p in peers if p.get(what)]
    p99 = [p[what]["p99"] for p in peers if p.get(what)]
    return (f"{statistics.median(p50) if p50 else float('nan'):>11.0f}  "
            f"{max(p99) if p99 else float('nan'):>5.0f}")  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--senders", type=int, default=8)
    p.add_argument("--watchers", type=int, default=8)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--clips", metavar="DIR", help="176x144 clips (*.mp4, *.avi); default: "
                   "the bundled clip scaled to 176x144")  # fmt: skip
    p.add_argument("--live", action="store_true", help="each sender encodes as it goes")
    p.add_argument("--replay-as", nargs=6, metavar="ARG", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.replay_as:  # one sender's process (see room_replay.replay)
        server, key_file, name, recording, expect, work_dir = args.replay_as
        work = Path(work_dir)
        replay(server, Path(key_file), name, Path(recording), expect.split(","),
               work / "go", work / f"{name}.json")  # fmt: skip
        return 0
    clips = sorted(Path(args.clips).glob("*_qcif.*")) if args.clips else []
    work = Path(tempfile.mkdtemp(prefix="bench-room-"))
    key = work / "bench.room"
    RoomKey.generate("bench").write(key)
    env = dict(os.environ, PYOPENGL_PLATFORM="egl")
    recordings: list[Path] = []
    ready = 0
    fps = 30.0
    if not args.live:
        for i, clip in enumerate(clips or [None]):
            recordings.append(work / f"clip{i}.pickle")
            fps = record(clip, (176, 144), args.frames, recordings[-1])["fps"]
    with Relay(RelayConfig(port=free_port())) as relay:
        assert relay.process is not None
        url = relay.config.client_url()
        base = [sys.executable, "-m", "facewire", "room", "--room", "bench", "--key", str(key),
                "--server", url, "--no-sound"]  # fmt: skip
        people = []
        names = [f"w{i}" for i in range(args.watchers)] + [f"s{i}" for i in range(args.senders)]
        for name in names[: args.watchers]:
            cmd = [*base, "--name", name, "--receive-only", "--stats", str(work / f"{name}.json")]
            people.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL))
        for i, name in enumerate(names[args.watchers :]):
            if args.live:
                source = (
                    ["--input", str(clips[i % len(clips)])] if clips else ["--max-size", "176x144"]
                )
                cmd = [*base, "--name", name, *source, "--frames", str(args.frames),
                       "--stats", str(work / f"{name}.json")]  # fmt: skip
            else:
                others = ",".join(n for n in names if n != name)
                cmd = [sys.executable, __file__, "--replay-as", url, str(key), name,
                       str(recordings[i % len(recordings)]), others, str(work)]  # fmt: skip
            people.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL))
        if not args.live:  # every sender has been asked for a keyframe by everyone: go
            deadline = time.monotonic() + 120
            senders = names[args.watchers :]
            while time.monotonic() < deadline:
                if all((work / f"{n}.ready").exists() for n in senders):
                    break
                time.sleep(0.5)
            ready = sum((work / f"{n}.ready").exists() for n in senders)
            (work / "go").write_text(f"{time.monotonic() + 1.0:.6f}")
            time.sleep(1.0)
        start_cpu, _ = _relay_usage(relay.process.pid)
        started = time.monotonic()
        most_rss = 0
        while any(person.poll() is None for person in people):
            most_rss = max(most_rss, _relay_usage(relay.process.pid)[1])
            time.sleep(0.5)
        elapsed = time.monotonic() - started
        cpu = _relay_usage(relay.process.pid)[0] - start_cpu
    clip_s = args.frames / fps
    mode = "live encoders" if args.live else f"replayed, {ready}/{args.senders} senders ready"
    print(f"room: {args.senders} sending, {args.watchers} receiving only, {args.frames} frames "
          f"each, {len(clips) or 1} clip(s), {mode}; {elapsed:.1f} s")  # fmt: skip
    print("who   peers  frames  kbit/s  arrived p50    p99  decoded p50    p99  CPU s")
    messages = sealed = faces = late = 0
    for person in sorted(work.glob("*.json")):
        stats = json.loads(person.read_text())
        peers = stats["peers"].values()
        if args.live:
            down = sum(p["kbps"]["nats"] for p in peers)
        else:
            down = sum(p["bytes"]["nats"] for p in peers) * 8 / clip_s / 1000
        messages += sum(p["messages"] for p in peers)
        sealed += sum(p["bytes"]["sealed"] for p in peers)
        faces += len(peers)
        late += stats.get("late_keyframe_requests", 0)
        cpu_s = stats.get("cpu_s", "")
        print(f"{stats['name']:<4}  {len(peers):>5}  {sum(p['frames'] for p in peers):>6}  "
              f"{down:>6.1f}  {_p50_p99(peers, 'arrival_ms')}  {_p50_p99(peers, 'latency_ms')}"
              f"  {cpu_s:>5}".rstrip())  # fmt: skip
    print(
        f"a face: {messages / max(1, faces) / clip_s:.1f} messages/s, "
        f"{sealed / max(1, messages):.0f} bytes sealed each (NATS's MSG line not counted); "
        f"{late} keyframe requests left unanswered"
    )
    print(f"relay: {cpu:.2f} CPU s over {elapsed:.1f} s ({100 * cpu / elapsed:.1f}% of a core), "
          f"largest RSS {most_rss / 2**20:.1f} MiB")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
