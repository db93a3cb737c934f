"""An independent measurement of the ordinary codecs, to check ``facewire bandwidth`` against.

Nothing here comes from facewire's codec or metric code. The ffmpeg program that
imageio-ffmpeg ships (its own FFmpeg build, not the libraries inside PyAV) encodes the frames
with the call settings written out below, writes the bitstream to a file and decodes it
again; scikit-image computes SSIM (Wang et al.'s Gaussian window) on BT.601 luma of the
decoded RGB, averaged over the face (the convex hull of the landmarks, from scipy and
scikit-image's polygon fill) and over the whole frame. The landmark tracker and the head
polygon's rule are facewire's: they define the regions, they do not measure.

Usage: python tests/independent_codecs.py CLIP CODEC KBPS [--frames N] [--scale S]
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from facewire.codecs import ordinary_scheduling

#: The call settings, spelt out as ffmpeg options (see README, facewire bandwidth).
SETTINGS = {
    "h264": [
        "-c:v",
        "libx264",
        "-preset",
        "medium",
        "-tune",
        "zerolatency",
        "-bf",
        "0",
        "-threads",
        "1",
    ],
    "vp9": [
        "-c:v",
        "libvpx-vp9",
        "-deadline",
        "realtime",
        "-cpu-used",
        "6",
        "-lag-in-frames",
        "0",
        "-row-mt",
        "1",
    ],
    "av1": ["-c:v", "libsvtav1", "-preset", "10", "-svtav1-params", "rtc=1:pred-struct=1:rc=2"],
}
#: Raw bitstream containers: H.264 Annex B as is; VP9 and AV1 in IVF (a 32-byte file header
#: and a 12-byte header per frame, taken off the count).
MUXER = {"h264": ("h264", 0, 0), "vp9": ("ivf", 32, 12), "av1": ("ivf", 32, 12)}


def ffmpeg() -> str:
    import imageio_ffmpeg

    return str(imageio_ffmpeg.get_ffmpeg_exe())


def read_video(path: Path, limit: int) -> tuple[list[np.ndarray], float]:
    """RGB frames ((h, w, 3) uint8) of a video, at most ``limit``, and its frame rate."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
    meta = next(reader)
    w, h = meta["size"]
    frames = []
    for raw in reader:
        frames.append(np.frombuffer(raw, np.uint8).reshape(h, w, 3))
        if len(frames) == limit:
            break
    reader.close()
    return frames, float(meta["fps"])


def _rung(w: int, h: int, scale: float) -> tuple[int, int]:
    return max(16, 2 * round(w * scale / 2)), max(16, 2 * round(h * scale / 2))


def _rate_options(codec: str, kbps: float) -> list[str]:
    rate = str(round(kbps * 1000))
    opts = ["-b:v", rate, "-maxrate", rate, "-bufsize", rate, "-g", "100000"]
    return opts + (["-minrate", rate] if codec == "vp9" else [])  # libvpx's CBR


