"""``facewire demo``: a loopback call on a video file, recorded and measured.

The sender runs in this process; the receiver runs in a child process (its own OpenGL
context) and talks to it over real ZeroMQ sockets on 127.0.0.1.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import logging
import multiprocessing as mp
import queue
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.call import MAX_SIZE, sound_as_asked
from facewire.protocol.clock import now_us
from facewire.protocol.constants import CHANNELS
from facewire.protocol.keys import write_keypair
from facewire.protocol.transport import SenderEndpoint
from facewire.receiver.recorder import Mp4Recorder, at_input_size
from facewire.sender.audio import with_sound
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder
from facewire.sender.lift import MarkerFaceTracker
from facewire.sender.rate_cap import GEOMETRY_KBPS
from facewire.sender.session import (
    capped_size,
    run_sender,
    scaled,
    start_session,
    wait_until_ready,
)
from facewire.sender.snapshot_draft import draft, sharper
from facewire.sheet import write_contact_sheet

logger = logging.getLogger(__name__)

HOST = "127.0.0.1"
JOIN_TIMEOUT_S = 60.0
RECEIVER_TIMEOUT_S = 120.0


def _receiver_main(
    ports: tuple[int, int], output: str, verbosity: int, results: Any, keys: dict[str, Any]
) -> None:
    """Child process: join the call, record, send the report back."""
    logging.basicConfig(level=verbosity, format="%(asctime)s receiver %(name)s: %(message)s")
    try:
        from facewire.receiver.session import run_receiver

        # Frame i of the recording rebuilds input frame i, from the first: where the file's
        # first face comes late, the first picture stands for the frames before it.
        report = run_receiver(
            HOST, ports[0], ports[1], output, join_timeout_s=JOIN_TIMEOUT_S, record_from=0, **keys
        )
        results.put(("ok", report.as_dict()))
    except Exception as exc:  # reported as one line by the parent
        logging.getLogger(__name__).debug("receiver failed", exc_info=True)
        results.put(("error", f"receiver: {exc}"))


def _wait_for_join(endpoint: SenderEndpoint, proc: Any, results: Any) -> None:
    """Until the receiver has the snapshot and says it is ready to render."""
    if wait_until_ready(endpoint, JOIN_TIMEOUT_S, proc.is_alive):
        return
    try:
        status, detail = results.get(timeout=1.0)
    except queue.Empty:
        status, detail = "error", f"the receiver did not join within {JOIN_TIMEOUT_S:g} s"
    raise RuntimeError(detail if status == "error" else "the receiver ended before the call began")


def run_demo(args: argparse.Namespace) -> int:
    # A number names a camera; anything else is a file.
    source: str | Path = args.input if args.input else demo_clip_path()
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    video = VideoSource(source, realtime=not args.fast, keep_late=args.every_frame)
    with video, tempfile.TemporaryDirectory() as tmp:
        # A camera cannot be read twice: keep what was sent for the side-by-side video.
        keep = video.is_camera and (args.compare or args.sheet)
        sent = Path(tmp) / "input.mp4" if keep else None
        stats = _call(video, args, sent, Path(tmp))
        reference = sent or Path(source)
        if args.compare:
            _write_compare(reference, Path(args.output), Path(args.compare), stats["frames_out"])
        if args.sheet:
            write_contact_sheet(reference, Path(args.output), Path(args.sheet), stats["frames_out"])
    stats["input"] = video.name
    _print_summary(stats, args)
    if args.stats:
        Path(args.stats).write_text(json.dumps(stats, indent=2) + "\n")
    return 0


def _call(
    video: VideoSource, args: argparse.Namespace, sent: Path | None, tmp: Path
) -> dict[str, Any]:
    markers = getattr(args, "tracker", "landmarks") == "markers"
    tracker = MarkerFaceTracker() if markers else None
    # Scaled as `facewire send` scales it: the call runs at the size a receiver is sent.
    size = capped_size(video.width, video.height, *getattr(args, "max_size", MAX_SIZE))
    encoder = FaceEncoder(
        *size,
        video.fps,
        tracker=tracker,
        geometry_kbps=getattr(args, "geometry_kbps", GEOMETRY_KBPS) or None,
    )
    frames = scaled(video.frames(limit=args.frames), size)
    # The frames before the face are not sent (but the last FACE_SEARCH_KEEP): the snapshot
    # holds from frame 0, so the recording shows the first picture for them.
    snapshot, buffered = start_session(encoder, frames, video.fps, video.name, seq=0)

    ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited sockets or GL state
    results = ctx.Queue()
    verbosity = logging.getLogger().getEffectiveLevel()
    # The loopback call is encrypted too: a keypair for each end, made for this call only.
    sender_public, sender_secret = write_keypair(tmp, "sender")
    receiver_public, receiver_secret = write_keypair(tmp, "receiver")
    receiver_keys = {"secret_key_file": str(receiver_secret), "server_key_file": str(sender_public)}
    with SenderEndpoint(
        HOST,
        secret_key_file=sender_secret,
        allowed_keys=[receiver_public],
        max_bps=None if args.max_kbps is None else args.max_kbps * 1000,
        fps=video.fps,
        udp=not args.tcp_only,
    ) as endpoint:
        endpoint.set_snapshot(snapshot, draft(snapshot), sharper(snapshot))
        proc = ctx.Process(
            target=_receiver_main,
            args=(endpoint.ports, str(args.output), verbosity, results, receiver_keys),
        )
        proc.start()
        try:
            _wait_for_join(endpoint, proc, results)
            # Frames read before the call began count as captured now; pacing restarts.
            video.resync(buffered[-1].index + 1)
            buffered = [dataclasses.replace(f, capture_us=now_us()) for f in buffered]
            keep = Mp4Recorder(sent, *size, video.fps) if sent else None  # as sent
            sound = sound_as_asked(
                args,
                video.name if not video.is_camera else 0,
                video.is_camera,
                video.realtime,
                endpoint.publish,
                print,
                endpoint.max_bps,
            )
            sent_frames = with_sound(itertools.chain(buffered, frames), sound, video.fps)
            sender = run_sender(
                endpoint, encoder, _kept(sent_frames, keep), read_to=lambda: video.read_to
            )
            if keep is not None:
                keep.close()
            status, report = results.get(timeout=RECEIVER_TIMEOUT_S)
        except queue.Empty:
            raise RuntimeError("the receiver did not finish in time") from None
        finally:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.terminate()
        if status == "error":
            raise RuntimeError(report)
        traffic = {
            ch: endpoint.bytes_sent.get(ch, 0) + endpoint.bytes_received.get(ch, 0)
            for ch in CHANNELS
        }
        # Message sizes, for the wire overhead (facewire.wire): sender -> receiver and back.
        messages = {
            "to_receiver": _by_size(endpoint.sizes_sent),
            "to_sender": _by_size(endpoint.sizes_received),
        }
    duration = (sender.frames_in + video.dropped) / video.fps  # the input's span
    kbps = {ch: traffic[ch] * 8 / duration / 1000 for ch in CHANNELS}
    kbps["total"] = sum(kbps.values())
    return {
        "frames_in": sender.frames_in,
        "frames_dropped": video.dropped,
        "frames_out": report["frames_out"],
        "frames_held": report["frames_held"],
        "frames_untracked": encoder.frames_untracked,
        "frames_over_rate": 0 if encoder.rate_cap is None else encoder.rate_cap.held,
        "quantiser_clipped": encoder.values_clipped,
        # New scenes: the sender's cuts, other faces and better views of the face (its
        # sessions after the first), and seconds from the capture of each one's first
        # frame to its first picture on the receiver's screen (one host: one clock).
        "scenes": sender.scenes,
        "scene_frames": sender.scene_frames,
        "scene_first_s": [
            (shown - captured) / 1e6
            for captured, shown in zip(
                sender.scene_capture_us, report.get("scene_shown_us", []), strict=False
            )
        ],
        "width": size[0],  # the call's, after --max-size
        "height": size[1],
        "fps": video.fps,
        "duration_s": duration,
        "sender_fps": sender.fps,
        "receiver_fps": report["receiver_fps"],
        "latency_ms": report["latency_ms"],
        "kbps": kbps,
        # The face's edge corrections and the body's motion ride in the geometry's packets,
        # each on a budget of its own.
        "edge_kbps": encoder.edge_bytes * 8 / duration / 1000,
        "body_kbps": encoder.body_bytes * 8 / duration / 1000,
        # What the model misses, sent as it is: a part of `rem` (models/refresh.py).
        "refresh_kbps": 0.0
        if encoder.refresh is None
        else encoder.refresh.bytes * 8 / duration / 1000,
        "bytes": traffic,
        "messages": messages,
        "encrypted": True,
        "malformed": report["malformed"],
        "ended_by": report["ended_by"],
        "audio": report.get("audio", {}),
        "rem": _rem_stats(encoder, report),
        "fit_residual": encoder.residual.summary(),
        "output": str(args.output),
    }


def _rem_stats(encoder: FaceEncoder, report: dict[str, Any]) -> dict[str, Any]:
    """REM patches: the sender's counts (images, references, repeats, bytes per region) and
    the receiver's (received, applied per region, dropped per reason)."""
    sent = encoder.rem.counts.as_dict() if encoder.rem is not None else {"patches": 0}
    return {"patches": sent["patches"], "sender": sent, "receiver": report.get("rem", {})}


