"""Fuzz what a receiver does with packets: 100,000 random and mutated ones, then a live receiver.

Usage: python benchmarks/bench_fuzz.py [--count 100000] [--live 30000] [--seed 1]
       python benchmarks/bench_fuzz.py --case I [--seed S]   # replay one case, with traceback

Inputs are random bytes (one in ten) or a seed packet with one to four stacked mutations: bit
flips, bytes set to 00/7F/80/FF, random bytes inserted, spans deleted or repeated, truncation,
a splice of two seeds, and a boundary integer (0, 2^k - 1, 2^k, ...) written over 1, 2, 4 or
8 bytes in either byte order (any length, count or size field). Case i depends only on the
seed and i.

Decoder (``--count`` cases), seeds: the golden fixtures, tests/fixtures/packets/*.bin. Each
input goes where a receiver sends it:

- ``facewire.protocol.packets.decode``, whose documented error is PacketError; a packet it
  returns must come back from ``decode(bytes(p))`` equal;
- a KeyFrame or DeltaFrame to a ``facewire.protocol.channels.ChannelDecoder`` of the golden
  snapshot's channel table (a delta right after a keyframe whose counter precedes its own,
  so its chain is intact): PacketError or ChainBroken;
- a Snapshot's texture and background, and a RemPatch's image, to
  ``facewire.protocol.images.decode_image`` (ImageError); a Snapshot also makes a ChannelDecoder of
  its own channel table, which decodes the golden frames.

Live (``--live N`` cases), seeds: a real session (the snapshot and packets of the bundled
clip's first 60 frames, through the sender's FaceEncoder) and keyframes of it with one value
at a boundary (+-2^24, +-2^17, +-2^10). A thread plays the sender on raw loopback ZeroMQ
sockets: it publishes each case to a real ``facewire.protocol.transport.ReceiverEndpoint`` (plain),
then a marker heartbeat, and answers probes and snapshot requests; a decodable delta is
preceded by the session's keyframe with the counter before its own. The receiver side does
what ``facewire.receiver.session`` does: frame packets go through the receive loop's ``_decode`` to
the session's ``FaceDecoder``, every frame that decodes is rebuilt and rendered
(``FaceDecoder.reconstruct``), and RejoinNeeded is answered by ``fetch_snapshot``. Each case's
outcome: what ``recv`` returned and what became of it, or what the endpoint counted.

A crash is any exception other than the documented ones; a hang is a case that takes longer
than 1 s (one stuck for a minute dumps every stack and ends the run). Exit status 1 on any
crash or hang, if resident memory grows by more than 20 MB after the first tenth of the
cases, or if its peak rises more than 256 MB above the start.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import faulthandler
import logging
import os
import queue
import random
import sys
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from facewire.protocol.channels import ChainBroken, ChannelDecoder, ChannelEncoder, ChannelSpec  # noqa: E402
from facewire.protocol.images import ImageError, decode_image  # noqa: E402
from facewire.protocol.packets import (  # noqa: E402
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    Packet,
    PacketError,
    RemPatch,
    Snapshot,
    decode,
)

FIXTURES = ROOT / "tests" / "fixtures" / "packets"
HANG_S = 1.0
#: A case still running after this long is stuck for good: dump every stack and exit 1.
STUCK_S = 60.0
MAX_RSS_GROWTH_MB = 20.0
#: A peer's image may decode to 4096 x 4096 (48 MB) and its decoder's buffers; far more is a bomb.
MAX_PEAK_MB = 256.0
BOUNDARY = [0, 1, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 2**31 - 1, 2**31]
BOUNDARY += [2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1]

Seeds = list[tuple[str, bytes]]


# --- inputs --------------------------------------------------------------------------------------


def _mutate(rng: random.Random, data: bytearray, seeds: Seeds) -> str:
    """Apply one random mutation to ``data`` in place; returns its name."""
    n = len(data)
    i = rng.randrange(n) if n else 0
    what = rng.randrange(8)
    if what == 0 and n:
        data[i] ^= 1 << rng.randrange(8)
        return "flip"
    if what == 1 and n:
        data[i] = rng.choice((0x00, 0x7F, 0x80, 0xFF))
        return "set"
    if what == 2:
        data[i:i] = rng.randbytes(rng.choice((1, 2, 4, 16, 64)))
        return "insert"
    if what == 3:
        del data[i : i + rng.choice((1, 2, 4, 16))]
        return "delete"
    if what == 4:
        del data[i:]
        return "truncate"
    if what == 5:
        other = rng.choice(seeds)[1]
        data[i:] = other[rng.randrange(len(other) + 1) :]
        return "splice"
    if what == 6:
        span = data[i : i + rng.choice((1, 4, 16, 64))]
        data[i:i] = span * rng.choice((1, 2, 16))
        return "repeat"
    width = rng.choice((1, 2, 4, 8))
    value = rng.choice(BOUNDARY) % (1 << 8 * width)
    data[i : i + width] = value.to_bytes(width, rng.choice(("big", "little")))
    return f"int{width}"


def make_case(seed: int, i: int, seeds: Seeds) -> tuple[bytes, str]:
    """Input ``i`` of run ``seed`` and how it was made."""
    rng = random.Random(seed * 1_000_003 + i)
    if rng.random() < 0.1:
        noise = rng.randbytes(int(2 ** rng.uniform(0, 12)))
        if rng.random() < 0.5:  # a valid header byte, so that the body gets parsed
            noise = bytes([0x20 | rng.randrange(1, 10)]) + noise
        return noise, f"random {len(noise)} B"
    name, seed_bytes = rng.choice(seeds)
    data = bytearray(seed_bytes)
    steps = [_mutate(rng, data, seeds) for _ in range(rng.choice((0, 1, 1, 1, 2, 3, 4)))]
    return bytes(data), f"{name}: {'+'.join(steps) or 'as it is'}"


def load_fixtures(folder: Path) -> Seeds:
    seeds = [(p.stem, p.read_bytes()) for p in sorted(folder.glob("*.bin"))]
    if not seeds:
        raise SystemExit(f"no fixtures (*.bin) in {folder}")
    return seeds


# --- measuring -----------------------------------------------------------------------------------


def rss_mb() -> tuple[float, float]:
    """(resident, peak resident) memory of this process, MB (VmRSS, VmHWM)."""
    fields = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            fields[line[:5]] = int(line.split()[1]) / 1024
    return fields["VmRSS"], fields["VmHWM"]


@dataclass
class Tally:
    """What happened to the cases of one stage."""

    cases: int = 0
    crash_count: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    crashes: dict[str, list[str]] = field(default_factory=dict)  # signature -> examples
    hangs: list[str] = field(default_factory=list)
    slowest: tuple[float, str] = (0.0, "")
    busy_s: float = 0.0
    rss: list[tuple[int, tuple[float, float]]] = field(default_factory=list)

    def crash(self, exc: BaseException, case: str, data: bytes) -> None:
        self.crash_count += 1
        tb = traceback.extract_tb(exc.__traceback__)
        own = [f for f in tb if "bench_fuzz" not in f.filename] or tb
        at = f" at {Path(own[-1].filename).name}:{own[-1].lineno}" if own else ""
        examples = self.crashes.setdefault(f"{type(exc).__name__}{at}", [])
        if len(examples) < 3:
            hexed = data[:40].hex() + ("..." if len(data) > 40 else "")
            lines = [f"{case}, {len(data)} B {hexed}", f"  {type(exc).__name__}: {exc}"[:300]]
            lines += [f"    {Path(f.filename).name}:{f.lineno} {f.line}" for f in own[-4:]]
            examples.append("\n    ".join(lines))

    def timed(self, seconds: float, case: str) -> None:
        self.busy_s += seconds
        if seconds > self.slowest[0]:
            self.slowest = (seconds, case)
        if seconds > HANG_S:
            self.hangs.append(f"{seconds:.2f} s: {case}")

    def report(self, name: str, wall_s: float) -> bool:
        """Print the figures; True if the stage failed."""
        growth = self.rss[-1][1][0] - self.rss[1][1][0]
        peak = self.rss[-1][1][1] - self.rss[0][1][0]
        print(f"\n== {name}: {self.cases} cases in {wall_s:.1f} s")
        for outcome, n in sorted(self.outcomes.items()):
            print(f"  {n:7d}  {outcome}")
        print(f"crashes          {self.crash_count} ({len(self.crashes)} kinds, examples below)")
        print(f"hangs (> {HANG_S:g} s)   {len(self.hangs)}")
        print(f"slowest case     {self.slowest[0] * 1000:.1f} ms ({self.slowest[1]})")
        print(
            f"throughput       {self.cases / wall_s:.0f} cases/s "
            f"(mean {self.busy_s / max(self.cases, 1) * 1e6:.0f} us per case, timed)"
        )
        samples = ", ".join(f"{k}: {mb:.1f}" for k, (mb, _) in self.rss)
        print(f"VmRSS MB by case {samples}")
        print(f"RSS growth after the first tenth: {growth:+.1f} MB")
        print(f"peak RSS (VmHWM) above the start: {peak:+.1f} MB")
        for signature, examples in self.crashes.items():
            print(f"CRASH {signature}")
            for example in examples:
                print(f"  {example}")
        for hang in self.hangs[:10]:
            print(f"HANG {hang}")
        return bool(
            self.crash_count or self.hangs or growth > MAX_RSS_GROWTH_MB or peak > MAX_PEAK_MB
        )


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[TextIO]:
    """Send file descriptor 2 to /dev/null (libpng and libjpeg print a line for every damaged
    image); yields the real stderr, where a fatal signal still dumps every stack."""
    sys.stderr.flush()
    real = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    report_to = os.fdopen(os.dup(real), "w")
    faulthandler.enable(report_to)
    try:
        yield report_to
    finally:
        faulthandler.cancel_dump_traceback_later()
        faulthandler.disable()
        os.dup2(real, 2)
        for fd in (real, devnull):
            os.close(fd)
        report_to.close()


def run(tally: Tally, count: int, one: Callable[[int], None]) -> float:
    """Call ``one(k)`` for k in 0..count-1, sampling RSS; returns the wall time."""
    marks = {0, max(1, count // 10)} | {count * j // 10 for j in range(2, 10)}
    with native_stderr_silenced() as report_to:
        start = armed = time.perf_counter()
        for k in range(count):
            if k in marks:
                tally.rss.append((k, rss_mb()))
            if k == 0 or time.perf_counter() - armed > 1.0:  # re-arming costs 50 us
                faulthandler.dump_traceback_later(STUCK_S, exit=True, file=report_to)
                armed = time.perf_counter()
            one(k)
            tally.cases += 1
        wall = time.perf_counter() - start
    tally.rss.append((count, rss_mb()))
    return wall


# --- decoder stage -------------------------------------------------------------------------------


def channel_decoder(snapshot: Snapshot) -> ChannelDecoder:
    """The channel decoder a receiver builds from a snapshot (as receiver.decoder does)."""
    return ChannelDecoder([ChannelSpec(*c) for c in snapshot.channels], round(1e6 / snapshot.fps))


def decode_chain(channels: ChannelDecoder, key: KeyFrame, packet: KeyFrame | DeltaFrame) -> None:
    """Decode ``packet``; a delta right after ``key`` stamped with the counter before its own."""
    if isinstance(packet, DeltaFrame):
        channels.decode(dataclasses.replace(key, counter=(packet.counter - 1) % 256))
    channels.decode(packet)


def image(blob: bytes, what: str) -> str:
    """Decode an image a packet carries; how it went."""
    if not blob:
        return f"{what} empty"
    try:
        decode_image(blob, what)
    except ImageError:
        return f"{what} ImageError"
    return f"{what} decoded"


class Receiver:
    """What a receiver does with received bytes, without the sockets (the decoder stage)."""

    def __init__(self, fixtures: Seeds) -> None:
        blobs = dict(fixtures)
        snapshot, key, delta = (decode(blobs[k]) for k in ("snapshot", "key_frame", "delta_frame"))
        assert isinstance(snapshot, Snapshot) and isinstance(key, KeyFrame)
        assert isinstance(delta, DeltaFrame)
        self.key, self.delta = key, delta
        self.channels = channel_decoder(snapshot)
        self.snapshot(snapshot)  # imports OpenCV: not the first case's time

    def take(self, data: bytes) -> str:
        """The outcome of one input; anything but the documented errors propagates."""
        try:
            packet = decode(data)
        except PacketError:
            return "PacketError from decode"
        again = decode(bytes(packet))
        if again != packet:
            raise AssertionError(f"decode(bytes(p)) != p for {packet!r}")
        kind = type(packet).__name__
        try:
            if isinstance(packet, (KeyFrame, DeltaFrame)):
                decode_chain(self.channels, self.key, packet)
            elif isinstance(packet, Snapshot):
                return self.snapshot(packet)
            elif isinstance(packet, RemPatch):
                return f"RemPatch, {image(packet.data, 'image')}"
        except (PacketError, ChainBroken) as exc:
            return f"{kind}, {type(exc).__name__} from the channel decoder"
        return f"{kind}, accepted"

    def snapshot(self, snapshot: Snapshot) -> str:
        images = [image(snapshot.texture, "texture"), image(snapshot.background, "background")]
        channels = channel_decoder(snapshot)
        frames = "frames decoded"
        for packet in (self.key, self.delta):
            try:
                decode_chain(channels, self.key, packet)
            except (PacketError, ChainBroken) as exc:
                frames = f"frames: {type(exc).__name__}"
        return f"Snapshot, {', '.join(images)}, {frames}"


def run_decoder(count: int, seed: int, fixtures: Seeds) -> bool:
    receiver = Receiver(fixtures)
    tally = Tally()

    def one(i: int) -> None:
        data, how = make_case(seed, i, fixtures)
        start = time.perf_counter()
        try:
            tally.outcomes[receiver.take(data)] += 1
        except Exception as exc:  # noqa: BLE001 - any other exception is what we look for
            tally.outcomes["CRASH"] += 1
            tally.crash(exc, f"case {i} ({how})", data)
        tally.timed(time.perf_counter() - start, f"case {i} ({how})")

    wall = run(tally, count, one)
    return tally.report("decoder: packets.decode, channel and image decoders", wall)


def replay(case: int, seed: int, fixtures: Seeds) -> int:
    data, how = make_case(seed, case, fixtures)
    print(f"case {case} ({how}), {len(data)} bytes:\n{data.hex()}")
    start = time.perf_counter()
    try:
        print(Receiver(fixtures).take(data))
    except Exception:  # noqa: BLE001
        traceback.print_exc()
        return 1
    finally:
        print(f"{(time.perf_counter() - start) * 1000:.2f} ms")
    return 0


# --- live stage ----------------------------------------------------------------------------------


def real_session(frames: int) -> tuple[Snapshot, list[Packet]]:
    """The snapshot and the packets of the bundled clip's first ``frames`` frames."""
    from facewire.protocol.packets import Bye
    from facewire.sender.capture import VideoSource, demo_clip_path
    from facewire.sender.encoder import FaceEncoder

    snapshot = None
    packets: list[Packet] = []
    with VideoSource(demo_clip_path()) as source:
        encoder = FaceEncoder(source.width, source.height, source.fps, session_id=7)
        for frame in source.frames(frames):
            if snapshot is None:
                snapshot = encoder.start(frame)
            elif (packet := encoder.encode(frame)) is not None:
                packets.append(packet)
    assert snapshot is not None, "no face in the bundled clip"
    packets += [Heartbeat(snapshot.session_id, 10, 123_456), Bye(frames)]
    return snapshot, packets


