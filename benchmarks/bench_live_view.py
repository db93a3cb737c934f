"""The receiver's rendering rate while its live view is watched.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_live_view.py [--viewers 0,1,3]
       [--frames N] [--chromium]

The bundled clip's packets are made once (the sender is not timed). Then, for each number of
viewers, the receiver's work runs as fast as it can on one thread: decode + deform + render
each frame (receiver.decoder.FaceDecoder, as benchmarks/bench_call.py), every picture handed
to the live view's sink (receiver/live_view.py) with the figures so far, as the receive loop
does. Viewers are separate processes that read the MJPEG stream and decode every picture, and
fetch figures.json twice a second, as the page does (with --chromium: headless Chromium
pages, which also draw it). "no view" is the same loop without a live view.

Prints, per row: rendered frames per second (wall clock), per-frame time (wall clock, and the
loop thread's own CPU time), the receiver process's CPU time per frame over all its threads
(llvmpipe's, the JPEG encoder's, the server's), pictures JPEG-encoded per second, and the
pictures per second each viewer got. The machine's other load shows in the wall-clock
figures, not in the CPU times.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.protocol.packets import decode  # noqa: E402
from facewire.receiver.decoder import FaceDecoder  # noqa: E402
from facewire.receiver.live_view import LiveView  # noqa: E402
from facewire.receiver.session import ReceiverReport, RenderedFrame  # noqa: E402
from facewire.sender.capture import VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402

CTX = mp.get_context("spawn")


def make_packets() -> tuple[bytes, list[bytes]]:
    """The clip's snapshot and frame packets (b"" where nothing changed)."""
    with VideoSource(demo_clip_path()) as video:
        frames = list(video.frames())
        encoder = FaceEncoder(video.width, video.height, video.fps)
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    packets = []
    for frame in frames:
        sent = encoder.encode(frame)
        packets.append(b"" if sent is None else bytes(sent))
    return bytes(snapshot), packets


def viewer(url: str, stop: Any, results: Any) -> None:
    """A viewer process: reads the stream, decodes each picture, polls the figures."""
    pictures, polled, start = 0, time.monotonic(), time.monotonic()
    with urllib.request.urlopen(url + "stream.mjpg", timeout=30) as stream:
        stream.readline()  # the first boundary
        while not stop.is_set():
            length = 0
            while (line := stream.readline()) not in (b"\r\n", b""):
                if line.lower().startswith(b"content-length:"):
                    length = int(line.split(b":")[1])
            data = stream.read(length)
            stream.readline(), stream.readline()  # the CRLF and the next boundary
            cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            pictures += 1
            if time.monotonic() - polled > 0.5:
                with urllib.request.urlopen(url + "figures.json", timeout=30) as r:
                    json.load(r)
                polled = time.monotonic()
    results.put(pictures / (time.monotonic() - start))


@dataclass
class Row:
    label: str
    fps: float
    per_frame_ms: tuple[float, float]
    thread_ms: float  # the loop thread's CPU time per frame
    process_ms: float  # the whole receiver process's CPU time per frame
    encoded_fps: float
    viewer_fps: list[float]


