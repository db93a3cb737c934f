"""Geometry deformation elements (GDEs): local RBF deformations around a control point.

Noh, Fidaleo and Neumann, "Animated deformations with radial basis functions", section 2.
A GDE is a control point, an influence region found by breadth-first search over mesh
edges, stationary anchors on the region's boundary and a Hardy multiquadric RBF system
(Eq. 1-3) regularised by lambda (Eq. 5) and LU-factored once.

We interpolate *displacements*: the control point's target is its displacement ``d`` and
every anchor's is zero, so ``d = 0`` leaves the mesh exactly unchanged. The anchors are
fixed, hence each region vertex moves by ``w_v * d`` with a scalar weight ``w_v``
precomputed at load time; :class:`GdeSet` stacks those weights into one sparse matrix.

Anchors are the *first vertices outside* the region (the BFS frontier), not its leaf
layer: the motion is then pinned to zero exactly where the never-moving outside mesh
begins, every vertex the metric admits may move, and a one-vertex region reduces to
moving that vertex (the paper's limiting case), which a leaf-layer anchor would forbid.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from facewire.models.mesh import FaceMesh

logger = logging.getLogger(__name__)

Metric = Literal["edges", "euclidean"]


class GdeSpecLike(Protocol):
    """Anything naming a GDE like ``facewire.models.rig.GdeSpec`` (read-only attributes)."""

    @property
    def name(self) -> str: ...
    @property
    def control_vertex(self) -> int: ...
    @property
    def size(self) -> float: ...
    @property
    def metric(self) -> str: ...


@dataclass(frozen=True)
class GdeDef:
    """A plain GDE specification (the same fields as ``facewire.models.rig.GdeSpec``).

    size : edge depth for ``metric="edges"``, centimetres for ``"euclidean"``
    """

    name: str
    control_vertex: int
    size: float
    metric: str = "edges"


@dataclass(frozen=True)
class Expression:
    """A named set of GDEs moved together by one parameter (seed 002 section 2.5).

    targets : GDE name -> (3,) displacement in cm, model space, reached at d = 1
    """

    name: str
    targets: Mapping[str, np.ndarray] = field(default_factory=dict)


def hardy(r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Hardy multiquadric ``sqrt(r^2 + s^2)`` (broadcasts)."""
    return np.sqrt(np.square(r) + np.square(s))


def mouth_seam_edges(
    mesh: FaceMesh, inner_ring: Sequence[int], corner_a: int, corner_b: int
) -> np.ndarray:
    """(k, 2) mesh edges that bridge the closed mouth between upper and lower lip.

    The canonical mesh fills the mouth with triangles between inner-lip vertices, so
    an edge-depth search would leak from one lip to the other. ``inner_ring`` is the
    closed inner lip loop; ``corner_a``/``corner_b`` (ring members) split it into two
    arcs; edges joining the two arcs' interiors are returned.
    """
    ring = [int(v) for v in inner_ring]
    if corner_a not in ring or corner_b not in ring:
        raise ValueError(f"corners {corner_a}, {corner_b} must lie on the inner ring {ring}")
    ia, ib = sorted((ring.index(corner_a), ring.index(corner_b)))
    arc1 = set(ring[ia + 1 : ib])
    arc2 = set(ring[ib + 1 :] + ring[:ia])
    e = mesh.edges
    in1 = np.isin(e, list(arc1))
    in2 = np.isin(e, list(arc2))
    cross = (in1[:, 0] & in2[:, 1]) | (in2[:, 0] & in1[:, 1])
    return e[cross]


def _neighbour_lists(mesh: FaceMesh, cut_edges: np.ndarray | None) -> sp.csr_matrix:
    adj = mesh.adjacency.tolil(copy=True)
    if cut_edges is not None and len(cut_edges):
        cut = np.asarray(cut_edges, dtype=np.int64).reshape(-1, 2)
        adj[cut[:, 0], cut[:, 1]] = 0
        adj[cut[:, 1], cut[:, 0]] = 0
    out = adj.tocsr()
    out.eliminate_zeros()
    return out


