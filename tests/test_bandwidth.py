"""facewire bandwidth: the command on a short real clip, its JSON, the codecs' figures against
an independent measurement (tests/independent_codecs.py), our call on the wire (counted on a
link where namespaces can be made, else said to be unknown), bad input, the rate-quality
maths."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from independent_codecs import measure

from facewire import bandwidth, cli, codecs, onlink
from facewire.quality import read_frames
from facewire.ratequality import envelope, quality_at, rate_for
from facewire.rdplot import plot
from facewire.rdreport import break_even, print_report
from facewire.sender.capture import demo_clip_path

FRAMES = 8
RATES = (24, 64)
SIZE = (640, 480)
NO_LINK = onlink.unavailable()


@pytest.fixture(scope="module")
def clip() -> Path:
    """The bundled clip (640x480, with a speech track beside it), of which the tests use the
    first few frames."""
    return demo_clip_path()


@pytest.fixture(scope="module")
def result(clip: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One run of the command: the three codecs, two rates, two rungs, and our call (on a link
    too where namespaces can be made); what it printed is under "_printed"."""
    out = tmp_path_factory.mktemp("out")
    rates = ",".join(map(str, RATES))
    argv = ["bandwidth", "--input", str(clip), "--frames", str(FRAMES), "--rates", rates]
    argv += ["--ladder", "1,0.5", "--json", str(out / "rd.json"), "--plot", str(out / "rd.png")]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert cli.main(argv) == 0
    text = (out / "rd.json").read_text()
    assert "NaN" not in text and "Infinity" not in text  # standard JSON
    data: dict[str, Any] = json.loads(text)
    data["_png"] = str(out / "rd.png")
    data["_printed"] = printed.getvalue()
    return data


def test_json_holds_the_call_and_every_operating_point(result: dict[str, Any]) -> None:
    assert result["schema"] == 2
    assert (result["width"], result["height"], result["frames"]) == (*SIZE, FRAMES)
    assert result["untracked"] == 0
    settings = result["settings"]
    assert settings["rates_kbps"] == list(RATES)
    assert [(r["width"], r["height"]) for r in settings["ladder"]] == [(640, 480), (320, 240)]
    assert set(settings["codecs"]) == {"h264", "vp9", "av1"}
    assert settings["codecs"]["h264"]["options"]["tune"] == "zerolatency"
    assert settings["codecs"]["vp9"]["options"]["lag-in-frames"] == "0"

    points = result["points"]
    assert len(points) == 3 * 2 * len(RATES)
    duration = FRAMES / result["fps"]
    for p in points:
        assert p["frames"] == FRAMES and p["dropped"] == 0 and p["keyframes"] == 1
        kbps = p["kbps"]
        # The achieved rate is the bitstream's bytes over the clip, not the target.
        assert kbps["payload"]["amortised"] == pytest.approx(p["bytes"] * 8 / duration / 1000)
        steady = (p["bytes"] - p["first_packet_bytes"]) * 8 / duration / 1000
        assert kbps["payload"]["steady"] == pytest.approx(steady)
        assert kbps["wire"]["amortised"] > kbps["payload"]["amortised"]
        for region in ("face", "head", "frame"):
            assert 0.2 < p["ssim"][region] < 1.0, p
            assert 15 < p["psnr_db"][region] < 60, p
    # A real codec run: each codec at each rung looks better at the higher rate.
    for name in ("h264", "vp9", "av1"):
        for width in (640, 320):
            lo, hi = (
                next(
                    p
                    for p in points
                    if p["codec"] == name and p["width"] == width and p["target_kbps"] == r
                )
                for r in RATES
            )
            assert hi["bytes"] > lo["bytes"] and hi["ssim"]["face"] > lo["ssim"]["face"]

    # Payload, amortised and steady; on the wire steady only, and only where ours was counted.
    counted = result["ours"]["wire"]["source"] == "measured"
    assert len(result["matches"]) == 3 * 2 * (2 + counted)
    for m in result["matches"]:
        assert m["region"] in ("face", "head") and m["accounting"] in ("amortised", "steady")
        assert (m["level"], m["accounting"]) in (
            ("payload", "amortised"),
            ("payload", "steady"),
            ("wire", "steady"),
        )
        assert m["bound"] in ("=", "<=", ">")
        assert m["times_ours"] == pytest.approx(m["codec_kbps"] / m["our_kbps"])
        assert m["our_kbps"] == result["ours"]["kbps"][m["level"]][m["accounting"]]
        assert m["our_ssim"] == result["ours"]["quality"]["ssim"][m["region"]]
    assert {(b["codec"], b["region"]) for b in result["break_even"]} == {
        (c, r) for c in ("h264", "vp9", "av1") for r in ("face", "head")
    }


