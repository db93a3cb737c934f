"""``facewire bandwidth``: our call next to H.264, VP9 and AV1 on the same clip.

Our codec runs as ``facewire demo --every-frame`` does (a real, paced loopback call between
two processes, encrypted, every frame sent however busy the machine; run as a child process,
as benchmarks/bench_quality.py runs it). The ordinary codecs encode the same frames with call
settings (facewire.codecs) at each target rate and each rung of a resolution ladder. Every
output is scored against the input by facewire.quality: frame i against frame i, luma SSIM
and PSNR over the face, the head and the whole frame, regions from the input's own landmarks
(tracked once).

Rates are bits per second over the clip's duration: "amortised" counts everything (our
snapshot, the codecs' key frame), "steady" everything after it. Our payload rates are per
channel; our totals leave the sound out (the codecs compared carry none).

On the wire, our call is counted, not modelled: where the machine allows (root, ``ip
netns``), the same clip (its first --frames frames, looping) goes face only through a real
call between two network namespaces joined by a veth pair, and the link's own counters give
the bytes and packets each way over a steady window about as long as the clip, after the
full snapshot (facewire/onlink.py). Elsewhere our wire rate is unknown: no model of the
datagram path met the count within 3% (facewire/wire.py says what was tried). The codecs'
wire rates are a model: their frames over SRTP/UDP (facewire.wire.rtp_bytes).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facewire import codecs, wire
from facewire.quality import QualityReport, read_frames, score_frames
from facewire.rdreport import break_even, matches, print_report

logger = logging.getLogger(__name__)

SCHEMA_VERSION = 2
DEFAULT_RATES_KBPS = "8,16,32,64"
DEFAULT_LADDER = "1,0.5,0.25"
#: Channels left out of our totals: the codecs compared carry no sound.
NOT_PICTURE = ("audio",)
#: Ladder rungs whose shorter side would be under this many pixels are left out.
MIN_RUNG_SIDE = 64
#: Our call on a link: its steady window is the clip's length, at least this long (the
#: keyframes that bring REM patches come every 4 s), and starts this long after the receiver
#: has the full snapshot.
MIN_LINK_WINDOW_S = 8.0
LINK_SETTLE_S = 2.0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "bandwidth",
        help="our call against H.264, VP9 and AV1 on one clip: rates and region quality",
        description="Our call next to H.264, VP9 and AV1 on the same clip. Our call runs as "
        "facewire demo runs it; the codecs encode the same frames with a call's settings at "
        "each rate and each rung of a resolution ladder. Every output is scored against the "
        "input: luma SSIM and PSNR over the face, the head and the whole frame.",
    )
    p.add_argument("--input", metavar="FILE", help="video file (default: the bundled clip)")
    p.add_argument("--json", metavar="OUT.json", help="write every operating point")
    p.add_argument("--plot", metavar="OUT.png", help="draw the rate-quality curves")
    p.add_argument(
        "--rates",
        default=DEFAULT_RATES_KBPS,
        metavar="KBPS,...",
        help=f"codec target rates in kbit/s (default {DEFAULT_RATES_KBPS})",
    )
    p.add_argument(
        "--codecs",
        default=",".join(codecs.CODECS),
        metavar="NAME,...",
        help=f"codecs to run (default {','.join(codecs.CODECS)})",
    )
    p.add_argument(
        "--ladder",
        default=DEFAULT_LADDER,
        metavar="SCALE,...",
        help=f"frame sizes as fractions of the input's (default {DEFAULT_LADDER}; rungs under "
        f"{MIN_RUNG_SIDE} px are left out)",
    )
    p.add_argument("--frames", type=int, metavar="N", help="use at most the first N frames")
    p.add_argument(
        "--fast", action="store_true", help="run our call unpaced (see facewire demo --fast)"
    )

    p.set_defaults(func=run)


def _numbers(text: str, option: str) -> list[float]:
    values = []
    for part in text.split(","):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(f"{option}: {part.strip()!r} is not a number (in {text!r})") from None
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"{option}: {part.strip()} is not a positive number")
        values.append(value)
    return sorted(set(values))


def parse_rates(text: str) -> list[float]:
    """Target rates in kbit/s from "8,16,32"."""
    return _numbers(text, "--rates")


def parse_ladder(text: str) -> list[float]:
    """Scales from "1,0.5", largest first; each in (0, 1]."""
    scales = _numbers(text, "--ladder")
    if scales[-1] > 1:
        raise ValueError(f"--ladder: {scales[-1]:g} is larger than the input (at most 1)")
    return scales[::-1]


def parse_codecs(text: str) -> list[codecs.CodecSpec]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ValueError("--codecs: no codec named")
    return [codecs.codec_spec(n) for n in dict.fromkeys(names)]


def rungs(width: int, height: int, ladder: Sequence[float]) -> list[tuple[float, tuple[int, int]]]:
    """(scale, (w, h)) of each ladder rung to encode, distinct sizes only."""
    out: list[tuple[float, tuple[int, int]]] = []
    for scale in ladder:
        size = codecs.even_size(width, height, scale)
        if min(size) < MIN_RUNG_SIDE and out:
            logger.info("ladder rung %g (%dx%d) left out: under %d px", scale, *size, MIN_RUNG_SIDE)
            continue
        if all(size != s for _, s in out):
            out.append((scale, size))
    return out


def run(args: argparse.Namespace) -> int:
    from facewire.sender.capture import VideoSource, demo_clip_path

    rates = parse_rates(args.rates)
    specs = parse_codecs(args.codecs)
    ladder = parse_ladder(args.ladder)
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    codecs.check_available(specs)
    for name, path in (("--json", args.json), ("--plot", args.plot)):
        if path and not Path(path).resolve().parent.is_dir():
            raise ValueError(f"{name}: folder {Path(path).parent} does not exist")
    clip = Path(args.input) if args.input else demo_clip_path()
    with VideoSource(clip) as video:  # a missing or unreadable file ends here, one line
        width, height, fps = video.width, video.height, video.fps
        clip_frames = video.frame_count

    landmarks = _track(clip, args.frames)
    count = len(landmarks)
    result: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        "input": str(clip),
        "width": width,
        "height": height,
        "fps": fps,
        "frames": count,
        "untracked": sum(p is None for p in landmarks),
        "settings": {
            "rates_kbps": rates,
            "ladder": [
                {"scale": s, "width": w, "height": h} for s, (w, h) in rungs(width, height, ladder)
            ],
            "codecs": {
                s.name: {
                    "label": s.label,
                    "encoder": s.encoder,
                    "decoder": s.decoder,
                    "options": s.encoder_options("RATE"),
                }
                for s in specs
            },
        },
    }
    with tempfile.TemporaryDirectory(prefix="facewire-bandwidth-") as tmp:
        result["ours"] = run_ours(clip, count, fps, args.fast, landmarks, Path(tmp))
        whole = clip_frames is not None and count >= clip_frames
        result["ours"]["wire"] = our_wire(clip, count, fps, whole, Path(tmp))
    wire_up = result["ours"]["wire"].get("kbps", {}).get("up")
    if wire_up is not None:
        # The direction the codecs' SRTP model counts: sender to receiver.
        result["ours"]["kbps"]["wire"] = {"steady": wire_up}
    result["points"] = run_codecs(clip, count, fps, specs, rates, ladder, landmarks)
    result["matches"] = matches(result["ours"], result["points"], [s.name for s in specs])
    result["break_even"] = break_even(result)
    print_report(result, specs)
    if args.json:
        Path(args.json).write_text(json.dumps(_nulls(result), indent=2) + "\n")
        print(f"wrote {args.json}")
    if args.plot:
        from facewire.rdplot import plot

        plot(result, Path(args.plot))
        print(f"wrote {args.plot}")
    return 0


def _nulls(value: Any) -> Any:
    """``value`` with every nan (a region no frame showed, a rate not reached) as None: the
    JSON stays standard."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {k: _nulls(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nulls(v) for v in value]
    return value


