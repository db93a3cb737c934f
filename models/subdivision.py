"""Loop subdivision of a FaceMesh as a sparse linear operator.

One level splits every triangle into four. The fine mesh keeps the n coarse vertices first,
in their original order (so rig indices, i.e. MediaPipe landmark numbers, still name the same
points), followed by one new vertex per coarse edge in the order of ``mesh.edges``.

Rules (Loop 1987, with the usual boundary rules of Hoppe et al. 1994):

- interior edge (a, b) with opposite vertices c, d: 3/8 (a + b) + 1/8 (c + d)
- boundary edge (a, b): 1/2 (a + b)
- interior vertex of valence k: (1 - k beta) v + beta * sum(neighbours),
  beta = (5/8 - (3/8 + 1/4 cos(2 pi / k))^2) / k
- boundary vertex with boundary neighbours b1, b2: 3/4 v + 1/8 (b1 + b2)
- a vertex on more or fewer than two boundary edges (a non-manifold corner) stays put.

Every rule is an affine combination, so rows of the operator sum to 1. UVs are not smoothed:
coarse vertices keep theirs and a new vertex gets the midpoint of its edge's UVs, so the
texture atlas is not pulled around by the smoothing.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from facewire.models.mesh import FaceMesh

logger = logging.getLogger(__name__)


def loop_subdivide(mesh: FaceMesh, levels: int = 1) -> tuple[FaceMesh, sp.csr_matrix]:
    """Subdivide ``mesh`` ``levels`` times.

    Returns (fine, S) with S a (n_fine, n_coarse) csr_matrix such that
    ``fine.vertices == S @ mesh.vertices`` (so per-frame deformed coarse vertices can be
    refined with one sparse product). ``fine.vertices[:n_coarse]`` are the smoothed coarse
    vertices, in the coarse order. ``levels == 0`` returns the mesh and the identity.
    """
    if not isinstance(levels, int) or isinstance(levels, bool) or levels < 0:
        raise ValueError(f"levels must be a non-negative integer, got {levels!r}")
    total = sp.identity(mesh.n_vertices, format="csr")
    fine = mesh
    for _ in range(levels):
        step, triangles, uvs = _loop_step(fine)
        fine = FaceMesh(step @ fine.vertices, triangles, uvs)
        total = (step @ total).tocsr()
    logger.debug(
        "loop subdivision x%d: %d -> %d vertices, %d triangles",
        levels,
        mesh.n_vertices,
        fine.n_vertices,
        len(fine.triangles),
    )
    return fine, total


def _loop_step(mesh: FaceMesh) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """One level: (S, fine triangles, fine uvs)."""
    n = mesh.n_vertices
    tri = mesh.triangles
    edges = mesh.edges
    ne = len(edges)

    # Edge index of each triangle side k = (tri[:, k], tri[:, k+1]), opposite corner tri[:, k+2].
    keys = edges[:, 0] * n + edges[:, 1]
    side_a = tri
    side_b = np.roll(tri, -1, axis=1)
    opposite = np.roll(tri, -2, axis=1)
    lo, hi = np.minimum(side_a, side_b), np.maximum(side_a, side_b)
    side_edge = np.searchsorted(keys, lo * n + hi)  # (m, 3)
    faces_per_edge = np.bincount(side_edge.ravel(), minlength=ne)
    boundary_edge = faces_per_edge != 2

    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def put(r: np.ndarray, c: np.ndarray, w: np.ndarray | float) -> None:
        rows.append(np.asarray(r, dtype=np.int64))
        cols.append(np.asarray(c, dtype=np.int64))
        vals.append(np.broadcast_to(np.asarray(w, dtype=np.float64), np.shape(r)))

    # Odd (edge) vertices.
    e_rows = n + np.arange(ne)
    end_w = np.where(boundary_edge, 0.5, 3.0 / 8.0)
    put(e_rows, edges[:, 0], end_w)
    put(e_rows, edges[:, 1], end_w)
    interior_sides = ~boundary_edge[side_edge]
    put(n + side_edge[interior_sides], opposite[interior_sides], 1.0 / 8.0)

    # Even (original) vertices.
    adj = mesh.adjacency
    valence = np.diff(adj.indptr)
    b_edges = edges[boundary_edge]
    b_count = np.bincount(b_edges.ravel(), minlength=n)
    interior = (b_count == 0) & (valence > 0)
    smooth_boundary = b_count == 2
    fixed = ~interior & ~smooth_boundary

    k = valence[interior].astype(np.float64)
    beta = (5.0 / 8.0 - (3.0 / 8.0 + 0.25 * np.cos(2.0 * np.pi / k)) ** 2) / k
    idx = np.flatnonzero(interior)
    put(idx, idx, 1.0 - k * beta)
    nb = adj[idx].tocoo()
    put(idx[nb.row], nb.col, beta[nb.row])

    idx = np.flatnonzero(smooth_boundary)
    put(idx, idx, 0.75)
    put(b_edges[:, 0], b_edges[:, 1], np.where(smooth_boundary[b_edges[:, 0]], 0.125, 0.0))
    put(b_edges[:, 1], b_edges[:, 0], np.where(smooth_boundary[b_edges[:, 1]], 0.125, 0.0))

    idx = np.flatnonzero(fixed)
    put(idx, idx, 1.0)
    if idx.size:
        logger.debug("loop subdivision: %d non-manifold/isolated vertices kept fixed", idx.size)

    s = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n + ne, n),
    )
    s.eliminate_zeros()

    # Each triangle (a, b, c) with edge vertices ab, bc, ca -> four, same orientation.
    a, b, c = tri.T
    ab, bc, ca = (n + side_edge).T
    triangles = np.concatenate(
        [
            np.stack([a, ab, ca], axis=1),
            np.stack([ab, b, bc], axis=1),
            np.stack([ca, bc, c], axis=1),
            np.stack([ab, bc, ca], axis=1),
        ]
    )
    uvs = np.concatenate([mesh.uvs, 0.5 * (mesh.uvs[edges[:, 0]] + mesh.uvs[edges[:, 1]])])
    return s, triangles, uvs
