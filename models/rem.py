"""Regions effective for merging (REM, seed 003 section 2.2) laid out in a session's texture.

Both ends build the same :class:`RemLayout` from the canonical mesh's UVs, the rig and the
texture's side, so a REM patch needs to say no more than its region's name: the patch is the
region's rectangle of texels (:class:`RemBox`), and the receiver blends it in with the box's
feathered weight.

Regions:

- ``eye_right``, ``eye_left``: the rig's "spectacles" polygons, in the face's own UVs;
- ``mouth``: the lips, in the face's own UVs: the rig's outer lip contour grown by
  :data:`MOUTH_GROW` about its centre, so its feathered edge lies on skin. Cut through a
  mesh whose mouth opens less than the real one (the tracker and the wires under-shoot an
  open mouth), it carries the teeth and tongue the camera saw onto the lips;
- ``mouth_interior``: the inside of the innermost lip contour. The canonical mesh closes the
  mouth with a strip of triangles whose UVs are a line one texel high (the mouth is shut in
  the canonical face), so an opening mouth shows that line stretched. The layout gives the
  strip its own rectangle of texture (:data:`MOUTH_ATLAS`, above the face's UVs, which start
  at v = 0.107): the inner lip's vertices are duplicated with UVs there (upper lip along the
  top edge, lower lip along the bottom, corners half way), and the strip's triangles use the
  duplicates. :attr:`RemLayout.triangles`, :attr:`RemLayout.uvs` and
  :meth:`RemLayout.vertices` are that mesh, for unwrapping and rendering.

Texel conventions are those of ``facewire.sender.texture``: v = 0 at the top row, texel (row j,
column i) of a T x T texture centred at u = (i + 0.5) / T, v = (j + 0.5) / T.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.rig import Rig
from facewire.protocol.constants import REM_REGIONS

logger = logging.getLogger(__name__)

#: Every region a layout can hold, in the order patches are considered (a RemPatch names one
#: by its place here).
REGION_NAMES = REM_REGIONS
EYE_RIGHT, EYE_LEFT, MOUTH, MOUTH_INTERIOR = REGION_NAMES
#: The regions patches are sent for: those ``facewire rem-map`` finds to be REMs on real
#: footage (texture change at least 1.5 times the shape change and the face's typical
#: texel's). The lips are not one (their change is mostly shape), the mouth's inside is.
SENT_REGIONS = (EYE_RIGHT, EYE_LEFT, MOUTH_INTERIOR)
#: The regions whose skin gives the reference colour (seed 003 section 2.3).
EYES = (EYE_RIGHT, EYE_LEFT)
#: The mouth's region: the outer lip contour scaled about its centre by this.
MOUTH_GROW = 1.3
#: (u0, v0, u1, v1) of the mouth interior's rectangle: texture no face triangle samples. The
#: face's UVs start at v = 0.107, so a 64-texel texture keeps a texel between the two.
MOUTH_ATLAS = (0.36, 0.008, 0.64, 0.092)
#: Texels around a polygon's bounding box carried in its patch (for the feathered edge).
BOX_MARGIN = 1
#: The merge weight ramps from 0 at a region's edge to 1 over this fraction of its box's
#: shorter side (at least MIN_FEATHER texels), so no seam shows where the patch meets the face.
FEATHER_FRACTION = 0.18
MIN_FEATHER = 1.5
#: Smallest patch grid (and texture) side.
MIN_PATCH_SIZE = 16


@dataclass(frozen=True, eq=False)
class RemBox:
    """One region's rectangle, on the patch grid and in the texture.

    x, y, width, height : the rectangle on the patch grid (a patch is width x height)
    scale : texels of the texture per texel of the patch grid (an integer, 1 or more)
    inside : (height, width) bool, the patch grid's texels of the region proper
    alpha : (height, width) float32 weight on the patch grid, 0 outside the region rising to
        1 inside it (how much each texel's change counts)
    texture_inside, texture_alpha : the same at the texture's resolution (scale times the
        patch's size): what the receiver measures and blends with
    """

    name: str
    x: int
    y: int
    width: int
    height: int
    scale: int
    inside: np.ndarray
    alpha: np.ndarray
    texture_inside: np.ndarray
    texture_alpha: np.ndarray

    @property
    def texture_slices(self) -> tuple[slice, slice]:
        """(rows, columns) of the box in the texture."""
        k = self.scale
        return slice(k * self.y, k * (self.y + self.height)), slice(
            k * self.x, k * (self.x + self.width)
        )


def _feathered(inside: np.ndarray, feather: float) -> np.ndarray:
    distance = cv2.distanceTransform(np.pad(inside.astype(np.uint8), 1), cv2.DIST_L2, 3)
    return np.clip(distance[1:-1, 1:-1] / feather, 0.0, 1.0).astype(np.float32)


def _fill(uv: np.ndarray, size: int, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """(h, w) bool: texels of a (size, size) grid's rectangle inside the UV polygon."""
    shift = 4  # sub-texel vertex positions for fillPoly
    pts = np.round((uv * size - 0.5 - [x0, y0]) * (1 << shift)).astype(np.int32)
    inside = np.zeros((h, w), np.uint8)
    cv2.fillPoly(inside, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    return inside.astype(bool)


def _polygon_box(name: str, uv: np.ndarray, size: int, scale: int) -> RemBox:
    """A polygon's box on a (size, size) patch grid: its bounding box plus a margin, the
    weight feathered inward."""
    p = uv * size - 0.5  # texel coordinates (centres at integers)
    x0 = max(0, int(np.floor(p[:, 0].min())) - BOX_MARGIN)
    y0 = max(0, int(np.floor(p[:, 1].min())) - BOX_MARGIN)
    x1 = min(size - 1, int(np.ceil(p[:, 0].max())) + BOX_MARGIN)
    y1 = min(size - 1, int(np.ceil(p[:, 1].max())) + BOX_MARGIN)
    w, h = x1 - x0 + 1, y1 - y0 + 1
    feather = max(MIN_FEATHER, FEATHER_FRACTION * min(w, h))
    inside = _fill(uv, size, x0, y0, w, h)
    big = _fill(uv, size * scale, scale * x0, scale * y0, scale * w, scale * h)
    return RemBox(
        name,
        x0,
        y0,
        w,
        h,
        scale,
        inside,
        _feathered(inside, feather),
        big,
        _feathered(big, feather * scale),
    )


def _atlas_box(size: int, scale: int) -> RemBox:
    u0, v0, u1, v1 = MOUTH_ATLAS
    x0, y0 = int(np.floor(u0 * size)), int(np.floor(v0 * size))
    x1, y1 = int(np.ceil(u1 * size)) - 1, int(np.ceil(v1 * size)) - 1
    w, h = x1 - x0 + 1, y1 - y0 + 1
    # Its own surface: the lips border it in the mesh, so it is pasted whole, no feather.
    ones = np.ones((h, w), bool)
    big = np.ones((h * scale, w * scale), bool)
    return RemBox(
        MOUTH_INTERIOR,
        x0,
        y0,
        w,
        h,
        scale,
        ones,
        ones.astype(np.float32),
        big,
        big.astype(np.float32),
    )


def _split_loop(loop: list[int], uvs: np.ndarray) -> tuple[int, int, list[int], list[int]]:
    """Corners (smallest and largest u) of the inner lip loop, and the upper and lower chains
    between them (upper: the smaller v, nearer the top of the texture)."""
    u = uvs[loop, 0]
    a, b = int(np.argmin(u)), int(np.argmax(u))
    n = len(loop)
    first = [loop[(a + k) % n] for k in range(1, (b - a) % n)]
    second = [loop[(b + k) % n] for k in range(1, (a - b) % n)]
    if uvs[first, 1].mean() <= uvs[second, 1].mean():
        return loop[a], loop[b], first, second
    return loop[a], loop[b], second, first


def patch_size_for(texture_size: int, patch_size: int | None) -> int:
    """The patch grid's side for a texture: ``patch_size`` (a power of two, at least
    MIN_PATCH_SIZE and at most the texture's side) or the texture's own side if None.
    ValueError otherwise."""
    if patch_size is None:
        return texture_size
    p = int(patch_size)
    if p < MIN_PATCH_SIZE or p > texture_size or p & (p - 1) or texture_size % p:
        raise ValueError(
            f"REM patch grid {patch_size} must be a power of two in [{MIN_PATCH_SIZE}, "
            f"{texture_size}] dividing the texture's side"
        )
    return p


class RemLayout:
    """The REM regions of a (size, size) texture, and the mesh that gives the mouth's inside
    its own rectangle of it.

    triangles : (m, 3) int, the face's triangles (canonical topology)
    uvs : (n, 2) float, the face's UVs (v = 0 at the top row)
    rig : the rig (its ``rem`` polygons and its innermost lip contour)
    size : the texture's side in texels
    patch_size : the side of the grid patches are cut on (see :func:`patch_size_for`;
        default: the texture's). Patches travel at this resolution and are scaled up by
        ``size // patch_size`` into the texture: a texture sharper than the camera for the
        snapshot need not make every patch as large.
    regions : the regions to lay out (default: all of :data:`REGION_NAMES`)
    """

    def __init__(
        self,
        triangles: np.ndarray,
        uvs: np.ndarray,
        rig: Rig,
        size: int,
        patch_size: int | None = None,
        regions: tuple[str, ...] = REGION_NAMES,
    ) -> None:
        uv = np.asarray(uvs, dtype=np.float64)
        tris = np.asarray(triangles, dtype=np.int64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"expected (n, 2) uvs, got {uv.shape}")
        if int(size) < MIN_PATCH_SIZE:
            raise ValueError(
                f"expected a texture side of at least {MIN_PATCH_SIZE} texels, got {size}"
            )
        unknown = set(regions) - set(REGION_NAMES)
        if unknown:
            raise ValueError(f"unknown REM regions {sorted(unknown)}; known: {REGION_NAMES}")
        self.size = int(size)
        self.patch_size = patch_size_for(self.size, patch_size)
        scale = self.size // self.patch_size
        p = self.patch_size
        self.n_vertices = len(uv)
        polygons = {r.name: uv[list(r.polygon)] for r in rig.rem}
        lips = uv[list(rig.lips.contours[0])]
        polygons[MOUTH] = lips.mean(axis=0) + MOUTH_GROW * (lips - lips.mean(axis=0))
        self.boxes: dict[str, RemBox] = {}
        for name in regions:
            if name == MOUTH_INTERIOR:
                self.boxes[name] = _atlas_box(p, scale)
            elif name in polygons:
                self.boxes[name] = _polygon_box(name, polygons[name], p, scale)
            else:
                raise ValueError(f"the rig has no REM polygon {name!r}")
        # The mesh: with a mouth interior, its strip of triangles moves onto copies of the
        # inner lip's vertices whose UVs lie in the atlas rectangle.
        source = np.arange(self.n_vertices)
        ext_uv = uv
        ext_tris = tris
        self.interior_triangles = np.zeros(0, dtype=np.int64)
        if MOUTH_INTERIOR in self.boxes:
            loop = list(rig.lips.contours[-1])
            strip = np.flatnonzero(np.all(np.isin(tris, loop), axis=1))
            if len(strip) == 0:
                raise ValueError("the mesh has no triangles inside the inner lip contour")
            copy_of = {v: self.n_vertices + k for k, v in enumerate(loop)}
            _, _, upper, lower = _split_loop(loop, uv)
            box = self.boxes[MOUTH_INTERIOR]
            u_lo, u_hi = uv[loop, 0].min(), uv[loop, 0].max()
            # Texel centres of the box's edge texels on the patch grid: bilinear sampling
            # never reads outside the box.
            top, bottom = (box.y + 0.5) / p, (box.y + box.height - 0.5) / p
            left_u, right_u = (box.x + 0.5) / p, (box.x + box.width - 0.5) / p
            atlas = np.zeros((len(loop), 2))
            for k, v in enumerate(loop):
                t = (uv[v, 0] - u_lo) / (u_hi - u_lo)
                atlas[k, 0] = left_u + t * (right_u - left_u)
                if v in upper:
                    atlas[k, 1] = top
                elif v in lower:
                    atlas[k, 1] = bottom
                else:  # a corner
                    atlas[k, 1] = 0.5 * (top + bottom)
            ext_tris = tris.copy()
            ext_tris[strip] = np.vectorize(copy_of.__getitem__)(tris[strip])
            ext_uv = np.vstack([uv, atlas])
            source = np.concatenate([source, np.asarray(loop, dtype=np.int64)])
            self.interior_triangles = strip
        self.triangles = ext_tris
        self.uvs = ext_uv
        #: (n + k,) the vertex each of the layout's vertices takes its position from.
        self.source = source
        logger.debug(
            "REM layout, texture %d, patches on %d: %s",
            self.size,
            self.patch_size,
            ", ".join(f"{b.name} {b.width}x{b.height}" for b in self.boxes.values()),
        )

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.boxes)

    def vertices(self, vertices: np.ndarray) -> np.ndarray:
        """The layout mesh's vertices from the face's: (n, d) -> (n + k, d)."""
        v = np.asarray(vertices)
        if v.ndim != 2 or len(v) != self.n_vertices:
            raise ValueError(f"expected ({self.n_vertices}, d) vertices, got {v.shape}")
        return v[self.source]
