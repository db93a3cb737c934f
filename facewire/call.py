"""``facewire send``, ``facewire receive`` and ``facewire call``: a call between two machines.

``send`` tracks a camera or a video and sends the face; ``receive`` rebuilds it, records it
and measures it; ``call`` does both at once, each end showing the other. Either end may bind,
the other connects (addresses and keys: :mod:`facewire.peer`).

Ctrl-C or SIGTERM ends a command cleanly: a sender says Bye, a receiver closes its recording
(a playable MP4 with its index) and tells the sender it left. A receiver whose sender ended
says so in one line and waits for the next session; a sender whose receiver left waits for the
next receiver.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import multiprocessing as mp
import queue
import signal
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from types import FrameType
from typing import Any

from facewire.peer import (
    Address,
    add_address_arguments,
    add_key_arguments,
    address_from,
    check_ports_free,
    receiver_keys,
    sender_keys,
)
from facewire.protocol.constants import LATE_FRAMES
from facewire.protocol.transport import TransportError
from facewire.watch import Watchers, add_watch_arguments, check_watch_arguments, wants_watching

logger = logging.getLogger(__name__)

#: Larger inputs are scaled down to fit before tracking: the receiver renders at the sender's
#: size, and above this llvmpipe cannot render 30 fps (BENCHMARKS.md, "Renderer").
MAX_SIZE = (1280, 720)
#: Time a closing end gives its last message (Bye, "left") to leave.
LINGER_S = 0.5
#: A two-way call: the binding end sends on PORT, PORT+1 and receives on PORT+2, PORT+3.
CALL_PORTS = 4


class StopSignal:
    """SIGINT and SIGTERM ask the loops to end (they look at ``stop()``); a second one
    interrupts at once (KeyboardInterrupt)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.reason: str | None = None
        self._old: dict[int, Any] = {}

    def __call__(self) -> bool:
        return self.reason is not None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.reason is not None:
            raise KeyboardInterrupt
        self.reason = signal.Signals(signum).name

    def __enter__(self) -> StopSignal:
        for sig in self.SIGNALS:
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def say(line: str) -> None:
    """One line for the person running the command (stdout, at once: it may be a pipe)."""
    print(line, flush=True)


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if width < 16 or height < 16:
        raise argparse.ArgumentTypeError(f"too small: {text}")
    return width, height


def _playout_delay(text: str) -> float | None:
    if text == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected milliseconds or auto, got {text!r}") from None
    if not 0 <= value <= 2000:
        raise argparse.ArgumentTypeError(f"expected 0 to 2000 ms, got {text!r}")
    return value


