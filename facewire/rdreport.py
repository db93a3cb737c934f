"""What ``facewire bandwidth`` concludes: the rate each codec needs for our quality, printed.

Works on the result as the JSON holds it (``facewire bandwidth --json``).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from typing import Any

from facewire.codecs import CodecSpec
from facewire.quality import REGIONS
from facewire.ratequality import envelope, quality_at, rate_for

logger = logging.getLogger(__name__)

#: Quality regions compared in the final table and the plot.
COMPARED = ("face", "head")
ACCOUNTING = ("amortised", "steady")
#: Rates compared: the payload (our messages, the codecs' bitstream), and IP packets sender
#: to receiver, steady only (ours counted on a link, facewire/onlink.py; theirs a model, over
#: SRTP: facewire.wire).
LEVELS = ("payload", "wire")


def codec_curve(
    points: Sequence[dict[str, Any]],
    codec: str,
    region: str,
    accounting: str,
    level: str = "payload",
) -> list[tuple[float, float]]:
    """A codec's envelope over its ladder: (kbit/s at ``level``, SSIM of ``region``)."""
    return envelope(
        (p["kbps"][level][accounting], p["ssim"][region]) for p in points if p["codec"] == codec
    )


def matches(
    ours: dict[str, Any], points: Sequence[dict[str, Any]], names: Sequence[str]
) -> list[dict[str, Any]]:
    """For each codec, region, accounting and level where our rate is known: the rate it needs
    to match our SSIM, that rate over ours, and its SSIM at our rate."""
    out = []
    for codec, region, level, accounting in itertools.product(names, COMPARED, LEVELS, ACCOUNTING):
        our_rate = ours["kbps"].get(level, {}).get(accounting)
        if our_rate is None:
            continue
        our_ssim = ours["quality"]["ssim"][region]
        curve = codec_curve(points, codec, region, accounting, level)
        need = rate_for(curve, our_ssim)
        out.append(
            {
                "codec": codec,
                "region": region,
                "accounting": accounting,
                "level": level,
                "our_kbps": our_rate,
                "our_ssim": our_ssim,
                "codec_kbps": None if need is None else need.rate,
                "bound": None if need is None else need.bound,
                "times_ours": None if need is None else need.times(our_rate),
                "codec_ssim_at_our_rate": quality_at(curve, our_rate),
            }
        )
    return out


def break_even(result: dict[str, Any]) -> list[dict[str, Any]]:
    """For each codec and region: the call length (s) from which ours costs fewer bits than
    the codec at our SSIM, start-up (our snapshot, its key frame) included.

    Our start-up is (amortised - steady) x the clip's duration; the codec's is the same
    difference of the rates it needs (each interpolated on its curve). Beyond the break-even
    length the steady rates decide. None where a needed rate is outside the rates measured,
    or where the codec's steady rate is below ours (it never costs more).
    """
    duration = result["frames"] / result["fps"]
    ours = result["ours"]["kbps"]["payload"]
    our_startup = (ours["amortised"] - ours["steady"]) * duration
    by_key = {
        (m["codec"], m["region"], m["accounting"]): m
        for m in result["matches"]
        if m.get("level", "payload") == "payload"
    }
    out = []
    for codec, region in sorted({(m["codec"], m["region"]) for m in result["matches"]}):
        a, s = by_key[codec, region, "amortised"], by_key[codec, region, "steady"]
        seconds = None
        if a["bound"] == s["bound"] == "=" and s["codec_kbps"] > ours["steady"]:
            startup = max(0.0, (a["codec_kbps"] - s["codec_kbps"]) * duration)
            seconds = max(0.0, (our_startup - startup) / (s["codec_kbps"] - ours["steady"]))
        out.append({"codec": codec, "region": region, "seconds": seconds})
    return out


def _f(value: float | None, digits: int = 1) -> str:
    if value is None or math.isnan(value):
        return "-"
    return f"{value:.{digits}f}"


