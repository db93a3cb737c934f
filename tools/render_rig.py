"""Draw the canonical mesh with its rig (frontal orthographic view) into a PNG.

    python tools/render_rig.py [-o docs/rig.png] [--size 1000] [--labels]

Wire curve chains are drawn as thick coloured polylines (one colour per feature), markers as
discs coloured by role, the four lip rings in shades of red, the REM eye regions as dashed
outlines. ``--labels`` writes vertex indices for checking the rig by eye.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np

from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.rig import Rig, load_rig

logger = logging.getLogger(__name__)

# BGR
FEATURE_COLOURS = {
    "brows": (40, 90, 160),
    "eyes": (200, 120, 0),
    "nose": (0, 150, 0),
    "cheeks": (180, 0, 180),
    "mouth": (0, 140, 255),
    "chin": (130, 130, 0),
    "forehead": (120, 60, 200),
}
ROLE_COLOURS = {"pose": (0, 0, 0), "deform": (0, 200, 255), "mouth": (0, 0, 230)}
LIP_COLOURS = [(0, 0, 140), (60, 60, 200), (110, 110, 240), (160, 160, 255)]
REM_COLOUR = (150, 150, 0)
MESH_COLOUR = (215, 215, 215)


def project(mesh: FaceMesh, size: int, margin: int = 40) -> np.ndarray:
    """(n, 2) float pixel coordinates of a frontal orthographic view (x right, y down)."""
    v = mesh.vertices
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    scale = (size - 2 * margin) / float((hi - lo).max())
    x = (v[:, 0] - lo[0]) * scale + margin
    y = (hi[1] - v[:, 1]) * scale + margin
    return np.stack([x, y], axis=1)


def _poly(img: np.ndarray, pts: np.ndarray, closed: bool, colour, thickness: int) -> None:
    cv2.polylines(img, [np.round(pts).astype(np.int32)], closed, colour, thickness, cv2.LINE_AA)


def _dashed_loop(img: np.ndarray, pts: np.ndarray, colour, thickness: int) -> None:
    loop = np.vstack([pts, pts[:1]])
    for a, b in zip(loop[:-1], loop[1:], strict=True):
        n = max(2, int(np.linalg.norm(b - a) / 8))
        t = np.linspace(0.0, 1.0, n + 1)
        seg = a + (b - a) * t[:, None]
        for k in range(0, n, 2):
            p, q = np.round(seg[k]).astype(int), np.round(seg[k + 1]).astype(int)
            cv2.line(img, tuple(p), tuple(q), colour, thickness, cv2.LINE_AA)


def render_rig(mesh: FaceMesh, rig: Rig, size: int = 1000, labels: bool = False) -> np.ndarray:
    """(size + legend, size, 3) uint8 BGR picture of ``mesh`` with ``rig`` drawn on it."""
    rig.validate(mesh.n_vertices)
    legend_h = 120
    img = np.full((size + legend_h, size, 3), 255, np.uint8)
    p = project(mesh, size)
    for a, b in mesh.edges:
        cv2.line(img, tuple(np.round(p[a]).astype(int)), tuple(np.round(p[b]).astype(int)),
                 MESH_COLOUR, 1, cv2.LINE_AA)  # fmt: skip
    for r in rig.rem:
        _dashed_loop(img, p[list(r.polygon)], REM_COLOUR, 2)
    for ring, colour in zip(rig.lips.contours, LIP_COLOURS, strict=True):
        _poly(img, p[list(ring)], True, colour, 1)
    for c in rig.curves:
        _poly(img, p[list(c.vertices)], False, FEATURE_COLOURS[c.feature], 3)
    for m in rig.markers:
        q = tuple(np.round(p[m.vertex]).astype(int))
        cv2.circle(img, q, 7, ROLE_COLOURS[m.role], -1, cv2.LINE_AA)
        cv2.circle(img, q, 7, (255, 255, 255), 1, cv2.LINE_AA)
    if labels:
        for i, q in enumerate(np.round(p).astype(int)):
            cv2.putText(img, str(i), (q[0] + 2, q[1] - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.25,
                        (90, 90, 90), 1, cv2.LINE_AA)  # fmt: skip
    _legend(img, size)
    return img


def _legend(img: np.ndarray, top: int) -> None:
    font = cv2.FONT_HERSHEY_SIMPLEX
    x, y = 20, top + 25
    cv2.putText(img, "wires:", (x, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    x += 70
    for name, colour in FEATURE_COLOURS.items():
        cv2.line(img, (x, y - 5), (x + 25, y - 5), colour, 3, cv2.LINE_AA)
        cv2.putText(img, name, (x + 30, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        x += 40 + 11 * len(name)
    x, y = 20, top + 60
    cv2.putText(img, "markers:", (x, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    x += 90
    for role, colour in ROLE_COLOURS.items():
        cv2.circle(img, (x + 7, y - 5), 7, colour, -1, cv2.LINE_AA)
        cv2.putText(img, role, (x + 20, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        x += 40 + 11 * len(role)
    cv2.line(img, (x, y - 5), (x + 25, y - 5), LIP_COLOURS[0], 2, cv2.LINE_AA)
    cv2.putText(img, "lip rings (4)", (x + 30, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    x += 170
    _dashed_loop(img, np.array([[x, y - 12], [x + 25, y - 12], [x + 25, y + 2], [x, y + 2]],
                               float), REM_COLOUR, 2)  # fmt: skip
    cv2.putText(img, "REM eye regions", (x + 32, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "canonical face mesh, frontal orthographic; rig from models/data/rig.json",
                (20, top + 95), font, 0.45, (90, 90, 90), 1, cv2.LINE_AA)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=Path("docs/rig.png"))
    ap.add_argument("--size", type=int, default=1000, help="image width in pixels")
    ap.add_argument("--rig", type=Path, default=None, help="rig JSON (default: bundled)")
    ap.add_argument("--labels", action="store_true", help="write vertex indices")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO)
    img = render_rig(load_canonical(), load_rig(args.rig), args.size, args.labels)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.output), img):
        raise SystemExit(f"cannot write {args.output}")
    logger.info("wrote %s (%dx%d)", args.output, img.shape[1], img.shape[0])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