def _display_fps(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frames per second, got {text!r}") from None
    if not 0 < value <= 240:
        raise argparse.ArgumentTypeError(f"expected above 0 and at most 240 fps, got {text!r}")
    return value


def _timeout(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}")
    return value


# --- the sending end -------------------------------------------------------------------------


def _add_source_arguments(p: argparse.ArgumentParser) -> None:
    source = p.add_mutually_exclusive_group()
    source.add_argument("--camera", type=int, metavar="N", help="send camera N (/dev/videoN)")
    source.add_argument(
        "--input", metavar="FILE", help="send a video file (default: the bundled clip)"
    )
    p.add_argument(
        "--loop", action="store_true", help="play the file again and again, its sound too"
    )
    p.add_argument("--frames", type=int, metavar="N", help="send at most N frames")
    add_size_argument(p)


def add_size_argument(p: argparse.ArgumentParser) -> None:
    """--max-size, for `send`, `room` and `demo` alike."""
    p.add_argument(
        "--max-size",
        type=_size,
        default=MAX_SIZE,
        metavar="WxH",
        help=f"scale larger inputs down to fit, turned the way the input is (default "
        f"{MAX_SIZE[0]}x{MAX_SIZE[1]}: a 720x1280 phone picture is sent as it is)",
    )


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def _sound_kbps(text: str) -> float:
    from facewire.sender.audio import MAX_BITRATE, MIN_BITRATE

    kbps = _number(text)
    if not MIN_BITRATE <= kbps * 1000 <= MAX_BITRATE:
        raise argparse.ArgumentTypeError(
            f"{kbps:g} kbit/s is outside Opus' {MIN_BITRATE // 1000}-{MAX_BITRATE // 1000}"
        )
    return kbps


def _geometry_kbps(text: str) -> float:
    kbps = _number(text)
    if not (0 <= kbps < float("inf")):
        raise argparse.ArgumentTypeError(f"expected kbit/s >= 0 (0: no cap), got {text!r}")
    return kbps


def add_geometry_arguments(p: argparse.ArgumentParser) -> None:
    """The sending end's cap on the face's parameter packets (sender/rate_cap.py)."""
    from facewire.sender.rate_cap import GEOMETRY_KBPS

    p.add_argument(
        "--geometry-kbps",
        type=_geometry_kbps,
        default=GEOMETRY_KBPS,
        metavar="KBPS",
        help=f"cap on the face's parameter packets; over it a frame's packet waits and the "
        f"receiver keeps the last picture (default {GEOMETRY_KBPS:g}; 0: no cap)",
    )


def _max_kbps(text: str) -> float:
    from facewire.protocol.congestion import MIN_RATE_BPS

    value = _number(text)
    if not MIN_RATE_BPS / 1000 <= value < float("inf"):
        raise argparse.ArgumentTypeError(
            f"expected at least {MIN_RATE_BPS / 1000:g} kbit/s (the face alone needs that), "
            f"got {text!r}"
        )
    return value


def add_budget_argument(p: argparse.ArgumentParser) -> None:
    """The sending end's budget on the wire (protocol/media_path.py)."""
    from facewire.protocol.media_path import DEFAULT_BUDGET_BPS

    p.add_argument(
        "--max-kbps",
        type=_max_kbps,
        metavar="N",
        help="the most this end sends, kbit/s on the wire with every header counted; less when "
        f"the receiver's reports say the link carries less (default {DEFAULT_BUDGET_BPS / 1000:g})",
    )
    p.add_argument(
        "--tcp-only",
        action="store_true",
        help="send the media over ZeroMQ/TCP, as version 2 did, instead of as datagrams (UDP)",
    )


def add_sound_arguments(p: argparse.ArgumentParser) -> None:
    """The sending end's sound: the file's audio track, or the microphone with a camera."""
    sound = p.add_mutually_exclusive_group()
    sound.add_argument(
        "--sound-kbps",
        type=_sound_kbps,
        default=12.0,
        metavar="N",
        help="Opus bit rate of the voice, kbit/s (default 12)",
    )
    sound.add_argument("--no-sound", action="store_true", help="send the face alone")


def sound_as_asked(
    args: argparse.Namespace,
    source: int | str | Path,
    is_camera: bool,
    realtime: bool,
    publish: Callable[[Any], None],
    notify: Callable[[str], None],
    budget_bps: float,
) -> Any:
    """The AudioSender for ``source`` at the options' bit rate, in Opus packets as long as the
    call's on-the-wire budget asks; None with --no-sound, or when there is no sound to send
    (said in one line to ``notify``)."""
    from facewire.sender.audio import AudioSettings, frame_ms_for, sound_for

    if args.no_sound:
        return None
    settings = AudioSettings(
        bitrate=round(args.sound_kbps * 1000), frame_ms=frame_ms_for(budget_bps)
    )
    loop = bool(getattr(args, "loop", False))
    return sound_for(source, is_camera, realtime, publish, settings, notify, loop)


@dataclass
class _Presence:
    """Receivers that said they are ready and have not said they left."""

    active: int = 0
    lossy: bool = False  # a receiver has reported late frames

    def on_stats(self, values: dict[str, float], tell: Callable[[str], None]) -> None:
        if values.get(LATE_FRAMES) and not self.lossy:
            self.lossy = True
            tell("the receiver sees late frames (packets lost): frames go by the second path too")
        if values.get("ready"):
            self.active += 1
            tell("a receiver joined")
        if values.get("left"):
            self.active = max(0, self.active - 1)
            tell("the receiver left" + ("; waiting for another" if self.active == 0 else ""))


class _Source:
    """The frames to send: camera or file (looped if asked), scaled to fit, numbered on."""

    def __init__(self, args: argparse.Namespace) -> None:
        from facewire.sender.capture import VideoSource, demo_clip_path
        from facewire.sender.session import capped_size

        if args.frames is not None and args.frames < 1:
            raise ValueError(f"--frames must be at least 1, got {args.frames}")
        self.path = None if args.camera is not None else Path(args.input or demo_clip_path())
        self.loop = args.loop and self.path is not None
        self.video = VideoSource(
            args.camera if self.path is None else self.path, realtime=self.path is not None
        )
        self.size = capped_size(self.video.width, self.video.height, *args.max_size)
        self.limit = args.frames
        bundled = args.camera is None and args.input is None
        self.name = "the bundled clip" if bundled else self.video.name
        self._dropped_before = 0  # by the file's earlier loops
        self._offset = 0  # the number of the file's first frame in this loop

    @property
    def read_to(self) -> int:
        """The number of the input's frame after the last one read (sent or left out)."""
        return self._offset + self.video.read_to

    @property
    def dropped(self) -> int:
        """Input frames left out because this end was behind (see VideoSource)."""
        return self._dropped_before + self.video.dropped

    @property
    def scaled_from(self) -> str:
        native = (self.video.width, self.video.height)
        return "" if native == self.size else f", scaled from {native[0]}x{native[1]}"

    def frames(self) -> Iterator[Any]:
        from facewire.sender.session import scaled

        return scaled(self._numbered(), self.size)

    def _numbered(self) -> Iterator[Any]:
        from facewire.sender.capture import VideoSource

        while True:
            # --frames counts the input's frames, those a busy machine left out too.
            left = None if self.limit is None else self.limit - self._offset
            if left is not None and left <= 0:
                return
            count = 0
            for frame in self.video.frames(limit=left):
                count += 1
                yield replace(frame, index=frame.index + self._offset)
            if not self.loop or count == 0:
                return
            self._offset += self.video.read_to  # every frame the file has, left out or not
            self._dropped_before += self.video.dropped
            self.video.close()
            assert self.path is not None
            self.video = VideoSource(self.path, realtime=True)

    def close(self) -> None:
        self.video.close()


def _paused_while_alone(
    frames: Iterator[Any],
    source: _Source,
    endpoint: Any,
    presence: _Presence,
    stop: Callable[[], bool],
    tell: Callable[[str], None],
    wait: bool = True,
) -> Iterator[Any]:
    """``frames``, waiting for a new receiver whenever the last one has left (``wait``), or
    ending there."""
    from facewire.sender.session import wait_until_ready

    for frame in frames:
        if presence.active == 0:
            if not wait or not wait_until_ready(endpoint, math.inf, lambda: not stop()):
                return
            presence.active += 1
            tell("a receiver joined")
            source.video.resync(frame.index + 1)
        yield frame


def send(
    args: argparse.Namespace,
    address: Address,
    keys: dict[str, Any],
    stop: Callable[[], bool],
    tell: Callable[[str], None] = say,
    offset: int = 0,
    wait_when_alone: bool = True,
) -> dict[str, Any]:
    """Run the sending end until its input ends or ``stop()``; returns its figures.

    ``offset``: ports used from the address's PORT on (a two-way call's second direction).
    When its receiver has left, it waits for another (``wait_when_alone``), or ends.
    """
    from facewire.protocol.transport import SenderEndpoint
    from facewire.sender.audio import with_sound
    from facewire.sender.encoder import FaceEncoder
    from facewire.sender.session import restamped, run_sender, start_session, wait_until_ready
    from facewire.sender.snapshot_draft import draft, sharper

    source = _Source(args)
    try:
        encoder = FaceEncoder(
            *source.size, source.video.fps, geometry_kbps=args.geometry_kbps or None
        )
        frames = source.frames()
        snapshot, buffered = start_session(encoder, frames, source.video.fps, source.name)
        width, height = source.size
        endpoint = SenderEndpoint(
            address.host,
            *address.ports(offset),
            connect=not address.bind,
            max_bps=None if args.max_kbps is None else args.max_kbps * 1000,
            fps=source.video.fps,
            udp=not args.tcp_only,
            **keys,
        )
        try:
            endpoint.set_snapshot(snapshot, draft(snapshot), sharper(snapshot))
            tell(
                f"sending {source.name} ({width}x{height} at {source.video.fps:g} fps"
                f"{source.scaled_from}) as session {snapshot.session_id}; waiting for a "
                f"receiver {address.describe(offset)}"
            )
            timeout = args.join_timeout or math.inf
            if not wait_until_ready(endpoint, timeout, lambda: not stop()):
                if stop():
                    tell("stopped before a receiver joined")
                    return {"frames_in": 0, "packets": 0, "stopped": True}
                hint = (
                    "is the other end running?"
                    if keys.get("plain")
                    else "is the other end running, with this end's public key as its --peer "
                    "and its own among this end's --peer files?"
                )
                raise RuntimeError(
                    f"no receiver joined within {timeout:g} s {address.describe(offset)} ({hint})"
                )
            tell("a receiver joined; sending")
            source.video.resync(buffered[-1].index + 1)
            presence = _Presence(active=1)
            rest = _paused_while_alone(
                frames, source, endpoint, presence, stop, tell, wait_when_alone
            )
            where = source.path if source.path is not None else args.camera
            sound = sound_as_asked(
                args, where, source.video.is_camera, True, endpoint.publish, tell,
                endpoint.max_bps,
            )  # fmt: skip
            sent = with_sound(itertools.chain(restamped(buffered), rest), sound, source.video.fps)
            report = run_sender(
                endpoint,
                encoder,
                sent,
                stop=stop,
                on_stats=lambda values: presence.on_stats(values, tell),
                read_to=lambda: source.read_to,
            )
        finally:
            media = endpoint.media_figures()
            endpoint.close(linger_s=LINGER_S)  # the Bye gets out
    finally:
        source.close()
    why = "stopped" if report.stopped or stop() else "end of input"
    behind = f", {source.dropped} left out: this machine was behind" if source.dropped else ""
    tell(f"sent {report.frames_in} frames ({why}{behind}); said bye")
    return {
        "frames_in": report.frames_in,
        "frames_dropped": source.dropped,
        "packets": report.packets,
        "keyframe_requests": report.keyframe_requests,
        "sender_fps": report.fps,
        "frames_untracked": encoder.frames_untracked,
        "frames_over_rate": 0 if encoder.rate_cap is None else encoder.rate_cap.held,
        "edge_bytes": round(encoder.edge_bytes),
        "body_bytes": round(encoder.body_bytes),
        "refresh_bytes": 0 if encoder.refresh is None else encoder.refresh.bytes,
        "fit_residual": encoder.residual.summary(),
        "width": width,
        "height": height,
        "fps": source.video.fps,
        "bytes_sent": dict(endpoint.bytes_sent),
        "bytes_received": dict(endpoint.bytes_received),
        "media": media,
        "stopped": report.stopped or stop(),
    }


def run_send(args: argparse.Namespace) -> int:
    address = address_from(args)
    keys = sender_keys(args)
    _check_stats(args.stats)
    with StopSignal() as stop:
        stats = send(args, address, keys, stop)
    _write_stats(args.stats, stats)
    return 0


# --- the receiving end -----------------------------------------------------------------------


def _check_stats(path: str | None) -> None:
    """The figures are written at the end of a call: a folder that is not there would lose
    them after the whole call, so it is checked first."""
    if path is not None and not Path(path).parent.is_dir():
        raise ValueError(
            f"cannot write the figures to {path}: folder {Path(path).parent} does not exist"
        )


def _check_record(path: str | None) -> None:
    if path is None:
        return
    folder = Path(path).parent
    if not folder.is_dir():
        raise ValueError(f"cannot record to {path}: folder {folder} does not exist")
    if Path(path).suffix.lower() != ".mp4":
        raise ValueError(f"cannot record to {path}: the recording is an .mp4 file")


def receive(
    args: argparse.Namespace,
    address: Address,
    keys: dict[str, Any],
    stop: Callable[[], bool],
    tell: Callable[[str], None] = say,
    offset: int = 0,
    sink: Any = None,
    once: bool = False,
) -> dict[str, Any]:
    """Run the receiving end until ``stop()`` (or, with ``once``, the first session's end).

    ``sink`` gets every rendered picture (receiver.session.FrameSink): the seam for a live
    view. Raises TransportError when ``args.join_timeout`` passes before any sender comes.
    """
    from facewire.receiver.playout import PlayoutSettings
    from facewire.receiver.session import run_receiver

    timeout = args.join_timeout or math.inf
    playout = PlayoutSettings(args.playout_delay, args.display_fps)
    report = run_receiver(
        address.host,
        *address.ports(offset),
        args.record,
        join_timeout_s=timeout,
        rejoin_timeout_s=0.0 if once else timeout,
        sink=sink,
        stop=stop,
        notify=tell,
        playout=playout,
        bind=address.bind,
        **keys,
    )
    stats = report.as_dict()
    tell(summary(report, stats, args.record))
    return stats


def summary(report: Any, stats: dict[str, Any], record: str | None) -> str:
    """``receive``'s last line, from its ReceiverReport and that report's ``as_dict()``."""
    lat = stats["latency_ms"]
    recorded = f" to {record}" if record and report.sessions else ""
    # Capture times are the sender's clock: only a shared clock (one host) gives a latency.
    latency = (
        f", latency p50 {lat['p50']:.1f} ms p99 {lat['p99']:.1f} ms"
        if report.latency_ms and 0 <= min(report.latency_ms) and lat["max"] < 60_000
        else ""
    )
    spare = report.second_path
    # Only the TCP fallback has a second path: over datagrams late frames bring no copies.
    second = (
        f"; {spare['late_frames']} frames came late, the second path brought "
        f"{spare['saved']} sooner"
        if spare.get("copies")
        else ""
    )
    return (
        f"received {report.sessions} session(s), {report.frames_out} frames{recorded} "
        f"({report.ended_by}){latency}{second}"
    )


def run_receive(args: argparse.Namespace) -> int:
    address = address_from(args)
    keys = receiver_keys(args)
    _check_record(args.record)
    _check_stats(args.stats)
    with StopSignal() as stop, Watchers(args, say) as watch:
        stats = receive(
            args, address, keys, watch.stop(stop), watch.tell, sink=watch.sink, once=args.once
        )
    _write_stats(args.stats, stats)
    return 0


def _write_stats(path: str | None, stats: dict[str, Any]) -> None:
    if path:
        Path(path).write_text(json.dumps(stats, indent=2) + "\n")


# --- both at once ----------------------------------------------------------------------------


def _call_receiver(
    args: argparse.Namespace,
    address: Address,
    keys: dict[str, Any],
    offset: int,
    level: int,
    stop_event: Any,
    done: Any,
    results: Any,
) -> None:
    """Child process (its own OpenGL context): receive the other end until told to stop.

    With a live view or a window it first says ("watching", None), or ("error", why).
    """
    logging.basicConfig(level=level, format="%(asctime)s receive %(name)s: %(message)s")
    with StopSignal() as stop:
        try:
            watch = Watchers(args, lambda line: say(f"receive: {line}"))
        except (OSError, ValueError, RuntimeError) as exc:
            results.put(("error", str(exc)))
            done.set()
            return
        if wants_watching(args):
            results.put(("watching", None))
        try:
            stats = receive(
                args,
                address,
                keys,
                watch.stop(lambda: stop() or stop_event.is_set()),
                watch.tell,
                offset,
                sink=watch.sink,
                once=True,
            )
            results.put(("ok", stats))
        except TransportError as exc:  # names its side already
            logger.debug("receiver failed", exc_info=True)
            results.put(("error", str(exc)))
        except Exception as exc:  # reported as one line by the parent
            logger.debug("receiver failed", exc_info=True)
            results.put(("error", f"receiver: {exc}"))
        finally:
            watch.close()
            done.set()


def run_call(args: argparse.Namespace) -> int:
    address = address_from(args, ports_used=CALL_PORTS)
    check_ports_free(address, CALL_PORTS)
    keys_out, keys_in = sender_keys(args), receiver_keys(args)
    _check_record(args.record)
    _check_stats(args.stats)
    check_watch_arguments(args)
    # The binding end sends on PORT, PORT+1; the connecting end on PORT+2, PORT+3.
    send_offset, receive_offset = (0, 2) if address.bind else (2, 0)
    ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited sockets or GL state
    stop_event, done, results = ctx.Event(), ctx.Event(), ctx.Queue()
    level = logging.getLogger().getEffectiveLevel()
    child = ctx.Process(
        target=_call_receiver,
        args=(args, address, keys_in, receive_offset, level, stop_event, done, results),
    )
    child.start()
    try:
        if wants_watching(args):
            # A view that cannot be served (its port in use) ends the call before it starts.
            try:
                status, detail = results.get(timeout=60)
            except queue.Empty:
                raise RuntimeError("the receiving side did not start in time") from None
            if status == "error":
                raise RuntimeError(detail)
        # An endless input (a camera, a looped file) is sent until either end hangs up (here,
        # or the other end's Bye); a finite one (--frames, a file) to its end, unless this end
        # stops or the other end's receiver leaves: the other end's input ending first does
        # not cut this end's short.
        endless = args.frames is None and (args.camera is not None or args.loop)
        with StopSignal() as stop:
            sent = send(
                args,
                address,
                keys_out,
                lambda: stop() or (done.is_set() and endless),
                lambda line: say(f"send: {line}"),
                send_offset,
                wait_when_alone=False,
            )
            while not (stop() or done.wait(0.2)):
                pass  # our input ended; keep showing the other end until it hangs up
            stop_event.set()
            try:
                status, received = results.get(timeout=30)
            except queue.Empty:
                raise RuntimeError("the receiving side did not finish in time") from None
    finally:
        stop_event.set()
        child.join(timeout=10)
        if child.is_alive():
            child.terminate()
    if status == "error":
        raise RuntimeError(received)
    _write_stats(args.stats, {"sent": sent, "received": received})
    return 0


# --- the command line ------------------------------------------------------------------------


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--join-timeout",
        type=_timeout,
        metavar="S",
        help="give up (exit status 1) when the other end has not come within S seconds "
        "(default: wait until Ctrl-C)",
    )
    p.add_argument("--stats", metavar="FILE.json", help="write the figures as JSON at the end")


