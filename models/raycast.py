"""Ray casting onto a triangle mesh: 2D image points lifted to 3D points on the face.

Seed 002 (Noh, Fidaleo and Neumann), section 2.2: the point where the ray from the camera
through an image point meets the face mesh is that point's 3D position. Our camera is
orthographic (``facewire.models.pose``: image = scale R model + t, x and y in pixels, z away
from the camera), so the ray through pixel (u, v) is the line {(u, v, z)}: in model space it runs
along ``R.T @ (0, 0, 1)``.

Speed comes from a bounding volume hierarchy over the triangles, built once for a topology
(median splits of the rest mesh's triangle centroids) and refitted in one vectorised pass
per level when the vertices move (the face deforms every frame; the tree's shape stays
good because faces deform locally). Rays walk the tree together, breadth first, so a frame
costs one numpy pass per tree level plus Moller-Trumbore on the few triangles in the leaves
each ray reaches.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from facewire.models.pose import Pose

logger = logging.getLogger(__name__)

LEAF_SIZE = 4  # triangles per leaf at most
# How far in front of the model's origin (cm) rays start: far beyond any face mesh.
RAY_START_CM = 1000.0
_EPS = 1e-12


@dataclass(frozen=True)
class RayHits:
    """Nearest hits of r rays.

    hit : (r,) bool, the ray meets the mesh
    points : (r, 3) model space (cm); NaN where there is no hit
    triangle : (r,) int64 triangle index, -1 where there is no hit
    barycentric : (r, 3) weights of the triangle's three vertices (NaN without a hit)
    distance : (r,) distance along the ray from its origin (inf without a hit)
    facing : (r,) cosine between the triangle's outward normal and the direction back
        along the ray: 1 head-on, 0 at the silhouette, negative on a back face (NaN without
        a hit)
    """

    hit: np.ndarray
    points: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray
    facing: np.ndarray


def _vectors(name: str, x: np.ndarray) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"expected {name} as (n, 3) float array, got {a.shape}")
    return a


def orthographic_rays(pose: Pose, image_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model-space rays (origins (r, 3) cm, unit directions (r, 3)) through image points.

    image_xy : (r, 2) pixels. The rays start ``RAY_START_CM`` in front of the model's origin
    and point away from the camera, so the first hit is the surface the camera sees.
    """
    xy = np.asarray(image_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"expected image points as (r, 2) float array, got {xy.shape}")
    image = np.column_stack([xy, np.full(len(xy), pose.translation[2])])
    direction = pose.rotation[2]  # R.T @ (0, 0, 1): image +z in model space
    origins = pose.inverse(image) - RAY_START_CM * direction
    return origins, np.broadcast_to(direction, origins.shape).copy()