def _progress(total: int, desc: str) -> Any:
    from tqdm import tqdm

    # disable=None: no bar when stderr is not a terminal (a log file stays clean).
    return tqdm(total=total, desc=desc, unit="", leave=False, disable=None, file=sys.stderr)


def _frames(clip: Path, count: int | None) -> Iterator[np.ndarray]:
    return itertools.islice(read_frames(clip), count)


def _track(clip: Path, limit: int | None) -> list[np.ndarray | None]:
    """The input's landmarks ((468, 3) image pixels, None without a face), frame by frame."""
    from facewire.sender.landmarks import LandmarkTracker

    tracker = LandmarkTracker()
    out: list[np.ndarray | None] = []
    with _progress(limit or 0, "tracking the input") as bar:
        for frame in _frames(clip, limit):
            found = tracker.track(frame)
            out.append(None if found is None else found.points)
            bar.update()
    if not out:
        raise ValueError(f"no frames in {clip}")
    return out


def _quality(report: QualityReport) -> dict[str, Any]:
    d = report.as_dict()
    return {"ssim": d["ssim"], "psnr_db": d["psnr_db"], "held": d["held"]}


def run_call(clip: Path, frames: int, fast: bool, folder: Path) -> tuple[dict[str, Any], Path]:
    """``facewire demo`` on ``clip`` as a child process: its stats and its recording."""
    output, stats = folder / "call.mp4", folder / "call.json"
    cmd = [sys.executable, "-m", "facewire", "demo", "--input", str(clip), "--frames", str(frames)]
    cmd += ["--output", str(output), "--compare", "", "--stats", str(stats)]
    cmd.append("--fast" if fast else "--every-frame")  # the picture is scored, not the load
    env = dict(os.environ, PYOPENGL_PLATFORM=os.environ.get("PYOPENGL_PLATFORM", "egl"))
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines() or [f"exit status {done.returncode}"]
        raise RuntimeError(f"our call failed: {lines[-1].removeprefix('facewire: error: ')}")
    return json.loads(stats.read_text()), output