def test_our_call_per_channel_payload(result: dict[str, Any]) -> None:
    ours = result["ours"]
    call = ours["call"]  # a frame read late on a busy machine is left out, as a camera does
    assert call["frames_in"] + call["frames_dropped"] == FRAMES and call["encrypted"] is True
    duration = FRAMES / result["fps"]
    payload = ours["channels_kbps"]["payload"]
    assert set(ours["channels_kbps"]) == {"payload"}  # no per-channel model of the wire
    for channel, nbytes in ours["bytes"].items():
        assert payload[channel] == pytest.approx(nbytes * 8 / duration / 1000)
    assert ours["bytes"]["snapshot"] > 1000 and ours["messages"]["snapshot"] >= 1
    assert ours["bytes"]["audio"] > 0, "the bundled clip's speech goes with the call"
    # The first frame's keyframe, then a packet only for a frame where something moved by a
    # step (docs/protocol.md 5.5): the bundled clip's face is nearly still in these eight, and
    # four or five of them go.
    assert 1 <= ours["messages"]["geometry"] <= FRAMES
    # The totals are the picture's: the sound (the bundled clip has a speech track) is left
    # out, as the codecs compared carry none.
    picture = sum(v for ch, v in payload.items() if ch != "audio")
    assert ours["kbps"]["payload"]["amortised"] == pytest.approx(picture)
    assert ours["kbps"]["payload"]["steady"] == pytest.approx(picture - payload["snapshot"])
    for region in ("face", "head", "frame"):
        assert 0.3 < ours["quality"]["ssim"][region] < 1.0
        assert ours["quality"]["ssim"][region] < ours["recording_ceiling"]["ssim"][region] <= 1
    assert ours["quality"]["held"] == 0


@pytest.mark.skipif(NO_LINK is not None, reason=f"no link: {NO_LINK}")
def test_our_call_on_the_wire_is_counted_on_a_link(result: dict[str, Any]) -> None:
    """Where namespaces can be made, our wire rate is what a veth link counted: both ways,
    packets and bytes, over a window of the clip's first frames looping."""
    wire = result["ours"]["wire"]
    assert wire["source"] == "measured", wire
    assert wire["link"] == "veth, unshaped" and wire["sent"] == f"its first {FRAMES} frames"
    assert wire["seconds"] >= bandwidth.MIN_LINK_WINDOW_S - 0.5
    assert wire["frames_shown"] > 0 and wire["frames_sent"] > 0
    kbps, pps = wire["kbps"], wire["pps"]
    for d in ("up", "down"):
        assert kbps[d] > 0 and pps[d] > 0
        # Packets of IP: at least the smallest (a UDP header and a datagram's 12 bytes), at
        # most a datagram of 1200 bytes with its headers.
        assert 28 + 12 <= wire["mean_packet"][d] <= 1200 + 28
    assert kbps["total"] == pytest.approx(kbps["up"] + kbps["down"])
    assert pps["total"] == pytest.approx(pps["up"] + pps["down"])
    # The wire comparison takes ours sender to receiver, as the codecs' SRTP model counts.
    assert result["ours"]["kbps"]["wire"] == {"steady": kbps["up"]}
    printed = result["_printed"]
    assert "our call on the wire, steady: measured on a veth link" in printed
    for name in ("up (sender to receiver)", "down (receiver to sender)", "both"):
        line = next(x for x in printed.splitlines() if x.strip().startswith(name))
        assert "kbit/s" in line and "packets/s" in line
    assert "unknown" not in printed
    assert "on the wire, steady, sender to receiver (ours" in printed