def _add_playout(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--playout-delay",
        type=_playout_delay,
        metavar="MS",
        default=0.0,
        help="time a jitter buffer adds to even out the network's jitter, in ms, or auto "
        "(adapted to the jitter seen, up to 80 ms); 0 (the default) shows each frame as it "
        "arrives: the least latency",
    )
    p.add_argument(
        "--display-fps",
        type=_display_fps,
        metavar="N",
        help="pictures per second on screen, in between frames blended feature by feature "
        "(default: the sender's frame rate)",
    )


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register ``send``, ``receive`` and ``call``."""
    p = subparsers.add_parser(
        "send",
        help="send a camera or video to a receiver",
        description="Tracks the face of a camera or a video and sends it to facewire "
        "receive. Ends at the end of the input or on Ctrl-C, with a Bye.",
    )
    add_address_arguments(p)
    _add_source_arguments(p)
    add_geometry_arguments(p)
    add_budget_argument(p)
    add_sound_arguments(p)
    add_key_arguments(p, "a receiver's public key file, or a folder of them (repeatable)")
    _add_common(p)
    p.set_defaults(func=run_send)

    p = subparsers.add_parser(
        "receive",
        help="receive a call, record and measure it",
        description="Rebuilds the face facewire send sends. Waits for the next session "
        "when one ends, until Ctrl-C.",
    )
    add_address_arguments(p)
    p.add_argument("--record", metavar="FILE.mp4", help="record what is rebuilt")
    p.add_argument("--once", action="store_true", help="end when the first session ends")
    add_watch_arguments(p)
    _add_playout(p)
    add_key_arguments(p, "the sender's public key file")
    _add_common(p)
    p.set_defaults(func=run_receive)

    p = subparsers.add_parser(
        "call",
        help="a two-way call: send and receive at once",
        description="Sends this end's camera or video and receives the other end's. One end "
        "binds tcp://*:PORT (it uses PORT..PORT+3), the other connects to it.",
    )
    add_address_arguments(p)
    _add_source_arguments(p)
    add_geometry_arguments(p)
    add_budget_argument(p)
    add_sound_arguments(p)
    p.add_argument("--record", metavar="FILE.mp4", help="record the other end")
    add_watch_arguments(p)
    _add_playout(p)
    add_key_arguments(p, "the other end's public key file")
    _add_common(p)
    p.set_defaults(func=run_call)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use the facewire command")
