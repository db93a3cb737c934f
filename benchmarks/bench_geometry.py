"""Geometry bit rate and the error its coding adds, on a clip (no network, no render).

Usage: python benchmarks/bench_geometry.py [--input CLIP] [--error-px E ...] [--frames N]
       [--no-smoothing] [--geometry-kbps KBPS]

Runs the sender's encoder over every frame and decodes every packet as the receiver would.
Frames are stamped with their nominal capture times (frame index / fps), as a call paced at
the clip's frame rate stamps them; reading as fast as possible would make every frame look
33 ms early and cost a capture-time residual per packet that no call pays. Prints, at the
clip's frame rate:
- payload: bytes of the frame packets (key and delta) as ZeroMQ carries them, in kbit/s, split
  into packet headers and range-coded bodies, with the keyframes and the frames that needed
  no packet, and of those the frames the rate cap held back (``--geometry-kbps``, default
  the sender's 1.5; 0: no cap);
- where the body bits go: the information coded per channel in delta frames, the delta frames'
  frame step and capture time, whole keyframe bodies, and what rounding bodies up to whole
  bytes adds;
- on the wire: the same packets with ZMTP framing (2 bytes) and TCP/IPv4 headers (52 bytes
  with timestamps) each, plus one 52-byte ACK per packet back, as a user on a network sees it;
- the error quantisation adds: vertices rebuilt from the decoded values against vertices
  rebuilt from the values the sender quantised (after its smoothing), in mm (model space,
  expression only) and in pixels at the call's size (RMS, 99th percentile, max);
- how far the rebuilt face is from the tracker's raw measurement (smoothing plus
  quantisation), in pixels.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from facewire.models.face_channels import DEFAULT_ERROR_PX, LIPS, WIRE, pose_from_channels
from facewire.protocol.channels import ChannelDecoder, ChannelSpec
from facewire.protocol.packets import KeyFrame, decode
from facewire.protocol.quant import dequantise
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder
from facewire.sender.rate_cap import GEOMETRY_KBPS

ZMTP_BYTES = 2
TCP_IP_BYTES = 52


def _stats(prefix: str, x: np.ndarray) -> dict[str, float]:
    return {
        f"{prefix}_rms": float(np.sqrt((x**2).mean())),
        f"{prefix}_p99": float(np.percentile(x, 99)),
        f"{prefix}_max": float(x.max()),
    }


def measure(
    path: Path,
    error_px: float,
    frames: int | None,
    smoothing: bool = True,
    geometry_kbps: float = GEOMETRY_KBPS,
) -> dict[str, object]:
    with VideoSource(path) as video:
        fps = video.fps
        encoder = FaceEncoder(
            video.width,
            video.height,
            fps,
            error_px=error_px,
            smoothing=smoothing,
            geometry_kbps=geometry_kbps or None,
        )
        it = (
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / fps))
            for f in video.frames(limit=frames)
        )
        snapshot = None
        for frame in it:
            snapshot = encoder.start(frame)
            if snapshot is not None:
                break
        assert snapshot is not None, f"no face in {path}"
        specs = [ChannelSpec(*c) for c in snapshot.channels]
        decoder = ChannelDecoder(specs, round(1e6 / fps))
        wires = encoder.wires
        assert wires is not None
        sizes, heads, keys, n = [], [], 0, 0
        err_cm: list[np.ndarray] = []
        err_px: list[np.ndarray] = []
        raw_px: list[np.ndarray] = []
        shown = None

        mouth = encoder.mouth
        assert mouth is not None

        def image(values: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
            model = wires.deform(encoder.rest_params + encoder.basis.params(values[WIRE]))
            model = model + mouth.displacement(values[LIPS])
            return model, pose_from_channels(values).apply(model)[:, :2]

        for frame in it:
            n += 1
            result = encoder.analyse(frame.image)
            packet = encoder.encode_analysed(frame, result)
            if packet is not None:
                data = bytes(packet)
                sizes.append(len(data))
                heads.append(len(data) - len(packet.body))
                keys += isinstance(packet, KeyFrame)
                shown = decoder.decode(decode(data))
            if result is None or shown is None or encoder.intended is None:
                continue
            floats = {s.name: dequantise(shown.values[s.name], s.step) for s in specs}
            q_model, q_image = image(floats)
            meant_model, meant_image = image(encoder.intended)
            _, raw_image = image(encoder.channel_values(*result, encoder.points))
            err_cm.append(np.linalg.norm(q_model - meant_model, axis=1))
            err_px.append(np.linalg.norm(q_image - meant_image, axis=1))
            raw_px.append(np.linalg.norm(q_image - raw_image, axis=1))
    duration = n / fps

    def kbps(nbytes: float) -> float:
        return nbytes * 8 / duration / 1000

    body_bytes = sum(sizes) - sum(heads)
    coded = {k: v / 8 for k, v in encoder.coded_bits.items()}
    coded["byte rounding"] = body_bytes - sum(coded.values())
    mm, px = np.concatenate(err_cm) * 10, np.concatenate(err_px)
    return {
        "frames": n,
        "payload_kbps": kbps(sum(sizes)),
        "header_kbps": kbps(sum(heads)),
        "body_kbps": kbps(body_bytes),
        "bodies_kbps": {k: kbps(v) for k, v in coded.items()},
        "keyframes": keys,
        "skipped": n - len(sizes),
        "wire_kbps": kbps(sum(sizes) + len(sizes) * (ZMTP_BYTES + TCP_IP_BYTES)),
        "ack_kbps": kbps(len(sizes) * TCP_IP_BYTES),
        **_stats("mm", mm),
        **_stats("px", px),
        **_stats("raw_px", np.concatenate(raw_px)),
        "size": f"{snapshot.width}x{snapshot.height}",
        "budget_px": encoder.budget_px,
        "held": 0 if encoder.rate_cap is None else encoder.rate_cap.held,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=demo_clip_path())
    parser.add_argument("--error-px", type=float, nargs="+", default=[DEFAULT_ERROR_PX])
    parser.add_argument("--frames", type=int)
    parser.add_argument(
        "--no-smoothing", action="store_true", help="quantise the tracker's raw values"
    )
    parser.add_argument("--geometry-kbps", type=float, default=GEOMETRY_KBPS)
    args = parser.parse_args()
    for e in args.error_px:
        r = measure(
            args.input, e, args.frames, not args.no_smoothing, geometry_kbps=args.geometry_kbps
        )
        smoothing = "no smoothing" if args.no_smoothing else "smoothed"
        print(
            f"{args.input.name} {r['size']}, error budget {e} px/channel (this face: "
            f"{r['budget_px']:.3f} px), {smoothing}, "
            f"{r['frames']} frames: payload {r['payload_kbps']:.2f} kbit/s (headers "
            f"{r['header_kbps']:.2f}, bodies {r['body_kbps']:.2f}; {r['keyframes']} keyframes, "
            f"{r['skipped']} frames without a packet, {r['held']} of them held back by the "
            f"rate cap); on the wire {r['wire_kbps']:.1f} kbit/s "
            f"+ {r['ack_kbps']:.1f} kbit/s of ACKs back"
        )
        bodies = r["bodies_kbps"]
        assert isinstance(bodies, dict)
        print("  bodies, kbit/s: " + ", ".join(f"{k} {v:.3f}" for k, v in bodies.items()))
        print(
            f"  quantisation error: {r['mm_rms']:.3f} mm RMS, p99 {r['mm_p99']:.3f}, "
            f"max {r['mm_max']:.3f} mm; {r['px_rms']:.3f} px RMS, p99 {r['px_p99']:.3f}, "
            f"max {r['px_max']:.3f} px"
        )
        print(
            f"  rebuilt against the raw tracking (smoothing + quantisation): "
            f"{r['raw_px_rms']:.3f} px RMS, p99 {r['raw_px_p99']:.3f}, max {r['raw_px_max']:.3f} px"
        )


if __name__ == "__main__":
    main()