def moller_trumbore(
    origins: np.ndarray, directions: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairwise ray-triangle intersection (Moller and Trumbore 1997), all arrays (p, 3).

    Returns (hit (p,) bool, t (p,), u (p,), v (p,)): the point is origin + t * direction =
    v0 + u * e1 + v * e2. Both faces count; rays parallel to the plane miss.
    """
    p = np.cross(directions, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > _EPS
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", directions, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    tol = 1e-9  # a ray through an edge or a vertex still hits
    hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t >= 0)
    return hit, t, u, v


class RayCaster:
    """Nearest hits of rays on a triangle mesh whose vertices may move between casts.

    triangles : (m, 3) vertex indices (counter-clockwise seen from outside, as
    ``facewire.models.mesh.FaceMesh``); vertices : (n, 3) the rest positions the tree is built on.
    Call :meth:`update` with new vertex positions (same topology), then :meth:`cast`.
    """

    def __init__(self, triangles: np.ndarray, vertices: np.ndarray) -> None:
        tri = np.asarray(triangles, dtype=np.int64)
        if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
            raise ValueError(f"expected (m, 3) triangles, got {tri.shape}")
        verts = _vectors("vertices", vertices)
        if tri.min() < 0 or tri.max() >= len(verts):
            raise ValueError(f"triangle index out of range for {len(verts)} vertices")
        self.triangles = tri
        self.n_vertices = len(verts)
        self._build(verts[tri].mean(axis=1))
        self.update(verts)

    # -- the tree ------------------------------------------------------------------------

    def _build(self, centroids: np.ndarray) -> None:
        """Median splits along the widest axis; nodes numbered level by level."""
        order = np.arange(len(centroids))
        # Each node: (start, end) into ``order``; children appended level by level.
        starts, ends, lefts, rights, levels = [0], [len(order)], [-1], [-1], [0]
        frontier = [0]
        while frontier:
            nxt = []
            for node in frontier:
                a, b = starts[node], ends[node]
                if b - a <= LEAF_SIZE:
                    continue
                idx = order[a:b]
                c = centroids[idx]
                axis = int(np.argmax(np.ptp(c, axis=0)))
                mid = (b - a) // 2
                part = np.argpartition(c[:, axis], mid)
                order[a:b] = idx[part]
                for lo, hi in ((a, a + mid), (a + mid, b)):
                    starts.append(lo)
                    ends.append(hi)
                    lefts.append(-1)
                    rights.append(-1)
                    levels.append(levels[node] + 1)
                    nxt.append(len(starts) - 1)
                lefts[node], rights[node] = nxt[-2], nxt[-1]
            frontier = nxt
        self._order = order
        self._start = np.array(starts)
        self._end = np.array(ends)
        self._left = np.array(lefts)
        self._right = np.array(rights)
        self._leaf = self._left < 0
        level = np.array(levels)
        # Internal nodes of each level, deepest first: the order refitting goes in.
        self._refit_levels = [
            np.flatnonzero((level == d) & ~self._leaf) for d in range(level.max(), -1, -1)
        ]
        leaves = np.flatnonzero(self._leaf)
        self._leaf_nodes = leaves
        # Triangles of each leaf, padded with -1 to LEAF_SIZE: (leaves, LEAF_SIZE).
        slots = np.full((len(self._start), LEAF_SIZE), -1, dtype=np.int64)
        for node in leaves.tolist():
            tris = order[self._start[node] : self._end[node]]
            slots[node, : len(tris)] = tris
        self._slots = slots
        self.depth = int(level.max()) + 1
        logger.debug(
            "ray caster: %d triangles, %d nodes, depth %d", len(order), len(starts), self.depth
        )

    def update(self, vertices: np.ndarray) -> None:
        """New vertex positions (n, 3): triangles and the tree's boxes follow them."""
        v = _vectors("vertices", vertices)
        if len(v) != self.n_vertices:
            raise ValueError(f"expected ({self.n_vertices}, 3) vertices, got {v.shape}")
        corners = v[self.triangles]  # (m, 3, 3)
        self._v0 = corners[:, 0]
        self._e1 = corners[:, 1] - corners[:, 0]
        self._e2 = corners[:, 2] - corners[:, 0]
        normal = np.cross(self._e1, self._e2)
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        self._normal = normal / np.where(norm > 0, norm, 1.0)
        tri_lo, tri_hi = corners.min(axis=1), corners.max(axis=1)
        n_nodes = len(self._start)
        lo = np.empty((n_nodes, 3))
        hi = np.empty((n_nodes, 3))
        leaves = self._leaf_nodes
        slots = self._slots[leaves]
        # Padding slots (-1) repeat the leaf's first triangle, which changes no bound.
        slots = np.where(slots >= 0, slots, slots[:, :1])
        lo[leaves] = tri_lo[slots].min(axis=1)
        hi[leaves] = tri_hi[slots].max(axis=1)
        for nodes in self._refit_levels:
            left, right = self._left[nodes], self._right[nodes]
            lo[nodes] = np.minimum(lo[left], lo[right])
            hi[nodes] = np.maximum(hi[left], hi[right])
        self._lo, self._hi = lo, hi

    # -- casting -------------------------------------------------------------------------

    def candidates(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(p, 2) (ray, triangle) pairs whose leaf box the ray passes through."""
        o = _vectors("ray origins", origins)
        d = _vectors("ray directions", directions)
        safe = np.where(np.abs(d) > _EPS, d, _EPS)
        inv = 1.0 / safe
        rays = np.arange(len(o))
        nodes = np.zeros(len(o), dtype=np.int64)
        found_rays, found_nodes = [], []
        while len(rays):
            t1 = (self._lo[nodes] - o[rays]) * inv[rays]
            t2 = (self._hi[nodes] - o[rays]) * inv[rays]
            near = np.minimum(t1, t2).max(axis=1)
            far = np.maximum(t1, t2).min(axis=1)
            through = far >= np.maximum(near, 0.0)
            rays, nodes = rays[through], nodes[through]
            leaf = self._leaf[nodes]
            found_rays.append(rays[leaf])
            found_nodes.append(nodes[leaf])
            inner = ~leaf
            rays = np.repeat(rays[inner], 2)
            nodes = np.column_stack([self._left[nodes[inner]], self._right[nodes[inner]]]).ravel()
        ray_ids = np.concatenate(found_rays)
        slots = self._slots[np.concatenate(found_nodes)]  # (leaves hit, LEAF_SIZE)
        pairs_ray = np.repeat(ray_ids, LEAF_SIZE)
        pairs_tri = slots.ravel()
        keep = pairs_tri >= 0
        return np.column_stack([pairs_ray[keep], pairs_tri[keep]])

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Nearest hit of each ray (origins, unit directions: (r, 3), model space)."""
        o = _vectors("ray origins", origins)
        d = _vectors("ray directions", directions)
        if o.shape != d.shape:
            raise ValueError(f"ray origins {o.shape} and directions {d.shape} differ")
        pairs = self.candidates(o, d)
        return self._nearest(o, d, pairs[:, 0], pairs[:, 1])

    def cast_all(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """:meth:`cast` by testing every triangle (no tree): the reference it must equal."""
        o = _vectors("ray origins", origins)
        d = _vectors("ray directions", directions)
        m = len(self.triangles)
        rays = np.repeat(np.arange(len(o)), m)
        tris = np.tile(np.arange(m), len(o))
        return self._nearest(o, d, rays, tris)

    def _nearest(self, o: np.ndarray, d: np.ndarray, rays: np.ndarray, tris: np.ndarray) -> RayHits:
        r = len(o)
        hit, t, u, v = moller_trumbore(
            o[rays], d[rays], self._v0[tris], self._e1[tris], self._e2[tris]
        )
        rays, tris, t, u, v = rays[hit], tris[hit], t[hit], u[hit], v[hit]
        # The nearest hit per ray: sort by (ray, t) and keep each ray's first.
        order = np.lexsort((t, rays))
        rays, tris, t, u, v = rays[order], tris[order], t[order], u[order], v[order]
        first = np.ones(len(rays), dtype=bool)
        first[1:] = rays[1:] != rays[:-1]
        rays, tris, t, u, v = rays[first], tris[first], t[first], u[first], v[first]
        out_hit = np.zeros(r, dtype=bool)
        out_hit[rays] = True
        triangle = np.full(r, -1, dtype=np.int64)
        triangle[rays] = tris
        distance = np.full(r, np.inf)
        distance[rays] = t
        bary = np.full((r, 3), np.nan)
        bary[rays] = np.column_stack([1.0 - u - v, u, v])
        points = np.full((r, 3), np.nan)
        points[rays] = o[rays] + t[:, None] * d[rays]
        facing = np.full(r, np.nan)
        facing[rays] = -np.einsum("ij,ij->i", self._normal[tris], d[rays])
        return RayHits(out_hit, points, triangle, bary, distance, facing)
