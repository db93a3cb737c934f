"""Texture unwrap (image -> UV space) and a face-free background, for the session snapshot.

Pure numpy + OpenCV. Conventions match receiver.render.FaceRenderer:

- UVs: u to the right, v = 0 at the TOP row of the texture image. Texel (row j, column i)
  of a (size, size) texture is centred at u = (i + 0.5) / size, v = (j + 0.5) / size.
- image space: pixels, x right, y down, z away from the camera; pixel centres at integer
  coordinates (OpenCV).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import scipy.sparse as sp

from facewire.models.fill import fill_invalid

logger = logging.getLogger(__name__)

# Barycentric slack so texels exactly on a shared UV edge are not lost to rounding.
_EDGE_EPS = 1e-6


def _check_vertices(image_vertices: np.ndarray, n: int) -> np.ndarray:
    v = np.asarray(image_vertices, dtype=np.float64)
    if v.shape != (n, 3):
        raise ValueError(f"expected ({n}, 3) image_vertices, got {v.shape}")
    return v


def _check_frame(frame_bgr: np.ndarray) -> np.ndarray:
    f = np.asarray(frame_bgr)
    if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
        raise ValueError(f"expected frame_bgr (h, w, 3) uint8, got {f.shape} {f.dtype}")
    return f


def _check_triangles(triangles: np.ndarray, n: int) -> np.ndarray:
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"expected (m, 3) int triangles, got {t.shape} {t.dtype}")
    if t.size and (t.min() < 0 or t.max() >= n):
        raise ValueError(f"triangle index out of range 0..{n - 1}")
    return t.astype(np.int64)


def scan_triangles(tri_xy: np.ndarray, width: int, height: int) -> tuple[np.ndarray, ...]:
    """Vectorised scan conversion of many 2D triangles at once.

    tri_xy : (m, 3, 2) float, corner positions in pixel coordinates whose centres are at
        integers (x = column, y = row)
    returns (tri, px, py, bary) for every (pixel centre, triangle) pair with the centre
    inside the triangle (edges included) and inside the width x height grid: tri (k,)
    triangle index, px, py (k,) int64 column and row, bary (k, 3) float64 weights.
    Degenerate triangles cover nothing.
    """
    empty = np.zeros(0, dtype=np.int64)
    if len(tri_xy) == 0:
        return empty, empty, empty, np.zeros((0, 3))
    lo = np.floor(tri_xy.min(axis=1)).astype(np.int64)
    hi = np.ceil(tri_xy.max(axis=1)).astype(np.int64)
    lo[:, 0] = np.clip(lo[:, 0], 0, width - 1)
    lo[:, 1] = np.clip(lo[:, 1], 0, height - 1)
    hi[:, 0] = np.clip(hi[:, 0], 0, width - 1)
    hi[:, 1] = np.clip(hi[:, 1], 0, height - 1)
    nx = hi[:, 0] - lo[:, 0] + 1
    ny = hi[:, 1] - lo[:, 1] + 1
    counts = nx * ny
    tri_of = np.repeat(np.arange(len(tri_xy)), counts)
    # Position of each candidate pixel inside its triangle's bounding box.
    starts = np.cumsum(counts) - counts
    local = np.arange(counts.sum()) - np.repeat(starts, counts)
    px = lo[tri_of, 0] + local % nx[tri_of]
    py = lo[tri_of, 1] + local // nx[tri_of]

    a, b, c = tri_xy[tri_of, 0], tri_xy[tri_of, 1], tri_xy[tri_of, 2]
    v0, v1 = b - a, c - a
    dx = px - a[:, 0]
    dy = py - a[:, 1]
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    w1 = (dx * v1[:, 1] - v1[:, 0] * dy) / den
    w2 = (v0[:, 0] * dy - dx * v0[:, 1]) / den
    w0 = 1.0 - w1 - w2
    inside = ok & (w0 >= -_EDGE_EPS) & (w1 >= -_EDGE_EPS) & (w2 >= -_EDGE_EPS)
    bary = np.column_stack([w0, w1, w2])[inside]
    return tri_of[inside], px[inside], py[inside], bary


def z_buffer(
    image_vertices: np.ndarray, triangles: np.ndarray, width: int, height: int
) -> np.ndarray:
    """(height, width) float64 nearest image-space z of the mesh per pixel (inf: empty)."""
    v = np.asarray(image_vertices, dtype=np.float64)
    tri, px, py, bary = scan_triangles(v[triangles, :2], width, height)
    z = np.einsum("kj,kj->k", bary, v[triangles[tri], 2])
    zbuf = np.full(height * width, np.inf)
    np.minimum.at(zbuf, py * width + px, z)
    return zbuf.reshape(height, width)


class UvRasteriser:
    """Maps every texel of a (size, size) texture to a point on the mesh, once.

    triangles : (m, 3) int, vertex indices
    uvs : (n, 2) float in [0, 1], v = 0 at the top row
    size : texture side in texels

    Attributes, all (size, size): ``triangle`` (int64, -1 where no triangle covers the
    texel centre), ``bary`` (size, size, 3) float32 barycentric weights of the triangle's
    corners, ``covered`` bool.
    """

    def __init__(self, triangles: np.ndarray, uvs: np.ndarray, size: int = 512) -> None:
        uv = np.asarray(uvs, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"expected (n, 2) uvs, got {uv.shape}")
        if int(size) < 2:
            raise ValueError(f"expected texture size >= 2, got {size}")
        self.size = int(size)
        self.n_vertices = len(uv)
        self.triangles = _check_triangles(triangles, len(uv))
        self.uvs = uv
        s = self.size
        tri, px, py, bary = scan_triangles(uv[self.triangles] * s - 0.5, s, s)
        self.triangle = np.full((s, s), -1, dtype=np.int64)
        self.bary = np.zeros((s, s, 3), dtype=np.float32)
        # Where UV triangles touch, the later one wins; both give the same surface point.
        self.triangle[py, px] = tri
        self.bary[py, px] = bary
        self.covered = self.triangle >= 0
        # Per-frame lookups over the covered texels only, in raster order.
        self._flat_index = np.flatnonzero(self.covered)
        self._flat_tri = self.triangle.ravel()[self._flat_index]
        k = len(self._flat_index)
        # (k, n) sparse matrix of barycentric weights: texel points = B @ vertices.
        self._bary_matrix = sp.csr_matrix(
            (
                self.bary.reshape(-1, 3)[self._flat_index].astype(np.float64).ravel(),
                (np.repeat(np.arange(k), 3), self.triangles[self._flat_tri].ravel()),
            ),
            shape=(k, self.n_vertices),
        )
        logger.debug(
            "UvRasteriser %d triangles, %dx%d texels, %.1f%% covered",
            len(self.triangles),
            s,
            s,
            100.0 * self.covered.mean(),
        )

    @property
    def covered_index(self) -> np.ndarray:
        """(k,) flat indices (row * size + column) of the covered texels, in raster order:
        the order of :meth:`texel_positions`' rows."""
        return self._flat_index

    @property
    def covered_triangle(self) -> np.ndarray:
        """(k,) the triangle under each covered texel, in the same order."""
        return self._flat_tri

    def texel_positions(self, image_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image-space point of each covered texel.

        image_vertices : (n, 3) float, image space
        returns points (k, 3) float64 image space (pixels; z away from the camera) for the
        covered texels in raster order, and facing (k,) float64, the cosine between the
        texel's triangle normal and the direction towards the camera (> 0: front-facing).
        """
        v = _check_vertices(image_vertices, self.n_vertices)
        t = self.triangles
        # Image space is right-handed (x right, y down, z away), and model triangles are
        # counter-clockwise seen from outside, so a triangle facing the camera has a
        # normal with negative z.
        n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        norm = np.linalg.norm(n, axis=1)
        facing = -n[:, 2] / np.where(norm > 0, norm, 1.0)
        return self._bary_matrix @ v, facing[self._flat_tri]

    def unwrap(
        self,
        frame_bgr: np.ndarray,
        image_vertices: np.ndarray,
        min_facing: float = 0.15,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sample the frame into the texture.

        frame_bgr : (h, w, 3) uint8 BGR
        image_vertices : (n, 3) float, the mesh in the frame's image space
        min_facing : texels on triangles seen more obliquely than this cosine are invalid
            (their frame pixels are smeared over many texels)
        returns texture_bgr (size, size, 3) uint8 and valid (size, size) bool: texels seen
        in the frame (covered, facing the camera, not hidden behind another part of the
        mesh, inside the frame). Invalid texels are filled from their valid neighbours so
        no black seams render.
        """
        texture, valid = self.sample(_check_frame(frame_bgr), image_vertices, min_facing)
        return fill_invalid(texture, valid), valid

    def sample(
        self,
        image: np.ndarray,
        image_vertices: np.ndarray,
        min_facing: float,
        hidden: bool = True,
        hidden_scale: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`unwrap` of an (h, w) or (h, w, c) image without the filling: the texture
        (what lies under invalid texels is undefined) and the (size, size) bool valid texels.
        ``hidden`` False skips the test for texels behind another part of the mesh (a
        z-buffer of the face: most of the cost, growing with its pixels), leaving facing and
        in-frame; ``hidden_scale`` below 1 makes that test on the image scaled by it (for a
        texture far coarser than the frame: the rim left out grows to 1 / scale pixels)."""
        pts, facing = self.texel_positions(image_vertices)
        h, w = image.shape[:2]
        s = self.size
        map_x = np.full(s * s, -1.0, dtype=np.float32)
        map_y = np.full(s * s, -1.0, dtype=np.float32)
        map_x[self._flat_index] = pts[:, 0]
        map_y[self._flat_index] = pts[:, 1]
        texture = cv2.remap(
            image,
            map_x.reshape(s, s),
            map_y.reshape(s, s),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        ok = facing > min_facing
        ok &= (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
        if hidden:
            ok[ok] = self._visible(image_vertices, pts[ok], w, h, hidden_scale)
        valid_flat = np.zeros(s * s, dtype=bool)
        valid_flat[self._flat_index] = ok
        return texture, valid_flat.reshape(s, s)

    def _visible(
        self, image_vertices: np.ndarray, pts: np.ndarray, w: int, h: int, scale: float = 1.0
    ) -> np.ndarray:
        """(k,) bool: the points (k, 3) are the nearest surface at their pixel, and not on
        the outline; with ``scale`` below 1, of the image scaled by it (x, y and z alike)."""
        v = np.asarray(image_vertices, dtype=np.float64)
        if scale != 1.0:
            v, pts = v * scale, pts * scale
            w, h = max(1, int(np.ceil(w * scale))), max(1, int(np.ceil(h * scale)))
        zbuf = z_buffer(v, self.triangles, w, h)
        # Bilinear sampling within a pixel of the silhouette mixes in what lies behind the
        # head (hair, background): treat a 1-pixel rim inside the outline as hidden.
        covered = np.isfinite(zbuf).astype(np.uint8)
        rim = covered.astype(bool) & ~cv2.erode(covered, np.ones((3, 3), np.uint8)).astype(bool)
        zbuf[rim] = -np.inf
        col = np.clip(np.rint(pts[:, 0]).astype(np.int64), 0, w - 1)
        row = np.clip(np.rint(pts[:, 1]).astype(np.int64), 0, h - 1)
        # Rounding to the pixel centre moves along a slanted surface, so allow the depth
        # change over about one pixel on a 60-degree slope, plus some slack.
        extent = float(np.ptp(v[:, :2], axis=0).max())
        tol = 2.0 + 0.005 * extent
        return pts[:, 2] <= zbuf[row, col] + tol


def face_hull_mask(
    shape: tuple[int, int], image_vertices: np.ndarray, triangles: np.ndarray, dilate: int = 0
) -> np.ndarray:
    """(h, w) bool mask of the convex hull of the projected mesh, grown by ``dilate`` px."""
    v = np.asarray(image_vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"expected (n, 3) image_vertices, got {v.shape}")
    t = _check_triangles(triangles, len(v))
    used = np.unique(t)
    pts = np.round(v[used, :2]).astype(np.int32)
    hull = cv2.convexHull(pts)
    mask: np.ndarray = np.zeros(shape, dtype=np.uint8)
    cv2.fillConvexPoly(mask, hull, 255)
    if dilate > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))
        mask = cv2.dilate(mask, k)
    return mask > 0


def make_background(
    frame_bgr: np.ndarray,
    image_vertices: np.ndarray,
    triangles: np.ndarray,
    dilate_fraction: float = 0.08,
) -> np.ndarray:
    """The frame with the face removed, for the receiver to render the head over.

    frame_bgr : (h, w, 3) uint8 BGR; image_vertices : (n, 3) image space; triangles (m, 3).
    The convex hull of the projected mesh, grown by ``dilate_fraction`` of its size (hair
    and the jaw line sit just outside the mesh), is filled from its surroundings, so a
    head that moves later leaves no ghost of this frame's face behind it.
    returns (h, w, 3) uint8 BGR.
    """
    frame = _check_frame(frame_bgr)
    v = _check_vertices(image_vertices, len(np.asarray(image_vertices)))
    extent = float(np.ptp(v[:, :2], axis=0).max())
    dilate = max(2, int(round(dilate_fraction * extent)))
    hole = face_hull_mask(frame.shape[:2], v, triangles, dilate)
    # The head is drawn over it anyway.
    return fill_invalid(frame, ~hole)