def print_report(result: dict[str, Any], specs: Sequence[CodecSpec]) -> None:
    ours = result["ours"]
    print(
        f"input {result['input']}: {result['frames']} frames, {result['width']}x"
        f"{result['height']} at {result['fps']:.2f} fps ({result['untracked']} without a face)"
    )
    payload = ours["channels_kbps"]["payload"]
    print(
        "our call, kbit/s   "
        + "".join(f"{c:>10}" for c in payload)
        + "     total    steady  (totals: the picture, sound left out)"
    )
    tot = ours["kbps"]["payload"]
    print(
        f"  {'payload':<16}"
        + "".join(f"{_f(v, 2):>10}" for v in payload.values())
        + f"{_f(tot['amortised'], 2):>10}{_f(tot['steady'], 2):>10}"
    )
    print_wire(ours["wire"])
    call = ours["call"]
    print(
        f"our call: {call['frames_in']} frames in, {call['frames_out']} out, "
        f"{call['frames_held']} of them the picture before held by the receiver (a paced call: "
        "a loaded machine or a late packet makes it hold)"
    )
    q, ceiling = ours["quality"], ours["recording_ceiling"]
    print(
        "our call, SSIM / PSNR dB: "
        + ", ".join(f"{r} {q['ssim'][r]:.3f} / {q['psnr_db'][r]:.1f}" for r in REGIONS)
        + f" (the recording alone: face {ceiling['ssim']['face']:.3f})"
    )
    print(
        "\ncodec operating points (payload kbit/s amortised / steady; on the wire, steady, a "
        "model: over SRTP/UDP; SSIM face, head, frame):"
    )
    for spec in specs:
        print(f"  {spec.label}")
        for p in (p for p in result["points"] if p["codec"] == spec.name):
            k = p["kbps"]["payload"]
            s = p["ssim"]
            print(
                f"    {p['width']:>4}x{p['height']:<4} target {p['target_kbps']:>6g}: "
                f"{k['amortised']:7.1f} / {k['steady']:7.1f}   "
                f"SRTP {p['kbps']['wire']['steady']:7.1f}   "
                f"{s['face']:.3f}  {s['head']:.3f}  {s['frame']:.3f}"
                + (f"  ({p['dropped']} dropped)" if p["dropped"] else "")
            )
    print(
        "\nrate each codec needs for our SSIM (best ladder rung at each rate; amortised: the "
        "whole clip with our snapshot and their key frame, steady: after them)"
    )
    print(
        f"  {'codec':<6}{'region':<7}{'our SSIM':>9}  {'amortised kbit/s':>17} {'x ours':>7}  "
        f"{'steady kbit/s':>14} {'x ours':>7}   its SSIM at our rate (amortised / steady)"
    )
    by = {
        (m["codec"], m["region"], m.get("level", "payload"), m["accounting"]): m
        for m in result["matches"]
    }
    for spec in specs:
        for region in COMPARED:
            a, s = (
                by[spec.name, region, "payload", "amortised"],
                by[spec.name, region, "payload", "steady"],
            )
            print(
                f"  {spec.name:<6}{region:<7}{a['our_ssim']:>9.3f}  "
                f"{_need(a):>17} {_times(a):>7}  {_need(s):>14} {_times(s):>7}   "
                f"{_f(a['codec_ssim_at_our_rate'], 3)} / {_f(s['codec_ssim_at_our_rate'], 3)}"
            )
    a_rate, s_rate = ours["kbps"]["payload"]["amortised"], ours["kbps"]["payload"]["steady"]
    for region in COMPARED:
        rows = [b for b in result["break_even"] if b["region"] == region]
        print(
            f"  a call costs fewer bits with facewire than at the same {region} SSIM with "
            + ", ".join(f"{b['codec']} after {_f(b['seconds'])} s" for b in rows)
        )
    print(
        f"  (ours: {a_rate:.1f} kbit/s amortised, {s_rate:.1f} steady; "
        "- : outside the rates measured)"
    )
    wire_rate = ours["kbps"].get("wire", {}).get("steady")
    if wire_rate is None:
        print(
            "\non the wire: no comparison, our rate is unknown (above); theirs, a model over "
            "SRTP/UDP, is in the codec operating points"
        )
        return
    print(
        f"\non the wire, steady, sender to receiver (ours {wire_rate:.2f} kbit/s of IP packets, "
        "measured on a veth link; theirs modelled over SRTP/UDP, RTCP not counted; our SSIM "
        "from the call above): rate each codec needs for our SSIM, x ours"
    )
    for region in COMPARED:
        cells = []
        for spec in specs:
            m = by.get((spec.name, region, "wire", "steady"))
            if m is not None:
                cells.append(f"{spec.name} {_need(m)} ({_times(m)})")
        print(f"  {region}: " + ", ".join(cells))


def print_wire(wire: dict[str, Any]) -> None:
    """Our call on the wire: what a link counted (facewire.bandwidth.our_wire), or why not."""
    if wire["source"] != "measured":
        print(
            f"our call on the wire: unknown, {wire['why']} (no model stands in for a count: "
            "facewire/wire.py says why)"
        )
        return
    print(
        f"our call on the wire, steady: measured on a veth link between two network namespaces "
        f"({wire['link'].removeprefix('veth, ')}), {wire['sent']} looping, face only; "
        f"{wire['seconds']:.1f} s from {wire['settle_s']:g} s after the full snapshot, "
        f"{wire['frames_shown']} frames shown of {wire['frames_sent']} sent; IP headers "
        "counted, Ethernet's not"
    )
    names = {"up": "up (sender to receiver)", "down": "down (receiver to sender)", "total": "both"}
    for d, name in names.items():
        print(
            f"  {name:<26}{wire['kbps'][d]:8.2f} kbit/s {wire['pps'][d]:6.1f} packets/s  "
            f"(mean {wire['mean_packet'][d]:.0f} B)"
        )
    for note in wire.get("notes") or []:
        print(f"  (the call on the link: {note})")


def _need(m: dict[str, Any]) -> str:
    if m["codec_kbps"] is None:
        return "-"
    prefix = {"=": "", "<=": "<= ", ">": "> "}[m["bound"]]
    return f"{prefix}{m['codec_kbps']:.1f}"


def _times(m: dict[str, Any]) -> str:
    if m["times_ours"] is None:
        return "-"
    prefix = {"=": "", "<=": "<=", ">": ">"}[m["bound"]]
    return f"{prefix}{m['times_ours']:.2f}"