def run(
    snapshot: bytes, packets: list[bytes], frames: int, viewers: int | None, chromium: bool
) -> Row:
    """``viewers`` None: no live view at all."""
    decoder = FaceDecoder(decode(snapshot))  # type: ignore[arg-type]
    view = LiveView("127.0.0.1", 0) if viewers is not None else None
    stop, results = CTX.Event(), CTX.Queue()
    clients: list[Any] = []
    profiles: list[str] = []
    report = ReceiverReport()
    try:
        if view is not None:
            first = decoder.reconstruct(decoder.decode(decode(packets[0])))  # type: ignore[arg-type]
            view(RenderedFrame(1, 0, first, 0, 0.0), report)
            for _ in range(viewers or 0):
                if chromium:
                    profiles.append(tempfile.mkdtemp(prefix="bench-chromium-"))
                    clients.append(_chromium(view.url, profiles[-1]))
                else:
                    clients.append(CTX.Process(target=viewer, args=(view.url, stop, results)))
                    clients[-1].start()
            deadline = time.monotonic() + 60
            while view.viewers < (viewers or 0):
                assert time.monotonic() < deadline, "the viewers did not connect"
                time.sleep(0.05)
            time.sleep(1.0)  # the viewers settle (Chromium starts its renderer)
        encoded_before = view.encoded if view else 0
        times = []
        shown = None
        cpu_before = os.times()
        thread_before = time.thread_time()
        start = time.perf_counter()
        for i in range(frames):
            t0 = time.perf_counter()
            data = packets[i % len(packets)]
            if data:
                shown = decoder.decode(decode(data))  # type: ignore[arg-type]
            assert shown is not None
            image = decoder.reconstruct(shown)
            if view is not None:
                report.frames_out += 1
                report.bytes_received = {"geometry": 60 * i, "snapshot": len(snapshot)}
                view(RenderedFrame(1, i, image, 0, 20.0), report)
            times.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - start
        thread_cpu = time.thread_time() - thread_before
        cpu_after = os.times()
        process_cpu = (cpu_after.user - cpu_before.user) + (cpu_after.system - cpu_before.system)
        encoded = (view.encoded - encoded_before) if view else 0
        stop.set()
        got = [results.get(timeout=30) for c in clients if not chromium]
    finally:
        stop.set()
        for c in clients:
            if chromium:
                c.terminate()
                c.wait(timeout=10)
            else:
                c.join(timeout=10)
        for profile in profiles:
            shutil.rmtree(profile, ignore_errors=True)
        if view is not None:
            view.close()
        decoder.close()
    ms = np.asarray(times) * 1000
    label = "no view" if viewers is None else f"{viewers} viewer(s)"
    if chromium and viewers:
        label += " (Chromium)"
    return Row(
        label,
        frames / elapsed,
        (float(np.median(ms)), float(np.percentile(ms, 90))),
        thread_cpu * 1000 / frames,
        process_cpu * 1000 / frames,
        encoded / elapsed,
        got,
    )


def _chromium(url: str, profile: str) -> subprocess.Popen[bytes]:
    path = shutil.which("chromium")
    if path is None:
        raise SystemExit("--chromium: no chromium (scripts/install-system-deps.sh --test)")
    return subprocess.Popen(
        [path, "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={profile}",
         "--window-size=1100,700", "--remote-debugging-port=0", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--viewers", default="0,1,3", help="numbers of viewers (default 0,1,3)")
    parser.add_argument("--frames", type=int, default=600, help="frames per row (default 600)")
    parser.add_argument("--chromium", action="store_true", help="viewers are Chromium pages")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    snapshot, packets = make_packets()
    print(
        f"bundled clip 640x480, {args.frames} frames per row, OpenCV threads {args.threads}, "
        f"{os.cpu_count()} cores"
    )
    print(
        f"{'':24} {'render fps':>10} {'ms/frame p50, p90':>18} {'loop CPU':>8} "
        f"{'process CPU':>11} {'JPEG/s':>7}  viewers got fps"
    )
    counts: list[int | None] = [None, *(int(n) for n in args.viewers.split(","))]
    for n in counts:
        row = run(snapshot, packets, args.frames, n, args.chromium)
        got = ", ".join(f"{v:.1f}" for v in row.viewer_fps) or "-"
        print(
            f"{row.label:24} {row.fps:10.1f} {row.per_frame_ms[0]:8.2f}, {row.per_frame_ms[1]:7.2f}"
            f" {row.thread_ms:6.2f} ms {row.process_ms:8.2f} ms {row.encoded_fps:7.1f}  {got}",
            flush=True,
        )


if __name__ == "__main__":
    main()