def encode_decode_ffmpeg(
    frames: list[np.ndarray], codec: str, kbps: float, fps: float, scale: float, folder: Path
) -> tuple[int, list[np.ndarray]]:
    """(bitstream bytes, decoded RGB frames at the input's size), by the ffmpeg program."""
    h, w = frames[0].shape[:2]
    sw, sh = _rung(w, h, scale)
    fmt, file_header, frame_header = MUXER[codec]
    out = folder / f"{codec}.{fmt}"
    cmd = [ffmpeg(), "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24"]
    cmd += ["-s", f"{w}x{h}", "-r", f"{fps:g}", "-i", "-"]
    if (sw, sh) != (w, h):
        cmd += ["-vf", f"scale={sw}:{sh}:flags=bicubic"]
    cmd += ["-pix_fmt", "yuv420p", *SETTINGS[codec], *_rate_options(codec, kbps)]
    cmd += ["-f", fmt, str(out)]
    subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), check=True)
    size = out.stat().st_size - file_header - frame_header * len(frames)
    dec = [ffmpeg(), "-v", "error", "-i", str(out), "-fps_mode", "passthrough"]
    if (sw, sh) != (w, h):
        dec += ["-vf", f"scale={w}:{h}:flags=bicubic"]
    dec += ["-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
    raw = subprocess.run(dec, capture_output=True, check=True).stdout
    decoded = np.frombuffer(raw, np.uint8).reshape(-1, h, w, 3)
    return size, list(decoded)


def encode_decode_pyav(
    frames: list[np.ndarray], codec: str, kbps: float, fps: float, scale: float, folder: Path
) -> tuple[int, list[np.ndarray]]:
    """The same through PyAV's container API: muxed to a file, demuxed and decoded again."""
    from fractions import Fraction

    import av

    h, w = frames[0].shape[:2]
    sw, sh = _rung(w, h, scale)
    fmt, file_header, frame_header = MUXER[codec]
    args = [*SETTINGS[codec], *_rate_options(codec, kbps)]
    pairs = zip(args[::2], args[1::2], strict=True)
    options = {k.lstrip("-").removesuffix(":v"): v for k, v in pairs}
    encoder = options.pop("c")
    out = folder / f"{codec}.{fmt}"
    # SVT-AV1 makes the thread real-time when run as root (facewire/codecs.py).
    with ordinary_scheduling(), av.open(str(out), "w", format=fmt) as container:
        stream = container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = sw, sh, "yuv420p"
        stream.bit_rate = int(options["b"])
        stream.codec_context.options = options
        for i, rgb in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            frame = frame.reformat(sw, sh, "yuv420p", interpolation="BICUBIC")
            frame.pts = i
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    size = out.stat().st_size - file_header - frame_header * len(frames)
    decoded = []
    with av.open(str(out)) as container:
        for frame in container.decode(video=0):
            decoded.append(frame.reformat(w, h, "rgb24", interpolation="BICUBIC").to_ndarray())
    return size, decoded


BACKENDS = {"pyav": encode_decode_pyav, "ffmpeg": encode_decode_ffmpeg}


def luma(rgb: np.ndarray) -> np.ndarray:
    r, g, b = (rgb[..., i].astype(np.float64) for i in range(3))
    return 0.299 * r + 0.587 * g + 0.114 * b


def hull_mask(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from scipy.spatial import ConvexHull
    from skimage.draw import polygon

    xy = np.asarray(points)[:, :2]
    hull = xy[ConvexHull(xy).vertices]
    mask = np.zeros(shape, bool)
    rows, cols = polygon(hull[:, 1], hull[:, 0], shape)
    mask[rows, cols] = True
    return mask


def measure(
    clip: Path, codec: str, kbps: float, frames: int, scale: float = 1.0, backend: str = "pyav"
) -> dict:
    """{"kbps", "ssim": {"face", "head", "frame"}, "frames"} of ``codec`` on ``clip``."""
    from skimage.metrics import structural_similarity

    from facewire.quality import head_polygon
    from facewire.sender.landmarks import LandmarkTracker

    inputs, fps = read_video(clip, frames)
    with tempfile.TemporaryDirectory() as tmp:
        nbytes, outputs = BACKENDS[backend](inputs, codec, kbps, fps, scale, Path(tmp))
    if len(outputs) != len(inputs):
        raise RuntimeError(f"{codec}: {len(outputs)} frames decoded for {len(inputs)}")
    tracker = LandmarkTracker()
    scores: dict[str, list[float]] = {"face": [], "head": [], "frame": []}
    for ref, out in zip(inputs, outputs, strict=True):
        _, smap = structural_similarity(
            luma(ref),
            luma(out),
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=255,
            full=True,
        )
        scores["frame"].append(float(smap.mean()))
        found = tracker.track(np.ascontiguousarray(ref[..., ::-1]))  # the tracker takes BGR
        if found is None:
            continue
        scores["face"].append(float(smap[hull_mask(found.points, smap.shape)].mean()))
        scores["head"].append(float(smap[hull_mask(head_polygon(found.points), smap.shape)].mean()))
    return {
        "kbps": nbytes * 8 / (len(inputs) / fps) / 1000,
        "ssim": {k: float(np.mean(v)) for k, v in scores.items()},
        "frames": len(inputs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("clip", type=Path)
    parser.add_argument("codec", choices=sorted(SETTINGS))
    parser.add_argument("kbps", type=float)
    parser.add_argument("--frames", type=int, default=10**9)
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--backend", choices=sorted(BACKENDS), default="pyav")
    args = parser.parse_args()
    print(measure(args.clip, args.codec, args.kbps, args.frames, args.scale, args.backend))


if __name__ == "__main__":
    main()
