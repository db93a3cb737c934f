"""The ``facewire`` command."""

from __future__ import annotations

import argparse
import logging
import os
import sys

logger = logging.getLogger("facewire")


def _add_demo(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "demo",
        help="loopback call on a video (the bundled clip by default)",
        description="Runs a sender and a receiver as two processes talking ZeroMQ on "
        "127.0.0.1, and records what the receiver rebuilds.",
    )
    p.add_argument(
        "--input", metavar="FILE", help="video file or camera number (default: the bundled clip)"
    )
    p.add_argument(
        "--output",
        metavar="FILE.mp4",
        default="demo-output.mp4",
        help="the reconstruction alone, frame i rebuilding input frame i",
    )
    p.add_argument(
        "--compare",
        metavar="FILE.mp4",
        default="demo-compare.mp4",
        help="input and reconstruction side by side",
    )
    p.add_argument(
        "--sheet",
        metavar="FILE.png",
        help="contact sheet: six frames as input, reconstruction and a heat map of the difference",
    )
    p.add_argument("--stats", metavar="FILE.json", help="write the call's statistics as JSON")
    p.add_argument("--frames", type=int, metavar="N", help="send at most N frames")
    p.add_argument(
        "--fast",
        action="store_true",
        help="read the file as fast as possible instead of at its frame rate",
    )
    p.add_argument(
        "--every-frame",
        action="store_true",
        help="at the file's frame rate, but never leave a frame out on a busy machine (as a "
        "camera would, and the call does by default): for scoring the picture, not the machine",
    )
    from facewire.call import (
        add_budget_argument,
        add_geometry_arguments,
        add_size_argument,
        add_sound_arguments,
    )

    add_size_argument(p)
    add_geometry_arguments(p)
    add_budget_argument(p)
    add_sound_arguments(p)
    p.add_argument(
        "--tracker",
        choices=("landmarks", "markers"),
        default="landmarks",
        help="landmarks (markerless, the default) or markers (coloured stickers at the rig's "
        "markers, lifted onto the face by ray casting: see the README)",
    )

    def run(args: argparse.Namespace) -> int:
        from facewire.demo import run_demo

        return run_demo(args)

    p.set_defaults(func=run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="facewire",
        description="A model-based video call: the sender tracks a face and sends a few kbit/s "
        "of its motion, the receiver rebuilds it from a 3D face model.",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    _add_demo(sub)
    from facewire import bandwidth

    bandwidth.add_parser(sub)
    from facewire import call, keys, relay, remmap, room, track, wirestool

    call.add_parsers(sub)
    relay.add_parser(sub)
    room.add_parser(sub)
    wirestool.add_parser(sub)
    keys.add_parser(sub)
    track.add_parser(sub)
    remmap.add_parser(sub)
    return parser


def _quiet_opencv() -> None:
    """OpenCV and the FFmpeg inside it print their own lines on stderr ("moov atom not found",
    "can't open camera by index") before ours says what is wrong; -vv lets them through."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    # AV_LOG_QUIET; OpenCV reads it when it first opens a file (child processes inherit it).
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    if args.verbose < 2:
        _quiet_opencv()
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print("facewire: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        # Bad input ends with one readable line; -vv shows where it came from.
        logger.debug("failed", exc_info=True)
        print(f"facewire: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