def test_without_a_link_our_wire_rate_is_unknown(
    result: dict[str, Any], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, clip: Path
) -> None:
    """Where no link can be made the wire rate is said to be unknown, with why; no model
    stands in for it, the comparison on the wire is left out and the plot says so."""
    monkeypatch.setattr(onlink, "unavailable", lambda *a: "network namespaces need root")
    wire = bandwidth.our_wire(clip, FRAMES, result["fps"], False, tmp_path)
    assert wire == {
        "source": "unknown",
        "why": "without a link to count on: network namespaces need root",
    }
    unknown = copy.deepcopy(result)
    unknown["ours"]["wire"] = wire
    unknown["ours"]["kbps"].pop("wire", None)
    unknown["matches"] = [m for m in unknown["matches"] if m["level"] == "payload"]
    specs = [codecs.codec_spec(n) for n in ("h264", "vp9", "av1")]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        print_report(unknown, specs)
    lines = printed.getvalue().splitlines()
    assert (
        "our call on the wire: unknown, without a link to count on: network namespaces need "
        "root (no model stands in for a count: facewire/wire.py says why)"
    ) in lines
    assert not any("measured on a veth link" in x or "modelled" in x for x in lines)
    assert any(x.startswith("on the wire: no comparison, our rate is unknown") for x in lines)
    # The codecs' wire rates stay, labelled as a model.
    assert any("a model: over SRTP/UDP" in x for x in lines)
    assert sum("SRTP" in x and "target" in x for x in lines) == 3 * 2 * len(RATES)
    plot(unknown, tmp_path / "unknown.png")
    image = cv2.imread(str(tmp_path / "unknown.png"))
    assert image is not None and image.shape == (900, 1800, 3)


def test_first_frames_are_copied_without_loss(clip: Path, tmp_path: Path) -> None:
    """What the sender loops on the link when --frames takes part of the clip."""
    path = bandwidth._first_frames(clip, 3, 30.0, tmp_path)
    copied = list(read_frames(path))
    assert len(copied) == 3
    for a, b in zip(read_frames(clip), copied, strict=False):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("codec", ["h264", "vp9", "av1"])
def test_codec_figures_agree_with_an_independent_measurement(
    clip: Path, result: dict[str, Any], codec: str
) -> None:
    """The same settings through PyAV's container API, scored by scikit-image (full rung)."""
    pytest.importorskip("skimage")
    tool = next(
        p
        for p in result["points"]
        if p["codec"] == codec and p["scale"] == 1 and p["target_kbps"] == RATES[0]
    )
    theirs = measure(clip, codec, RATES[0], FRAMES)
    assert theirs["kbps"] == pytest.approx(tool["kbps"]["payload"]["amortised"], rel=0.01)
    for region in ("face", "head", "frame"):
        assert abs(theirs["ssim"][region] - tool["ssim"][region]) < 0.01, region


@pytest.mark.parametrize("codec, scale", [("h264", 1.0), ("vp9", 0.5)])
def test_codec_figures_agree_with_the_ffmpeg_program(
    clip: Path, result: dict[str, Any], codec: str, scale: float
) -> None:
    """The ffmpeg program imageio-ffmpeg ships (another FFmpeg build) with the same settings.

    AV1 is left out: that build's SVT-AV1 is another version (see BENCHMARKS.md).
    """
    pytest.importorskip("imageio_ffmpeg")
    tool = next(
        p
        for p in result["points"]
        if p["codec"] == codec and p["scale"] == scale and p["target_kbps"] == RATES[1]
    )
    theirs = measure(clip, codec, RATES[1], FRAMES, scale, backend="ffmpeg")
    assert theirs["kbps"] == pytest.approx(tool["kbps"]["payload"]["amortised"], rel=0.02)
    for region in ("face", "head", "frame"):
        assert abs(theirs["ssim"][region] - tool["ssim"][region]) < 0.01, region


def test_plot_is_a_picture_with_every_codec(result: dict[str, Any]) -> None:
    """Four payload panels and, on the right, the one on the wire."""
    image = cv2.imread(result["_png"])
    assert image is not None and image.shape == (900, 1800, 3)
    wire_panel = image[:, 1250:]
    # Each codec's line colour and our black star are drawn, in the wire panel too.
    for bgr in ((180, 119, 31), (44, 160, 44), (40, 39, 214)):
        near = np.abs(image.astype(int) - bgr).sum(axis=2) < 30
        assert near[:, :1200].sum() > 200 and near[:, 1250:].sum() > 20, bgr
    assert (image[:, :1200].sum(axis=2) < 30).sum() > 500
    if result["ours"]["wire"]["source"] == "measured":
        assert (wire_panel.sum(axis=2) < 30).sum() > 300


