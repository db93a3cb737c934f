"""``facewire rem-map``: where texture change outweighs shape change (seed 003, Fig. 1-3).

Seed 003 section 2.2 defines a region effective for merging (REM) as one where the 2D texture
changes are much larger than the 3D shape deformation: there live video pasted onto the model
does what the model's geometry cannot. This tool measures that over a clip, in the model's
texture (UV) space, so every frame adds to the same texel:

1. the call's own sender tracks every frame, and the face is rebuilt as the receiver rebuilds
   it (quantised pose and wires): the *deformed model*;
2. dense optical flow (Farneback) between consecutive frames gives the image's motion at each
   texel's place in the earlier frame, |F|;
3. the model moves the texel from p(t-1) to p(t); of that, the part the head's pose does not
   explain is the *shape change* D = |pose_t(model_t) - pose_t(model_t-1)| (pixels);
4. what the model's motion does not explain is *texture change*. Moved along with the model,
   a texel whose texture does not change keeps its brightness (Eq. 1 with the model's motion
   for (u, v)): the residual r = |I_t(p(t)) - I_t-1(p(t-1))| (levels) is brightness the
   motion cannot account for, and r / |grad I| (the normal flow it takes, at least
   GRADIENT_FLOOR levels a pixel) puts it in pixels beside D: the texture change T. The dense
   flow's own disagreement with the model, |F - (p(t) - p(t-1))|, is reported too; being
   smooth over its window it misses small features (an iris, a lid's edge). Each counts
   only beyond its median over the face in that frame: what every texel shows (the
   tracker's jitter, the flow's own error) is no texture change.

Texels seen obliquely, or squeezed (the mouth's inside while the mouth is shut), count less.
The map (PNG) shows, over the snapshot texture: the mean flow magnitude (seed Fig. 2), the
mean shape change (Fig. 1) and the texture change's share T / (T + D) where it is large
(Fig. 3), with the REM regions of :mod:`facewire.models.rem` drawn over each panel. The JSON gives
the figures per region and for the face, and the verdict per region: a REM when its texture
change is at least :data:`REM_RATIO` times its shape change and :data:`STANDS_OUT` times the
face's typical (median) texel's.
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.models.rem import MOUTH_INTERIOR, RemLayout
from facewire.sender.capture import CapturedFrame, CaptureError, VideoSource
from facewire.sender.encoder import FaceEncoder
from facewire.sender.texture import UvRasteriser

logger = logging.getLogger(__name__)

#: Side of the UV grid the clip is measured on, texels; the map draws it MAP_SCALE times.
GRID = 128
MAP_SCALE = 4
#: A REM's texture change is at least this many times its shape change ...
REM_RATIO = 1.5
#: ... and this many times the face's typical (median) texel's.
STANDS_OUT = 1.5
#: Least luma gradient (levels per pixel) a texture change is divided by: flat skin's noise
#: must not read as pixels of motion.
GRADIENT_FLOOR = 8.0
#: Texels on triangles seen more obliquely than this cosine are left out of a frame.
MIN_FACING = 0.3
#: Frames looked at for a face to start from.
FACE_SEARCH = 60


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``rem-map`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "rem-map",
        help="map where a clip's texture change outweighs its shape change (REM analysis)",
        description="Where texture change outweighs shape change (seed 003's REM analysis): "
        "the flow, the shape change and the texture change over a clip, drawn over the face "
        "model's texture with the REM regions.",
    )
    p.add_argument("--input", metavar="VIDEO", required=True, help="video file to analyse")
    p.add_argument("--output", metavar="MAP.png", required=True, help="where to draw the map")
    p.add_argument("--json", metavar="OUT.json", help="figures per region and verdicts")
    p.add_argument("--frames", type=int, metavar="N", help="analyse at most N frames")

    def run(args: argparse.Namespace) -> int:
        return run_rem_map(args)

    p.set_defaults(func=run)


@dataclass
class Accumulated:
    """Per-texel sums over a clip (GRID x GRID each): weights and weighted measures."""

    weight: np.ndarray
    flow: np.ndarray  # |F|, px
    shape: np.ndarray  # D, px
    texture: np.ndarray  # T, px (brightness residual as normal flow)
    luma: np.ndarray  # brightness residual r, levels
    unexplained: np.ndarray  # |F - model motion|, px
    frames: int = 0  # pairs of consecutive frames with a face compared
    read: int = 0  # frames read, the first with a face and those before it included

    @classmethod
    def empty(cls) -> Accumulated:
        z = np.zeros(GRID * GRID)
        return cls(z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy())

    def mean(self, name: str) -> np.ndarray:
        """(GRID, GRID) weighted mean of one measure (NaN where nothing was seen)."""
        total = getattr(self, name)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(self.weight > 0, total / self.weight, np.nan)
        return out.reshape(GRID, GRID)


def _luma(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)


def _gradient(luma: np.ndarray) -> np.ndarray:
    """|grad I|, levels per pixel (Sobel, scaled to a unit step)."""
    gx = np.asarray(cv2.Sobel(luma, cv2.CV_32F, 1, 0, ksize=3), np.float32) / 8.0
    gy = np.asarray(cv2.Sobel(luma, cv2.CV_32F, 0, 1, ksize=3), np.float32) / 8.0
    return np.asarray(cv2.magnitude(gx, gy))


def _sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples of a (h, w) or (h, w, c) float image at (k, 2) points."""
    x = points[:, 0].astype(np.float32).reshape(1, -1)
    y = points[:, 1].astype(np.float32).reshape(1, -1)
    out = cv2.remap(image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(points.shape[0], -1).squeeze()


def analyse(path: str | Path, frames: int | None = None) -> tuple[Accumulated, RemLayout, Any]:
    """Accumulate flow, shape and texture change over a clip; also returns the layout (at
    GRID) and the snapshot texture resampled to GRID."""
    with VideoSource(path) as video:
        encoder = FaceEncoder(video.width, video.height, video.fps, rem=False)
        it = video.frames(limit=frames)
        snapshot = None
        read = 0
        for f in it:
            read += 1
            snapshot = encoder.start(CapturedFrame(f.index, f.image, f.capture_us))
            if snapshot is not None or f.index >= FACE_SEARCH:
                break
        if snapshot is None or encoder.session is None:
            raise CaptureError(f"no face found in the first frames of {path}")
        mesh = encoder.session.mesh
        layout = RemLayout(mesh.triangles, mesh.uvs, encoder.rig, GRID)
        rasteriser = UvRasteriser(layout.triangles, layout.uvs, GRID)
        texture = cv2.resize(encoder.session.texture, (GRID, GRID), interpolation=cv2.INTER_AREA)
        acc = Accumulated.empty()
        acc.read = read
        winsize = max(9, int(round(video.width / 40)) | 1)
        covered = rasteriser.covered_index
        uv_area = _uv_areas(layout)
        previous = None
        for f in it:
            acc.read += 1
            frame = CapturedFrame(f.index, f.image, f.capture_us)
            result = encoder.analyse(frame.image)
            encoder.encode_analysed(frame, result)
            values = encoder.values
            if result is None or values is None:
                previous = None
                continue
            pose, model = encoder.rebuilt(values)
            luma = _luma(frame.image)
            ext_model = layout.vertices(model)
            here, facing = rasteriser.texel_positions(pose.apply(ext_model))
            if previous is not None:
                p_luma, p_model, p_points, p_facing = previous
                flow = cv2.calcOpticalFlowFarneback(  # type: ignore[call-overload]
                    p_luma, luma, None, 0.5, 3, winsize, 3, 5, 1.2, 0
                )
                moved = here - p_points
                rigid = rasteriser.texel_positions(pose.apply(p_model))[0] - p_points
                squeeze = _squeeze(layout, pose.apply(ext_model), uv_area)
                seen = squeeze[rasteriser.covered_triangle]
                weight = (np.minimum(facing, p_facing) > MIN_FACING) * seen
                f_at = _sample(flow, p_points[:, :2])
                shape_change = np.linalg.norm(moved[:, :2] - rigid[:, :2], axis=1)
                residual = np.abs(_sample(luma, here[:, :2]) - _sample(p_luma, p_points[:, :2]))
                gradient = _sample(_gradient(p_luma), p_points[:, :2])
                excess = {
                    "texture": residual / np.maximum(gradient, GRADIENT_FLOOR),
                    "luma": residual,
                    "unexplained": np.linalg.norm(f_at - moved[:, :2], axis=1),
                }
                # What every texel shows this frame (the tracker's jitter, the model's misfit,
                # the flow's own error) is no texture change: only what a texel shows beyond
                # the face's median counts.
                typical = weight > 0.5
                if typical.any():
                    for k, v in excess.items():
                        excess[k] = np.maximum(v - np.median(v[typical]), 0.0)
                i = covered
                acc.weight[i] += weight
                acc.flow[i] += weight * np.linalg.norm(f_at, axis=1)
                acc.shape[i] += weight * shape_change
                for k, v in excess.items():
                    getattr(acc, k)[i] += weight * v
                acc.frames += 1
            previous = (luma, ext_model, here, facing)
    if acc.frames == 0:
        raise CaptureError(f"{path}: fewer than two frames with a face")
    return acc, layout, texture


def _uv_areas(layout: RemLayout) -> np.ndarray:
    uv = layout.uvs * GRID
    t = layout.triangles
    return _areas(uv[t[:, 0]], uv[t[:, 1]], uv[t[:, 2]])


def _areas(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Areas of 2-D triangles (k, 2) each."""
    u, v = b - a, c - a
    return np.asarray(0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]))


def _squeeze(layout: RemLayout, vertices: np.ndarray, uv_area: np.ndarray) -> np.ndarray:
    """Per triangle, 1 where it shows at least the face's typical pixels per texel, less
    where it is squeezed (a shut mouth's inside shows nothing)."""
    t = layout.triangles
    a, b, c = vertices[t[:, 0], :2], vertices[t[:, 1], :2], vertices[t[:, 2], :2]
    ratio = _areas(a, b, c) / np.maximum(uv_area, 1e-9)
    typical = float(np.median(ratio[uv_area > 0]))
    return np.clip(ratio / max(typical, 1e-9), 0.0, 1.0)


def region_figures(acc: Accumulated, layout: RemLayout) -> dict[str, Any]:
    """Weighted means per region and over the face, and each region's verdict."""
    seen = acc.weight.reshape(GRID, GRID) > 0
    weight = acc.weight.reshape(GRID, GRID)

    def figures(mask: np.ndarray) -> dict[str, float]:
        m = mask & seen
        w = weight[m]
        if w.sum() <= 0:
            return {"texels": 0}
        avg = {k: float(np.average(v[m], weights=w)) for k, v in _measures(acc).items()}
        return {"texels": int(m.sum()), **avg}

    face_mask = seen & ~_atlas_mask(layout)
    face = figures(face_mask)
    # The face's typical texel (its median: the silhouette, where hair and background slide
    # past the mesh's edge, must not set the bar).
    face_t = float(np.median(acc.mean("texture")[face_mask]))
    face["texture_change_median_px"] = face_t
    regions = {}
    for name, box in layout.boxes.items():
        mask = np.zeros((GRID, GRID), bool)
        mask[box.y : box.y + box.height, box.x : box.x + box.width] = box.inside
        fig = figures(mask)
        if fig.get("texels", 0):
            ratio = fig["texture_change_px"] / max(fig["shape_change_px"], 1e-6)
            fig["texture_over_shape"] = ratio
            fig["texture_over_face"] = fig["texture_change_px"] / max(face_t, 1e-6)
            fig["rem"] = bool(ratio >= REM_RATIO and fig["texture_over_face"] >= STANDS_OUT)
        regions[name] = fig
    return {"face": face, "regions": regions}


def _measures(acc: Accumulated) -> dict[str, np.ndarray]:
    return {
        "flow_px": acc.mean("flow"),
        "shape_change_px": acc.mean("shape"),
        "texture_change_px": acc.mean("texture"),
        "brightness_residual": acc.mean("luma"),
        "flow_unexplained_px": acc.mean("unexplained"),
    }


def _atlas_mask(layout: RemLayout) -> np.ndarray:
    mask = np.zeros((GRID, GRID), bool)
    box = layout.boxes.get(MOUTH_INTERIOR)
    if box is not None:
        mask[box.y : box.y + box.height, box.x : box.x + box.width] = True
    return mask


def draw_map(acc: Accumulated, layout: RemLayout, texture: np.ndarray, figures: dict) -> np.ndarray:
    """Three panels over the texture: flow magnitude, shape change, texture change's share."""
    base = cv2.cvtColor(cv2.cvtColor(texture, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    flow, shape, tex = acc.mean("flow"), acc.mean("shape"), acc.mean("texture")
    scale = float(np.nanpercentile(flow, 98)) or 1.0
    share = tex / (tex + shape + 1e-6)
    # The share only where texture change is real (above the face's median).
    strong = np.clip(tex / (2 * max(figures["face"]["texture_change_median_px"], 1e-6)), 0, 1)
    panels = [
        ("optical flow |F|", flow / scale),
        ("shape change D (model, pose removed)", shape / scale),
        ("texture change share T/(T+D)", share * strong),
    ]
    out = []
    for title, value in panels:
        heat = cv2.applyColorMap(
            np.clip(np.nan_to_num(value) * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_INFERNO
        )
        seen = ~np.isnan(value)
        tile = np.where(seen[:, :, None], (0.35 * base + 0.65 * heat).astype(np.uint8), base // 3)
        tile = cv2.resize(tile, None, fx=MAP_SCALE, fy=MAP_SCALE, interpolation=cv2.INTER_NEAREST)
        _outline_regions(tile, layout, figures)
        cv2.putText(tile, title, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        out.append(tile)
    return np.hstack(out)


def _outline_regions(tile: np.ndarray, layout: RemLayout, figures: dict) -> None:
    for name, box in layout.boxes.items():
        verdict = figures["regions"].get(name, {}).get("rem")
        colour = (80, 255, 80) if verdict else (80, 80, 255)
        inside = np.zeros((GRID, GRID), np.uint8)
        inside[box.y : box.y + box.height, box.x : box.x + box.width] = box.inside
        big = cv2.resize(inside, None, fx=MAP_SCALE, fy=MAP_SCALE, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(big, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(tile, contours, -1, colour, 1)
        x, y = MAP_SCALE * box.x, MAP_SCALE * (box.y + box.height) + 12
        label = f"{name}: {'REM' if verdict else 'no'}"
        cv2.putText(
            tile, label, (x, min(y, tile.shape[0] - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1
        )


def run_rem_map(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 2:
        raise ValueError(f"--frames must be at least 2, got {args.frames}")
    acc, layout, texture = analyse(args.input, args.frames)
    figures = region_figures(acc, layout)
    image = draw_map(acc, layout, texture, figures)
    if not cv2.imwrite(str(args.output), image):
        raise OSError(f"cannot write {args.output}")
    result = {"input": str(args.input), "frames": acc.read, "pairs": acc.frames, **figures}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    for name, fig in figures["regions"].items():
        if fig.get("texels"):
            print(
                f"{name}: texture change {fig['texture_change_px']:.2f} px, shape change "
                f"{fig['shape_change_px']:.2f} px ({fig['texture_over_shape']:.1f}x), "
                f"{fig['texture_over_face']:.1f}x the face's median: "
                f"{'a REM' if fig['rem'] else 'not a REM'}"
            )
    print(f"wrote {args.output}" + (f" and {args.json}" if args.json else ""))
    return 0