def _kbps(nbytes: float, duration_s: float) -> float:
    return nbytes * 8 / duration_s / 1000


def our_rates(stats: dict[str, Any]) -> dict[str, Any]:
    """Our call's payload kbit/s per channel from ``facewire demo``'s stats, the picture's
    totals amortised and steady, and the messages per channel (both directions)."""
    duration = stats["duration_s"]
    payload = {ch: _kbps(n, duration) for ch, n in stats["bytes"].items()}
    picture = {ch: v for ch, v in payload.items() if ch not in NOT_PICTURE}
    steady = sum(v for ch, v in picture.items() if ch != "snapshot")
    messages: dict[str, int] = {}
    for by_channel in stats["messages"].values():
        for channel, sizes in by_channel.items():
            messages[channel] = messages.get(channel, 0) + sum(int(n) for _, n in sizes)
    return {
        "kbps": {"payload": {"amortised": sum(picture.values()), "steady": steady}},
        "channels_kbps": {"payload": payload},
        "messages": messages,
    }


def our_wire(clip: Path, count: int, fps: float, whole: bool, folder: Path) -> dict[str, Any]:
    """Our call on the wire, counted on a veth link (facewire/onlink.py): the clip (``whole``)
    or its first ``count`` frames, looping, face only; or why it is unknown.

    Returns ``source`` "measured" with ``kbps`` and ``pps`` each way (``up``: sender to
    receiver, ``down``, ``total``; IP headers counted, Ethernet's not), ``mean_packet``,
    ``seconds`` (the steady window), ``link``, ``sent`` (what the sender played), the frames
    sent and shown, and the call's ``notes``; or ``source`` "unknown" with ``why``.
    """
    from facewire import onlink

    reason = onlink.unavailable()
    if reason is not None:
        return {"source": "unknown", "why": f"without a link to count on: {reason}"}
    seconds = max(count / fps, MIN_LINK_WINDOW_S)
    sent = clip if whole else _first_frames(clip, count, fps, folder)
    try:
        with _progress(1, "our call on a link") as bar:
            r = onlink.measure_call(sent, seconds, None, sound=False, settle_s=LINK_SETTLE_S)
            bar.update()
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        return {"source": "unknown", "why": f"the link could not be made: {exc}"}
    steady = r.get("steady")
    if steady is None:
        return {"source": "unknown", "why": f"the call on the link failed: {r['problem']}"}
    directions = ("up", "down", "total")
    return {
        "source": "measured",
        "link": r["link"],
        "sent": "the clip" if whole else f"its first {count} frames",
        "seconds": steady["seconds"],
        "settle_s": LINK_SETTLE_S,
        "kbps": {d: steady[d]["kbps"] for d in directions},
        "pps": {d: steady[d]["pps"] for d in directions},
        "mean_packet": {d: steady[d]["mean_packet"] for d in directions},
        "frames_sent": r.get("frames_sent"),
        "frames_shown": r.get("frames_shown"),
        "notes": r["notes"],
    }