def boundary_frames(snapshot: Snapshot) -> list[KeyFrame]:
    """Keyframes of ``snapshot``'s session with one value at a boundary (+-2^k up to the
    largest the format allows): what a bit flip inside a range-coded body rarely makes."""
    specs = [ChannelSpec(*c) for c in snapshot.channels]
    reference = dict(zip([s.name for s in specs], snapshot.reference, strict=True))
    frames = []
    for spec in specs:
        for value in (2**24, -(2**24), 2**17, -(2**17), 2**10, -(2**10)):
            values = {name: np.array(r, np.int64) for name, r in reference.items()}
            values[spec.name][spec.size // 2] = value
            encoder = ChannelEncoder(specs, 33_333, snapshot.session_id, keyframe_interval=60)
            packet, _ = encoder.encode(snapshot.seq + 1, 0, values)
            assert isinstance(packet, KeyFrame)
            frames.append(packet)
    return frames


class FakeSender(threading.Thread):
    """Raw PUB and ROUTER sockets (plain) that publish whatever bytes they are given.

    Each case is followed by a marker heartbeat; a decodable delta is preceded by the
    session's keyframe with the counter before its own, so that its chain is intact. Probes
    and snapshot requests are answered at once, and the last marker is repeated after them
    (a rejoin empties the receiver's queue).
    """

    def __init__(self, snapshot: Snapshot, key: KeyFrame) -> None:
        import zmq

        super().__init__(daemon=True)
        self.context = zmq.Context()
        self.pub, self.router = self.context.socket(zmq.PUB), self.context.socket(zmq.ROUTER)
        for sock in (self.pub, self.router):
            sock.setsockopt(zmq.LINGER, 0)
        self.ports = (
            self.pub.bind_to_random_port("tcp://127.0.0.1"),
            self.router.bind_to_random_port("tcp://127.0.0.1"),
        )
        self.snapshot, self.key, self.session = bytes(snapshot), key, snapshot.session_id
        self.cases: queue.Queue[bytes | None] = queue.Queue()
        self.sent = 0

    def is_chain_start(self, packet: KeyFrame) -> bool:
        """Is ``packet`` the keyframe this sender puts before a delta?"""
        return dataclasses.replace(packet, counter=self.key.counter) == self.key

    def marker(self, case: int) -> Heartbeat:
        """The heartbeat after case number ``case`` (from 1; 0 before the first): a time no
        sender would send."""
        return Heartbeat(self.session, 0, -1 - case)

    def answer(self) -> None:
        """Answer probes and snapshot requests, each with the last marker again."""
        while self.router.poll(0):
            identity, *frames = self.router.recv_multipart()
            if frames and frames[-1][:1] == b"\x28":  # SnapshotRequest
                self.router.send_multipart([identity, self.snapshot])
            self.pub.send(bytes(self.marker(self.sent)))

    def is_marker(self, packet: Packet) -> bool:
        return isinstance(packet, Heartbeat) and packet.seq == 0 and packet.sent_us < 0

    def run(self) -> None:
        while True:
            try:
                data = self.cases.get(timeout=0.002)
            except queue.Empty:
                self.answer()
                continue
            if data is None:
                break
            try:
                packet: Packet | None = decode(data)
            except PacketError:
                packet = None
            if isinstance(packet, DeltaFrame):
                counter = (packet.counter - 1) % 256
                self.pub.send(bytes(dataclasses.replace(self.key, counter=counter)))
            self.pub.send(data)
            self.sent += 1
            self.pub.send(bytes(self.marker(self.sent)))
            self.answer()
        self.pub.close()
        self.router.close()
        self.context.term()


def run_live(count: int, seed: int) -> bool:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from facewire.protocol.transport import ReceiverEndpoint, RejoinNeeded
    from facewire.receiver.decoder import FaceDecoder
    from facewire.receiver.session import ReceiverReport, _decode

    t0 = time.perf_counter()
    snapshot, packets = real_session(60)
    seeds = [("snapshot", bytes(snapshot))]
    seeds += [(f"{type(p).__name__}{i}", bytes(p)) for i, p in enumerate(packets)]
    seeds += [(f"boundary{i}", bytes(p)) for i, p in enumerate(boundary_frames(snapshot))]
    key = next(p for p in packets if isinstance(p, KeyFrame))
    sender = FakeSender(snapshot, key)
    sender.start()
    endpoint = ReceiverEndpoint("127.0.0.1", *sender.ports, plain=True)
    endpoint.fetch_snapshot(timeout_ms=10_000)
    decoder = FaceDecoder(snapshot)
    report = ReceiverReport()
    print(
        f"\nlive: {len(seeds)} seeds: the snapshot and {len(packets)} packets of a session of the "
        f"bundled clip ({snapshot.width}x{snapshot.height}) and keyframes with boundary values; "
        f"receiver ready in {time.perf_counter() - t0:.1f} s"
    )
    tally = Tally()
    offset = 10_000_000  # other cases than the decoder stage's

    def take(packet: Packet) -> str:
        """What the receive loop does with a packet from ``recv``; its outcome."""
        kind = type(packet).__name__
        if not isinstance(packet, (KeyFrame, DeltaFrame)):
            return f"{kind} from recv"
        values = _decode(decoder, packet, report)
        if values is None:
            return f"{kind} from recv, refused by the FaceDecoder"
        if isinstance(packet, KeyFrame) and sender.is_chain_start(packet):
            return ""
        decoder.reconstruct(values)
        return f"{kind} from recv, rendered"

    def one(k: int) -> None:
        i = offset + k
        data, how = make_case(seed, i, seeds)
        case = f"case {i} ({how})"
        before = endpoint.stats.malformed, endpoint.stats.dropped_old
        outcomes: list[str] = []
        sender.cases.put(data)
        deadline = time.perf_counter() + 10.0
        while time.perf_counter() < deadline:
            start = time.perf_counter()
            try:
                packet = endpoint.recv(timeout_ms=100)
            except RejoinNeeded:
                outcomes.append("RejoinNeeded, joined again")
                endpoint.fetch_snapshot(timeout_ms=5000)
                continue
            if packet is None:
                continue
            if sender.is_marker(packet):
                if packet == sender.marker(k + 1):
                    break
                continue
            try:
                outcomes.append(take(packet))
            except Exception as exc:  # noqa: BLE001 - any other exception is what we look for
                outcomes.append("CRASH")
                tally.crash(exc, case, data)
            tally.timed(time.perf_counter() - start, case)
        else:
            tally.hangs.append(f"no marker within 10 s after {case}")
        if endpoint.stats.malformed > before[0]:
            outcomes.append("dropped by the endpoint as malformed")
        if endpoint.stats.dropped_old > before[1]:
            outcomes.append("dropped by the endpoint as older than the snapshot")
        tally.outcomes[" + ".join(o for o in outcomes if o) or "nothing came out"] += 1

    wall = run(tally, count, one)
    sender.cases.put(None)
    sender.join()
    decoder.close()
    endpoint.close()
    return tally.report("live: ReceiverEndpoint, the receive loop's _decode, FaceDecoder", wall)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=100_000, help="decoder cases")
    parser.add_argument("--live", type=int, default=0, help="live receiver cases (default 0)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--case", type=int, help="replay this decoder case and exit")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    fixtures = load_fixtures(FIXTURES)
    if args.case is not None:
        return replay(args.case, args.seed, fixtures)
    print(f"seeds: {', '.join(f'{n} ({len(b)} B)' for n, b in fixtures)}")
    failed = run_decoder(args.count, args.seed, fixtures)
    if args.live:
        failed = run_live(args.live, args.seed) or failed
    print("\nFAILED" if failed else "\nOK: no crash, no hang, memory flat")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
