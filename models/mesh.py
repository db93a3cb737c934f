"""Triangle meshes with per-vertex UVs, and the bundled canonical face mesh."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np
import scipy.sparse as sp

logger = logging.getLogger(__name__)

CANONICAL_VERTEX_COUNT = 468


@dataclass(frozen=True, eq=False)
class FaceMesh:
    """A triangle mesh with one UV per vertex.

    vertices : (n, 3) float64, centimetres, model space
    triangles : (m, 3) int64, vertex indices, counter-clockwise seen from outside
    uvs : (n, 2) float64, texture coordinates, OpenGL convention (v = 0 at the bottom)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        t = np.asarray(self.triangles, dtype=np.int64)
        uv = np.asarray(self.uvs, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"expected (n, 3) vertices, got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"expected (m, 3) triangles, got {t.shape}")
        if uv.shape != (len(v), 2):
            raise ValueError(f"expected ({len(v)}, 2) uvs, got {uv.shape}")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError(f"triangle index out of range 0..{len(v) - 1}")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "triangles", t)
        object.__setattr__(self, "uvs", uv)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def with_vertices(self, vertices: np.ndarray) -> FaceMesh:
        """The same topology and UVs with other vertex positions."""
        return FaceMesh(vertices, self.triangles, self.uvs)

    @cached_property
    def edges(self) -> np.ndarray:
        """(e, 2) int64 unique undirected edges, smaller index first."""
        t = self.triangles
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        e.sort(axis=1)
        return np.unique(e, axis=0)

    @cached_property
    def outline(self) -> np.ndarray:
        """(k,) int64 vertex indices of the longest boundary loop, in order around it: on the
        canonical face mesh, the face's outer contour (forehead, cheeks, chin)."""
        t = self.triangles
        directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        undirected = np.sort(directed, axis=1)
        _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
        # An edge used by one triangle is on a boundary; follow the triangles' winding.
        following = {int(a): int(b) for a, b in directed[counts[inverse.ravel()] == 1]}
        loops: list[list[int]] = []
        while following:
            start, v = following.popitem()
            loop = [start]
            while v != start and v in following:
                loop.append(v)
                v = following.pop(v)
            loops.append(loop)
        if not loops:
            raise ValueError("the mesh has no boundary")
        return np.asarray(max(loops, key=len), dtype=np.int64)

    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        """(n, n) symmetric 0/1 vertex adjacency over mesh edges."""
        e = self.edges
        n = self.n_vertices
        data = np.ones(2 * len(e))
        rows = np.concatenate([e[:, 0], e[:, 1]])
        cols = np.concatenate([e[:, 1], e[:, 0]])
        return sp.csr_matrix((data, (rows, cols)), shape=(n, n))

    def neighbours(self, i: int) -> np.ndarray:
        """Indices of the vertices sharing an edge with vertex i."""
        a = self.adjacency
        return a.indices[a.indptr[i] : a.indptr[i + 1]]

    @cached_property
    def _areas(self) -> np.ndarray:
        v, t = self.vertices, self.triangles
        return 0.5 * np.linalg.norm(
            np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1
        )

    def facing_share(self, points: np.ndarray, min_facing: float = 0.15) -> float:
        """The share of the face, by this mesh's triangle areas, that ``points`` (n, 3), the
        face in image space (z away from the camera), turn towards the camera: triangles
        whose normal is within arccos(``min_facing``) of the view direction. A face looking
        into the camera shows 0.85-0.9 of itself this way, one in profile about 0.55."""
        p, t = np.asarray(points, dtype=np.float64), self.triangles
        normal = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
        length = np.linalg.norm(normal, axis=1)
        facing = -normal[:, 2] > min_facing * length
        return float(self._areas[facing].sum() / self._areas.sum())

    def vertex_normals(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) unit area-weighted vertex normals (of ``vertices`` if given)."""
        v = self.vertices if vertices is None else vertices
        t = self.triangles
        fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, t[:, k], fn)
        norm = np.linalg.norm(vn, axis=1, keepdims=True)
        return vn / np.where(norm > 0, norm, 1.0)


def load_obj(path: str | Path) -> FaceMesh:
    """Read a triangle OBJ with ``v``, optional ``vt`` and ``f v/vt`` lines.

    UVs must be one per vertex (as in the canonical mesh: ``f a/a b/b c/c``); a file
    without ``vt`` gets zero UVs. Faces with more than three corners are fanned.
    """
    vertices: list[list[float]] = []
    uvs: list[list[float]] = []
    tris: list[list[int]] = []
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read mesh {path}: {exc.strerror or exc}") from exc
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                vertices.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                uvs.append([float(x) for x in parts[1:3]])
            elif parts[0] == "f":
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
                tris.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}:{lineno}: malformed OBJ line {line!r}") from exc
    if not vertices:
        raise ValueError(f"{path}: no vertices")
    uv = np.asarray(uvs, dtype=np.float64) if len(uvs) == len(vertices) else None
    if uv is None:
        if uvs:
            logger.debug("%s: %d UVs for %d vertices, ignoring UVs", path, len(uvs), len(vertices))
        uv = np.zeros((len(vertices), 2))
    return FaceMesh(np.asarray(vertices), np.asarray(tris, dtype=np.int64).reshape(-1, 3), uv)


def save_obj(mesh: FaceMesh, path: str | Path) -> None:
    """Write ``mesh`` as OBJ, one UV per vertex, keeping vertex order."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uvs]
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in mesh.triangles + 1]
    Path(path).write_text("\n".join(lines) + "\n")


def data_path(name: str) -> Path:
    """Path of a file shipped in models/data."""
    return Path(str(resources.files("facewire.models") / "data" / name))


def load_canonical() -> FaceMesh:
    """MediaPipe's canonical face mesh: 468 vertices, vertex i = landmark i."""
    mesh = load_obj(data_path("canonical_face_mesh.obj"))
    assert mesh.n_vertices == CANONICAL_VERTEX_COUNT
    return mesh
