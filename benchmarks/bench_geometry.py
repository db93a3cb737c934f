"""Geometry bit rate and the error its quantisation adds, on a clip (no network, no render).

Usage: python benchmarks/bench_geometry.py [--input CLIP] [--error-px E] [--frames N]

Runs the sender's encoder over every frame and decodes every packet as the receiver would.
Prints, at the clip's frame rate:
- payload: bytes of the frame packets (key and delta) as ZeroMQ carries them, in kbit/s, split
  into packet headers and range-coded bodies, with the share of keyframes and of frames that
  needed no packet;
- on the wire: the same packets with ZMTP framing (2 bytes) and TCP/IPv4 headers (52 bytes
  with timestamps) each, plus one 52-byte ACK per packet back, as a user on a network sees it;
- the error quantisation adds: vertices rebuilt from the decoded values against vertices
  rebuilt from the unquantised parameters, in mm (model space) and in pixels at the call's
  size (RMS, 99th percentile, max).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from models.face_channels import WIRE, pose_from_channels
from protocol.channels import ChannelDecoder, ChannelSpec
from protocol.packets import KeyFrame, decode
from protocol.quant import dequantise
from sender.capture import VideoSource, demo_clip_path
from sender.encoder import FaceEncoder

ZMTP_BYTES = 2
TCP_IP_BYTES = 52


def measure(path: Path, error_px: float, frames: int | None) -> dict[str, float]:
    with VideoSource(path) as video:
        encoder = FaceEncoder(video.width, video.height, video.fps, error_px=error_px)
        it = video.frames(limit=frames)
        snapshot = None
        for frame in it:
            snapshot = encoder.start(frame)
            if snapshot is not None:
                break
        assert snapshot is not None, f"no face in {path}"
        specs = [ChannelSpec(*c) for c in snapshot.channels]
        decoder = ChannelDecoder(specs, round(1e6 / video.fps))
        wires = encoder.wires
        assert wires is not None
        sizes, heads, keys, n = [], [], 0, 0
        err_cm: list[np.ndarray] = []
        err_px: list[np.ndarray] = []
        shown = None
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
            if result is None or shown is None:
                continue
            pose, params = result
            floats = {s.name: dequantise(shown.values[s.name], s.step) for s in specs}
            q_pose = pose_from_channels(floats)
            q_model = wires.deform(encoder.rest_params + encoder.basis.params(floats[WIRE]))
            fit_model = wires.deform(
                encoder.rest_params + encoder.basis.params(encoder.projected(params))
            )
            err_cm.append(np.linalg.norm(q_model - fit_model, axis=1))
            err_px.append(
                np.linalg.norm((q_pose.apply(q_model) - pose.apply(fit_model))[:, :2], axis=1)
            )
        fps = video.fps
    duration = n / fps
    payload = sum(sizes) * 8 / duration / 1000
    head = sum(heads) * 8 / duration / 1000
    wire = (sum(sizes) + len(sizes) * (ZMTP_BYTES + TCP_IP_BYTES)) * 8 / duration / 1000
    acks = len(sizes) * TCP_IP_BYTES * 8 / duration / 1000
    mm, px = np.concatenate(err_cm) * 10, np.concatenate(err_px)
    return {
        "frames": n,
        "payload_kbps": payload,
        "header_kbps": head,
        "body_kbps": payload - head,
        "keyframes": keys,
        "skipped": n - len(sizes),
        "wire_kbps": wire,
        "ack_kbps": acks,
        "mm_rms": float(np.sqrt((mm**2).mean())),
        "mm_p99": float(np.percentile(mm, 99)),
        "mm_max": float(mm.max()),
        "px_rms": float(np.sqrt((px**2).mean())),
        "px_p99": float(np.percentile(px, 99)),
        "px_max": float(px.max()),
        "size": f"{snapshot.width}x{snapshot.height}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=demo_clip_path())
    parser.add_argument("--error-px", type=float, nargs="+", default=[0.5])
    parser.add_argument("--frames", type=int)
    args = parser.parse_args()
    for e in args.error_px:
        r = measure(args.input, e, args.frames)
        print(
            f"{args.input.name} {r['size']}, error budget {e} px/channel, {r['frames']} frames: "
            f"payload {r['payload_kbps']:.2f} kbit/s (headers {r['header_kbps']:.2f}, "
            f"bodies {r['body_kbps']:.2f}; {r['keyframes']} keyframes, "
            f"{r['skipped']} frames without a packet); on the wire {r['wire_kbps']:.1f} kbit/s "
            f"+ {r['ack_kbps']:.1f} kbit/s of ACKs back"
        )
        print(
            f"  quantisation error: {r['mm_rms']:.3f} mm RMS, p99 {r['mm_p99']:.3f}, "
            f"max {r['mm_max']:.3f} mm; {r['px_rms']:.3f} px RMS, p99 {r['px_p99']:.3f}, "
            f"max {r['px_max']:.3f} px"
        )


if __name__ == "__main__":
    main()