def test_dropped_frames_are_held(clip: Path) -> None:
    """A frame no packet carries decodes as None (the metric holds the one before)."""
    frames = [f for f, _ in zip(read_frames(clip), range(4), strict=False)]
    spec = codecs.codec_spec("h264")
    encoded = codecs.encode(frames, spec, 200_000, SIZE, 30.0)
    assert encoded.pts == [0, 1, 2, 3]
    # Stamp the same packets as frames 0, 2, 3, 5 of six: 1 and 4 were dropped.
    encoded.pts, encoded.frames = [0, 2, 3, 5], 6
    out = list(codecs.decode(encoded, spec, SIZE))
    assert [f is None for f in out] == [False, True, False, False, True, False]
    assert out[0] is not None and out[0].shape == (480, 640, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--input", "missing.avi"], "cannot open video missing.avi: no such file"),
        (["--codecs", "h264,h265"], "unknown codec 'h265' (known: h264, vp9, av1)"),
        (["--rates", "8,abc"], "--rates: 'abc' is not a number (in '8,abc')"),
        (["--rates", "8,0"], "--rates: 0 is not a positive number"),
        (["--rates", ""], "--rates: '' is not a number"),
        (["--ladder", "1,2"], "--ladder: 2 is larger than the input (at most 1)"),
        (["--frames", "0"], "--frames must be at least 1, got 0"),
        (["--json", "/no/such/folder/x.json"], "--json: folder /no/such/folder does not exist"),
    ],
)
def test_bad_input_is_one_line(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["bandwidth", *args]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("facewire: error: ") and message in err[0], err


def test_bad_input_exits_non_zero_from_the_shell(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "facewire", "bandwidth", "--input", str(tmp_path / "no.mp4")],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        check=False,
    )
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"facewire: error: cannot open video {tmp_path / 'no.mp4'}: no such file"
    ]


def test_envelope_keeps_the_best_quality_at_each_rate() -> None:
    pts = [(10, 0.5), (12, 0.45), (20, 0.7), (20, 0.72), (30, 0.69), (40, 0.8), (50, math.nan)]
    pts.append((60, None))  # type: ignore[arg-type]  # nan as the JSON holds it
    assert envelope(pts) == [(10, 0.5), (20, 0.72), (40, 0.8)]


def test_rate_for_interpolates_in_log_rate() -> None:
    curve = [(10.0, 0.5), (40.0, 0.7)]
    need = rate_for(curve, 0.6)
    assert need is not None and need.bound == "=" and need.rate == pytest.approx(20.0)
    assert need.times(5.0) == pytest.approx(4.0)
    assert quality_at(curve, 20.0) == pytest.approx(0.6)
    assert rate_for(curve, 0.4) == type(need)(10.0, "<=")
    assert rate_for(curve, 0.9) == type(need)(40.0, ">")
    assert math.isnan(quality_at(curve, 5.0)) and math.isnan(quality_at(curve, 41.0))
    assert rate_for([], 0.5) is None


def test_break_even_call_length() -> None:
    """Our start-up is 80 kbit (25 - 5 kbit/s over 4 s), the codec's 8: at 15 kbit/s steady
    against our 5 the difference is paid back after 7.2 s."""

    result: dict[str, Any] = {
        "frames": 120,
        "fps": 30.0,
        "ours": {"kbps": {"payload": {"amortised": 25.0, "steady": 5.0}}},
        "matches": [
            {
                "codec": "av1",
                "region": "face",
                "accounting": "amortised",
                "codec_kbps": 17.0,
                "bound": "=",
            },
            {
                "codec": "av1",
                "region": "face",
                "accounting": "steady",
                "codec_kbps": 15.0,
                "bound": "=",
            },
            {
                "codec": "vp9",
                "region": "face",
                "accounting": "amortised",
                "codec_kbps": 64.0,
                "bound": ">",
            },
            {
                "codec": "vp9",
                "region": "face",
                "accounting": "steady",
                "codec_kbps": 60.0,
                "bound": ">",
            },
            {
                "codec": "h264",
                "region": "face",
                "accounting": "amortised",
                "codec_kbps": 6.0,
                "bound": "=",
            },
            {
                "codec": "h264",
                "region": "face",
                "accounting": "steady",
                "codec_kbps": 4.0,
                "bound": "=",
            },
        ],
    }
    got = {b["codec"]: b["seconds"] for b in break_even(result)}
    assert got["av1"] == pytest.approx(7.2)
    assert got["vp9"] is None  # outside the rates measured
    assert got["h264"] is None  # cheaper than ours in steady state: never