def _first_frames(clip: Path, count: int, fps: float, folder: Path) -> Path:
    """The first ``count`` frames of ``clip`` as a lossless video (FFV1) the sender can loop."""
    import cv2

    path = folder / "first-frames.avi"
    writer: Any = None
    try:
        for frame in _frames(clip, count):
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"FFV1"), fps, size)
                if not writer.isOpened():
                    raise RuntimeError(f"cannot write {path} (FFV1)")
            writer.write(frame)
    finally:
        if writer is not None:
            writer.release()
    return path


def run_ours(
    clip: Path,
    count: int,
    fps: float,
    fast: bool,
    landmarks: list[np.ndarray | None],
    folder: Path,
) -> dict[str, Any]:
    with _progress(1, "our call") as bar:
        stats, output = run_call(clip, count, fast, folder)
        bar.update()
    report = score_frames(_frames(clip, count), read_frames(output), landmarks)
    out: dict[str, Any] = {
        "call": {
            k: stats.get(k)
            for k in (
                "frames_in",
                "frames_out",
                "frames_dropped",
                "frames_held",
                "frames_untracked",
                "encrypted",
            )  # fmt: skip
        },
        "bytes": stats["bytes"],
    }
    out.update(our_rates(stats))
    out["quality"] = _quality(report)
    out["recording_ceiling"] = _quality(recording_ceiling(clip, count, fps, landmarks, folder))
    return out


def recording_ceiling(
    clip: Path, count: int, fps: float, landmarks: list[np.ndarray | None], folder: Path
) -> QualityReport:
    """The input itself through the receiver's MP4 recorder: the best our scores can be."""
    from facewire.receiver.recorder import Mp4Recorder

    path = folder / "input-recorded.mp4"
    frames = _frames(clip, count)
    first = next(frames)
    with Mp4Recorder(path, first.shape[1], first.shape[0], fps) as rec:
        for frame in itertools.chain([first], frames):
            rec.write(frame)
    return score_frames(_frames(clip, count), read_frames(path), landmarks)


def run_codecs(
    clip: Path,
    count: int,
    fps: float,
    specs: Sequence[codecs.CodecSpec],
    rates_kbps: Sequence[float],
    ladder: Sequence[float],
    landmarks: list[np.ndarray | None],
) -> list[dict[str, Any]]:
    first = next(read_frames(clip))
    height, width = first.shape[:2]
    plan = [
        (spec, scale, size, rate)
        for spec in specs
        for scale, size in rungs(width, height, ladder)
        for rate in rates_kbps
    ]
    points = []
    with _progress(len(plan), "codecs") as bar:
        for spec, scale, size, rate in plan:
            bar.set_postfix_str(f"{spec.name} {size[0]}x{size[1]} {rate:g} kbit/s")
            encoded = codecs.encode(_frames(clip, count), spec, round(rate * 1000), size, fps)
            decoded = codecs.decode(encoded, spec, (width, height))
            report = score_frames(_frames(clip, count), decoded, landmarks)
            duration = encoded.duration_s
            wire_all = sum(wire.rtp_bytes(len(p)) for p in encoded.packets)
            wire_first = wire.rtp_bytes(encoded.first_packet_bytes)
            points.append(
                {
                    "codec": spec.name,
                    "target_kbps": rate,
                    "scale": scale,
                    "width": size[0],
                    "height": size[1],
                    "frames": encoded.frames,
                    "dropped": report.held,
                    "keyframes": encoded.keyframes,
                    "first_packet_bytes": encoded.first_packet_bytes,
                    "bytes": encoded.bytes,
                    "kbps": {
                        "payload": {
                            "amortised": encoded.bps / 1000,
                            "steady": encoded.steady_bps / 1000,
                        },
                        "wire": {
                            "amortised": _kbps(wire_all, duration),
                            "steady": _kbps(wire_all - wire_first, duration),
                        },
                    },
                    **_quality(report),
                }
            )
            bar.update()
    return points