def _order_along_boundary(points: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Indices sorting boundary points by angle around ``centre`` in the tangent plane."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    rel = points - centre
    return np.argsort(np.arctan2(rel @ e2, rel @ e1), kind="stable")


def sample_evenly(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of at most ``count`` points spread evenly by arc length along a closed loop.

    points : (b, 3) loop in order. For each target arc length k * L / count the first
    point at or beyond it is taken, so consecutive picks are at most L / count plus one
    loop segment apart.
    """
    b = len(points)
    if b <= count:
        return np.arange(b)
    seg = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg[:-1])])
    total = cum[-1] + seg[-1]
    targets = np.arange(count) * (total / count)
    picks = np.minimum(np.searchsorted(cum, targets - 1e-12 * total), b - 1)
    return np.unique(picks)


class Gde:
    """One geometry deformation element on ``mesh`` (seed 002 section 2).

    control_point : vertex index, or (3,) point in cm (model space) near the surface
    size : edge depth (int-valued, ``metric="edges"``) or radius in cm (``"euclidean"``)
    max_anchors : the boundary is sampled down to this many anchors
    lam : Tikhonov term added to H (Eq. 5); 0 interpolates exactly
    cut_edges : (k, 2) mesh edges the search must not cross (e.g. :func:`mouth_seam_edges`)

    Attributes: ``root`` (nearest vertex), ``region`` (r,) vertex indices that may move,
    ``anchors`` (a,) boundary vertices outside the region, ``features`` (1 + a, 3) rest
    positions (control point first), ``stiffness`` (1 + a,) s_i of Eq. 3, ``weights`` (r,).
    """

    def __init__(
        self,
        mesh: FaceMesh,
        control_point: int | np.ndarray | Sequence[float],
        size: float,
        metric: Metric | str = "edges",
        max_anchors: int = 20,
        lam: float = 0.01,
        cut_edges: np.ndarray | None = None,
    ) -> None:
        if metric not in ("edges", "euclidean"):
            raise ValueError(f"metric must be 'edges' or 'euclidean', got {metric!r}")
        if not size >= 0:
            raise ValueError(f"size must be >= 0, got {size}")
        if max_anchors < 1:
            raise ValueError(f"max_anchors must be >= 1, got {max_anchors}")
        if lam < 0:
            raise ValueError(f"lam must be >= 0, got {lam}")
        verts = mesh.vertices
        if isinstance(control_point, (int, np.integer)):
            if not 0 <= control_point < len(verts):
                raise ValueError(f"control vertex {control_point} out of range 0..{len(verts) - 1}")
            self.root = int(control_point)
            self.control_point = verts[self.root].copy()
        else:
            cp = np.asarray(control_point, dtype=np.float64)
            if cp.shape != (3,):
                raise ValueError(f"expected control point (3,) or vertex index, got {cp.shape}")
            self.control_point = cp
            self.root = int(np.argmin(np.linalg.norm(verts - cp, axis=1)))
        self.size = float(size)
        self.metric = metric
        self.lam = float(lam)
        self.n_vertices = len(verts)

        self.region, frontier = self._search(mesh, cut_edges)
        normal = mesh.vertex_normals()[self.root]
        order = _order_along_boundary(verts[frontier], self.control_point, normal)
        boundary = frontier[order]
        self.boundary = boundary
        self.anchors = boundary[sample_evenly(verts[boundary], max_anchors)]
        self.features = np.vstack([self.control_point[None], verts[self.anchors]])

        # Eq. 3: s_i = distance to the nearest other feature point.
        dist = np.linalg.norm(self.features[:, None] - self.features[None], axis=2)
        if len(self.features) > 1:
            off = dist + np.diag(np.full(len(dist), np.inf))
            self.stiffness = off.min(axis=1)
        else:
            self.stiffness = np.ones(1)  # no anchors (closed component): any s works
        # Eq. 2: row j = feature j evaluated, column i = basis of feature i with s_i.
        self.h_matrix = hardy(dist, self.stiffness[None, :])
        self._lu = sla.lu_factor(self.h_matrix + self.lam * np.eye(len(dist)))
        # d enters the right-hand side only in row 0, so c = A^-1 e_0 d^T.
        e0 = np.zeros(len(dist))
        e0[0] = 1.0
        self.unit_coefficients = sla.lu_solve(self._lu, e0)
        self.region_positions = verts[self.region].copy()
        self.weights = self.basis(self.region_positions) @ self.unit_coefficients
        logger.debug(
            "GDE root %d: %d region vertices, %d boundary, %d anchors",
            self.root,
            len(self.region),
            len(boundary),
            len(self.anchors),
        )

    def _search(
        self, mesh: FaceMesh, cut_edges: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """BFS from the root: (region, first vertices outside it), both sorted."""
        adj = _neighbour_lists(mesh, cut_edges)
        verts = mesh.vertices
        depth = {self.root: 0}
        region = [self.root]  # the root always moves, even if the point lies off it
        frontier: set[int] = set()
        queue = deque([self.root])
        while queue:
            u = queue.popleft()
            for v in adj.indices[adj.indptr[u] : adj.indptr[u + 1]]:
                v = int(v)
                if v in depth or v in frontier:
                    continue
                if self.metric == "edges":
                    inside = depth[u] + 1 <= self.size
                else:
                    inside = bool(np.linalg.norm(verts[v] - self.control_point) < self.size)
                if inside:
                    depth[v] = depth[u] + 1
                    region.append(v)
                    queue.append(v)
                else:
                    frontier.add(v)
        return np.array(sorted(region), dtype=np.int64), np.array(sorted(frontier), dtype=np.int64)

    def basis(self, points: np.ndarray) -> np.ndarray:
        """(p, 1 + a) Hardy basis values h_i(|x - x_i|) at ``points`` (p, 3)."""
        r = np.linalg.norm(points[:, None, :] - self.features[None], axis=2)
        return hardy(r, self.stiffness[None, :])

    def solve(self, d: np.ndarray) -> np.ndarray:
        """(1 + a, 3) RBF coefficients c of Eq. 5 for control displacement ``d`` (3,) cm.

        Back-substitution through the LU factors computed at construction.
        """
        d = np.asarray(d, dtype=np.float64)
        if d.shape != (3,):
            raise ValueError(f"expected displacement (3,), got {d.shape}")
        rhs = np.zeros((len(self.features), 3))
        rhs[0] = d
        return sla.lu_solve(self._lu, rhs)

    def displacements(self, d: np.ndarray) -> np.ndarray:
        """(r, 3) displacements of ``region`` vertices for control displacement ``d`` (3,).

        The per-frame path of the paper (solve, then evaluate Eq. 1); equals
        ``weights[:, None] * d``.
        """
        return self.basis(self.region_positions) @ self.solve(d)


class GdeSet:
    """Many GDEs on one mesh, applied together as one sparse product.

    specs : objects with ``name``, ``control_vertex``, ``size``, ``metric`` (e.g.
    :class:`GdeDef` or ``facewire.models.rig.GdeSpec``); their order fixes the row order of the
    (g, 3) displacement arrays. Overlapping elements add their displacements.
    """

    def __init__(
        self,
        mesh: FaceMesh,
        specs: Iterable[GdeSpecLike],
        max_anchors: int = 20,
        lam: float = 0.01,
        cut_edges: np.ndarray | None = None,
    ) -> None:
        specs = list(specs)
        self.names = [s.name for s in specs]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate GDE names in {self.names}")
        self.n_vertices = mesh.n_vertices
        self.elements = [
            Gde(mesh, int(s.control_vertex), s.size, s.metric, max_anchors, lam, cut_edges)
            for s in specs
        ]
        self._index = {name: i for i, name in enumerate(self.names)}
        rows = [g.region for g in self.elements]
        cols = [np.full(len(g.region), j) for j, g in enumerate(self.elements)]
        vals = [g.weights for g in self.elements]
        g = len(self.elements)
        if g:
            self.matrix = sp.csr_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                shape=(self.n_vertices, g),
            )
        else:
            self.matrix = sp.csr_matrix((self.n_vertices, 0))
        logger.debug("GdeSet: %d elements, %d weights", g, self.matrix.nnz)

    @classmethod
    def from_rig(
        cls,
        mesh: FaceMesh,
        rig: Any,
        max_anchors: int = 20,
        lam: float = 0.01,
        cut_mouth: bool = True,
    ) -> GdeSet:
        """Build from ``rig.gdes``; with ``cut_mouth`` the search never crosses the closed mouth.

        The seam is found from ``rig.lips``: the inner ring (last contour) split at the ring
        vertices nearest the left and right markers. Rig sizes are for the mesh the rig was
        written for; scale edge depths yourself for a subdivided mesh.
        """
        cut = None
        if cut_mouth and getattr(rig, "lips", None) is not None:
            cut = rig_mouth_seam(mesh, rig.lips)
        return cls(mesh, rig.gdes, max_anchors, lam, cut)

    def __len__(self) -> int:
        return len(self.elements)

    def index(self, name: str) -> int:
        """Row of GDE ``name`` in the (g, 3) displacement arrays."""
        try:
            return self._index[name]
        except KeyError:
            raise ValueError(f"unknown GDE {name!r}, known: {self.names}") from None

    def displacement_field(self, displacements: np.ndarray) -> np.ndarray:
        """(n, 3) per-vertex displacement in cm for control displacements (g, 3) cm."""
        d = np.asarray(displacements, dtype=np.float64)
        if d.shape != (len(self.elements), 3):
            raise ValueError(f"expected ({len(self.elements)}, 3) displacements, got {d.shape}")
        return np.asarray(self.matrix @ d)

    def deform(self, base_vertices: np.ndarray, displacements: np.ndarray) -> np.ndarray:
        """(n, 3) ``base_vertices`` plus the summed displacement of every element."""
        base = np.asarray(base_vertices, dtype=np.float64)
        if base.shape != (self.n_vertices, 3):
            raise ValueError(f"expected ({self.n_vertices}, 3) vertices, got {base.shape}")
        return base + self.displacement_field(displacements)

    def as_flat_matrix(self) -> sp.csr_matrix:
        """(3n, 3g) sparse matrix acting on row-major flattened displacements."""
        return sp.kron(self.matrix, sp.identity(3), format="csr")

    def expression_displacements(
        self, expressions: Iterable[Expression], weights: Mapping[str, float]
    ) -> np.ndarray:
        """(g, 3) control displacements for expression parameters d in [0, 1].

        Each expression contributes d times its maximum displacements; expressions
        absent from ``weights`` contribute nothing.
        """
        out = np.zeros((len(self.elements), 3))
        by_name = {e.name: e for e in expressions}
        for name, d in weights.items():
            if name not in by_name:
                raise ValueError(f"unknown expression {name!r}, known: {sorted(by_name)}")
            if not 0.0 <= d <= 1.0:
                raise ValueError(f"expression {name!r} weight must be in [0, 1], got {d}")
            for gde, target in by_name[name].targets.items():
                t = np.asarray(target, dtype=np.float64)
                if t.shape != (3,):
                    raise ValueError(
                        f"expression {name!r} target {gde!r}: expected (3,), got {t.shape}"
                    )
                out[self.index(gde)] += d * t
        return out


def rig_mouth_seam(mesh: FaceMesh, lips: Any) -> np.ndarray:
    """:func:`mouth_seam_edges` for a ``facewire.models.rig.LipRig`` (markers + four contours)."""
    inner = [int(v) for v in lips.contours[-1]]
    ring_pos = mesh.vertices[inner]

    def nearest(marker: str) -> int:
        p = mesh.vertices[int(lips.markers[marker])]
        return inner[int(np.argmin(np.linalg.norm(ring_pos - p, axis=1)))]

    return mouth_seam_edges(mesh, inner, nearest("left"), nearest("right"))