def _by_size(sizes: Mapping[str, Counter[int]]) -> dict[str, list[list[int]]]:
    """{channel: [[bytes, messages], ...]} in increasing size."""
    return {ch: [[size, n] for size, n in sorted(c.items())] for ch, c in sizes.items()}


def _kept(frames: Iterable[CapturedFrame], keep: Mp4Recorder | None) -> Iterator[CapturedFrame]:
    """``frames``, each also written to ``keep`` (a camera's frames cannot be read twice)."""
    for frame in frames:
        yield frame
        if keep is not None:
            keep.write(frame.image)


def _write_compare(source: Path, output: Path, compare: Path, count: int) -> None:
    """Input (left) and reconstruction (right), frame by frame."""
    inp, out = cv2.VideoCapture(str(source)), cv2.VideoCapture(str(output))
    fps = inp.get(cv2.CAP_PROP_FPS) or 30.0
    writer: Mp4Recorder | None = None
    try:
        for _ in range(count):
            ok_a, a = inp.read()
            ok_b, b = out.read()
            if not (ok_a and ok_b):
                break
            pair = np.hstack([a, at_input_size(b, a.shape)])
            for text, x in (("input", 8), ("facewire", a.shape[1] + 8)):
                cv2.putText(pair, text, (x, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
            if writer is None:
                writer = Mp4Recorder(compare, pair.shape[1], pair.shape[0], fps)
            writer.write(pair)
    finally:
        inp.release()
        out.release()
        if writer is not None:
            writer.close()


def _print_summary(stats: dict[str, Any], args: argparse.Namespace) -> None:
    k = stats["kbps"]
    lat = stats["latency_ms"]
    print(
        f"call: {stats['frames_in']} frames in, {stats['frames_out']} out "
        f"({stats['width']}x{stats['height']} at {stats['fps']:.1f} fps, "
        f"{stats['frames_dropped']} left out as this machine was behind, "
        f"{stats['frames_untracked']} untracked, {stats['frames_over_rate']} held back by the "
        f"geometry's rate cap, {stats['malformed']} malformed)"
    )
    # The second path's copies (late frames asked for them) are shown only when there were any.
    spare = f"  second path {k['spare']:.1f}" if k.get("spare") else ""
    print(
        f"kbit/s: geometry {k['geometry']:.1f} (of which the edge {stats['edge_kbps']:.1f})  "
        f"rem {k['rem']:.1f}  snapshot {k['snapshot']:.1f}  "
        f"control {k['control']:.2f}  audio {k['audio']:.1f}{spare}  total {k['total']:.1f}"
    )
    if stats.get("scenes"):
        firsts = ", ".join(f"{s:.2f}" for s in stats["scene_first_s"])
        print(f"scenes: {stats['scenes']} new, each one's first picture after {firsts} s")
    fit = stats.get("fit_residual") or {}
    if fit.get("sent_px"):
        f, sent = fit["fit_px"], fit["sent_px"]
        print(
            f"fit: the sent face is {sent['median']:.2f} px RMS from the tracked one "
            f"(p90 {sent['p90']:.2f}), the wire fit alone {f['median']:.2f} (p90 {f['p90']:.2f})"
        )
    rem = stats.get("rem") or {}
    if rem.get("patches"):
        sent, got = rem["sender"], rem.get("receiver", {})
        regions = sorted({*sent["images"], *sent["references"]})
        each = ", ".join(
            f"{r} {sent['images'].get(r, 0)}+{sent['references'].get(r, 0)}" for r in regions
        )
        print(
            f"rem: {rem['patches']} patches (images+references: {each}), "
            f"{sum(got.get('applied', {}).values())} applied, "
            f"{sum(got.get('dropped', {}).values())} dropped"
        )
    sound = stats.get("audio") or {}
    if sound.get("packets"):
        off = sound["av_offset_ms"]
        print(
            f"sound ({sound['sink']}): {sound['played']} x 20 ms played, "
            f"{sound['concealed']} concealed, "
            f"sound minus face {off['p50']:+.0f} ms (p5 {off['p5']:+.0f}, p95 {off['p95']:+.0f})"
        )
    print(
        f"sender {stats['sender_fps']:.0f} fps, receiver {stats['receiver_fps']:.0f} fps, "
        f"latency p50 {lat['p50']:.1f} ms p99 {lat['p99']:.1f} ms"
    )
    written = [str(p) for p in (args.output, args.compare, args.sheet) if p]
    print("wrote " + ", ".join(written))
