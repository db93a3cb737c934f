"""What a call costs on the wire, counted on a real link (facewire/onlink.py), not a model.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_wire.py [--input CLIP]... [--seconds S]
           [--rate-kbit none,48,24]... [--sound] [--json OUT.json]

``facewire receive`` and ``facewire send --loop`` (CURVE keys) run in two network namespaces
joined by a veth pair, unshaped ("none") or shaped both ways with ``tc tbf`` at each rate
(burst 1600 bytes, latency 400 ms: facewire/onlink.py says why). The veth's own counters give
the link's bytes and packets over a steady window of ``--seconds`` that starts 3 s after the
receiver has its snapshot (the full one, where a draft came first), and over the whole call.
Prints one line per run: the link, kbit/s up (sender to receiver) and down, counting IP
headers and not Ethernet's, their total, packets a second each way, frames shown by the
receiver / sent by the sender, the receiver's latency (capture to picture; the namespaces
share a clock) p50 / p99, and the seconds from the sender offering its snapshot to the
receiver's first picture. Below each line: the whole call (join and Bye included), the
qdisc's drops and TCP's resent segments. Needs root; prints why and exits 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

from facewire.onlink import measure_call, unavailable


def _rates(values: list[str]) -> list[float | None]:
    rates: list[float | None] = []
    for value in values:
        for word in value.split(","):
            word = word.strip().lower()
            if word in ("none", "clean", "0", ""):
                rates.append(None)
            else:
                rates.append(float(word))
    return rates


def _f(value: float | None, spec: str = ".1f") -> str:
    return "-" if value is None else format(value, spec)


def row(clip: str, r: dict[str, Any]) -> str:
    link = "clean" if r["rate_kbit"] is None else f"tbf {r['rate_kbit']:g}k"
    lat = r.get("latency_ms") or {}
    s = r.get("steady")
    if s is None:
        figures = f"{'-':>7} {'-':>7} {'-':>7} {'-':>11}"
    else:
        figures = (
            f"{s['up']['kbps']:7.2f} {s['down']['kbps']:7.2f} {s['total']['kbps']:7.2f} "
            f"{s['up']['pps']:5.1f}/{s['down']['pps']:<5.1f}"
        )
    frames = f"{r.get('frames_shown') or 0}/{r.get('frames_sent') or 0}"
    return (
        f"{clip:<10} {link:<9} {figures} {frames:>9} "
        f"{_f(lat.get('p50')):>7}/{_f(lat.get('p99')):<7} {_f(r.get('first_picture_s'), '.2f'):>6}"
    )


HEADER = (
    f"{'clip':<10} {'link':<9} {'up':>7} {'down':>7} {'total':>7} {'pps up/down':>11} "
    f"{'shown/sent':>9} {'lat p50/p99 ms':>15} {'first':>6}"
)


def details(r: dict[str, Any]) -> str:
    c = r["call"]
    drops = "/".join(str(r["qdisc"][d].get("drops", "-")) for d in ("up", "down"))
    resent = "/".join(str(r["tcp"][e].get("RetransSegs", "-")) for e in ("sender", "receiver"))
    s = r.get("steady")
    window = "" if s is None else f"steady {s['seconds']:.1f} s, mean packet "
    if s is not None:
        window += f"{s['up']['mean_packet']:.0f}/{s['down']['mean_packet']:.0f} B; "
    full = r.get("full_snapshot_s")
    line = (
        f"    {window}whole call {c['seconds']:.1f} s: up {c['up']['ip_bytes']} B in "
        f"{c['up']['packets']} packets, down {c['down']['ip_bytes']} B in {c['down']['packets']}; "
        f"snapshot in at {_f(r.get('snapshot_s'))} s"
        + ("" if full is None else f" (the full one after its draft at {full:.1f} s)")
        + f", frames from {_f(r.get('joined_s'))} s; "
        f"qdisc drops up/down {drops}, TCP resent sender/receiver {resent}"
    )
    sent, got = r["sender"].get("bytes_sent", {}), r["receiver"].get("bytes_received", {})
    if got.get("snapshot"):
        copies = sent.get("snapshot", 0) / got["snapshot"]
        line += f"; snapshot {got['snapshot']} B, served {copies:.0f}x"
    spare = r["receiver"].get("second_path", {})
    if spare.get("late_frames") or spare.get("copies"):
        line += (
            f"; second path: {spare['late_frames']} late frames, {spare.get('copies', 0)} copies "
            f"({got.get('spare', 0)} B)"
        )
    line += f"; receiver ended by {r['receiver'].get('ended_by', '-')}"
    if r.get("load"):
        line += f"; load {' -> '.join(f'{x:.1f}' for x in r['load'])}"
    if r.get("notes"):
        line += "\n    problems: " + "; ".join(r["notes"])
        errors = [e for e in r.get("output", {}).get("sender", "").splitlines() if "error" in e]
        line += "".join(f"\n    sender {e}" for e in errors[-1:])
    return line


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--input",
        action="append",
        metavar="CLIP",
        help="clip to send, repeatable (default: the bundled clip); e.g. carphone, "
        "/work/footage/carphone_qcif.avi (BENCHMARKS.md says where it comes from)",
    )
    p.add_argument("--seconds", type=float, default=20.0, help="steady window (default 20)")
    p.add_argument("--settle", type=float, default=3.0, help="after the snapshot, before it")
    p.add_argument(
        "--rate-kbit",
        action="append",
        metavar="R,...",
        help="link rates, repeatable or a comma list; none: unshaped (default none,48,24)",
    )
    p.add_argument("--sound", action="store_true", help="send the clip's sound too")
    p.add_argument("--plain", action="store_true", help="no CURVE (both ends --plain)")
    p.add_argument(
        "--max-kbps", type=float, metavar="N", help="the sender's --max-kbps (default: its own)"
    )
    p.add_argument("--json", metavar="OUT.json", help="write every run's figures")
    args = p.parse_args()
    # SIGTERM ends the runs as Ctrl-C does: the calls are stopped and the namespaces deleted.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    rates = _rates(args.rate_kbit or ["none,48,24"])
    reason = unavailable(shaping=any(r is not None for r in rates))
    if reason is not None:
        print(f"bench_wire: skipped ({reason})")
        return 0
    clips: list[Path | None] = [Path(c) for c in args.input] if args.input else [None]
    print(
        f"{'face and sound' if args.sound else 'face only (--no-sound)'}, "
        f"{'--plain' if args.plain else 'CURVE'}; kbit/s of IP "
        f"(headers counted, Ethernet's not) over {args.seconds:g} s steady, "
        f"{args.settle:g} s after the snapshot; first: s from offer to first picture"
    )
    print(HEADER)
    runs = []
    for clip in clips:
        name = "bundled" if clip is None or clip.stem == "demo_clip" else clip.stem.split("_")[0]
        for rate in rates:
            budget = () if args.max_kbps is None else ("--max-kbps", f"{args.max_kbps:g}")
            r = measure_call(
                clip, args.seconds, rate, args.sound, budget,
                settle_s=args.settle, encrypted=not args.plain,
            )  # fmt: skip
            runs.append(r)
            print(row(name, r))
            print(details(r), flush=True)
            if args.json:  # after each run: a later failure keeps what was measured
                Path(args.json).write_text(json.dumps(runs, indent=1) + "\n")
    example = runs[0]["commands"]
    print("commands (first run):\n  " + " ".join(example["receive"]))
    print("  " + " ".join(example["send"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
