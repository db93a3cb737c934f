"""How fast a real call recovers: loss, late joins, restarts, a lost peer.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_recovery.py [--runs N]

The same set-up as tests/test_recovery.py (whose helpers it uses): the bundled clip sent at
30 fps over CURVE on loopback, receivers in their own processes. Prints, over ``--runs`` runs:
- freezes under 10% random loss and under 1 s bursts of total loss: how long the picture stayed
  stale after a loss, in ms (frames x 33.3);
- a late joiner: seconds from asking for the snapshot to its first rendered frame;
- a sender killed and restarted on the same ports: seconds from the new sender binding its
  ports (its own start-up, about a second of loading models, is printed apart) until the
  receiver has rejoined its session and is ready, and from the rejoin to the first frame;
- a sender killed for good: seconds until the receiver declares the peer lost.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the call helpers

from call_helpers import (  # noqa: E402
    HOST,
    Keys,
    LossyLink,
    ReceiverProcess,
    SenderProcess,
    send,
    start_sender,
    wait_ready,
)

from facewire.protocol.transport import SenderEndpoint  # noqa: E402

FRAME_MS = 1000 / 30
BURSTS = [range(50, 80), range(150, 180)]  # frames lost: two seconds of total loss


def lossy(folder: Path, keys: Keys, drop, frames: int = 240) -> dict:
    encoder, snapshot, it = start_sender(frames)
    with SenderEndpoint(HOST, **keys.sender()) as endpoint:
        endpoint.set_snapshot(snapshot)
        receiver = ReceiverProcess(endpoint.ports, folder / "out.mp4", **keys.receiver())
        wait_ready(endpoint, receiver)
        send(endpoint, encoder, it, LossyLink(endpoint, drop))
        return receiver.report()


def late_join(folder: Path, keys: Keys) -> float:
    encoder, snapshot, it = start_sender(150)
    with SenderEndpoint(HOST, **keys.sender()) as endpoint:
        endpoint.set_snapshot(snapshot)
        first = ReceiverProcess(endpoint.ports, folder / "a.mp4", **keys.receiver())
        wait_ready(endpoint, first)
        late: list[ReceiverProcess] = []

        def join_at_40(seq: int) -> bool:
            if seq == 40 and not late:
                late.append(ReceiverProcess(endpoint.ports, folder / "b.mp4", **keys.receiver()))
            return False

        send(endpoint, encoder, it, LossyLink(endpoint, join_at_40))
        first.report()
        return late[0].report()["first_frame_s"][0]


def sender_restart(folder: Path, keys: Keys) -> tuple[float, float]:
    first = SenderProcess(keys, frames=300, announce=60)
    receiver = ReceiverProcess(
        first.ports, folder / "out.mp4", rejoin_timeout_s=5.0, **keys.receiver()
    )
    first.expect("sending")
    first.expect("frame")
    first.kill()
    killed = time.monotonic()
    second = SenderProcess(keys, frames=60, ports=first.ports)  # returns once bound
    bound = time.monotonic()
    second.expect("sending")  # the receiver has rejoined and is ready
    rejoined = time.monotonic()
    print(f"  new sender bound {bound - killed:.2f} s after the kill", flush=True)
    second.expect("ok")
    return rejoined - bound, receiver.report()["first_frame_s"][1]


def peer_lost(folder: Path, keys: Keys) -> float:
    sender = SenderProcess(keys, frames=300, announce=30)
    receiver = ReceiverProcess(sender.ports, folder / "out.mp4", **keys.receiver())
    sender.expect("sending")
    sender.expect("frame")
    sender.kill()
    killed = time.monotonic()
    report = receiver.report()
    assert report["ended_by"] == "peer lost", report["ended_by"]
    return time.monotonic() - killed


def _stats(name: str, values: list[float], unit: str) -> None:
    v = np.asarray(values)
    print(f"{name}: median {np.median(v):.2f} {unit}, max {v.max():.2f} {unit} (n={len(v)})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    found: dict[str, list[float]] = {k: [] for k in ("random", "burst", "late", "rejoin")}
    found |= {"first_after_rejoin": [], "lost": []}
    requests = []
    for run in range(args.runs):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            keys = Keys(folder)
            rng = random.Random(run)
            drops = {i for i in range(1, 240) if rng.random() < 0.1}
            report = lossy(folder, keys, drops.__contains__)
            found["random"] += [n * FRAME_MS for _, n in report["freezes"]]
            requests.append(report["keyframe_requests"])
            report = lossy(folder, keys, lambda s: any(s in b for b in BURSTS))
            # How long the picture stayed stale after each burst ended.
            for first, n in report["freezes"]:
                end = next((b.stop for b in BURSTS if first <= b.start < first + n), None)
                if end is not None:
                    found["burst"].append((first + n - end) * FRAME_MS)
            found["late"].append(late_join(folder, keys))
            rejoin, first_frame = sender_restart(folder, keys)
            found["rejoin"].append(rejoin)
            found["first_after_rejoin"].append(first_frame)
            found["lost"].append(peer_lost(folder, keys))
        print(f"run {run + 1} of {args.runs} done", flush=True)
    _stats("10% random loss, each freeze", found["random"], "ms")
    print(f"10% random loss, keyframe requests per 8 s call: {requests}")
    _stats("1 s bursts, stale after the burst ended", found["burst"], "ms")
    _stats("late join, snapshot request to first frame", found["late"], "s")
    _stats("sender restarted, new sender bound to receiver rejoined", found["rejoin"], "s")
    _stats("  then rejoin to first frame", found["first_after_rejoin"], "s")
    _stats("sender killed for good, kill to 'peer lost'", found["lost"], "s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
