import numpy as np
import pytest

from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.subdivision import loop_subdivide


def euler(mesh: FaceMesh) -> int:
    return mesh.n_vertices - len(mesh.edges) + len(mesh.triangles)


def grid(nx: int = 5, ny: int = 4) -> FaceMesh:
    """A planar triangulated grid on z = 0.3 x - 0.2 y + 1 (it has a boundary)."""
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
    x, y = x.ravel(), y.ravel()
    v = np.stack([x, y, 0.3 * x - 0.2 * y + 1.0], axis=1)
    tris = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a = j * nx + i
            tris += [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]
    uv = np.stack([x / (nx - 1), y / (ny - 1)], axis=1)
    return FaceMesh(v, np.array(tris), uv)


def octahedron() -> FaceMesh:
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    t = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )
    return FaceMesh(v, t, np.zeros((6, 2)))


@pytest.fixture(scope="module")
def canonical() -> FaceMesh:
    return load_canonical()


@pytest.mark.parametrize("levels,n_fine", [(1, 1833), (2, 7257)])
def test_canonical_counts_and_operator(canonical, levels, n_fine):
    fine, s = loop_subdivide(canonical, levels)
    assert fine.n_vertices == n_fine
    assert s.shape == (n_fine, canonical.n_vertices)
    assert len(fine.triangles) == 4**levels * len(canonical.triangles)
    np.testing.assert_allclose(np.asarray(s.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert s.data.min() >= 0.0
    np.testing.assert_allclose(s @ canonical.vertices, fine.vertices, atol=1e-12)
    assert euler(fine) == euler(canonical) == 1


def test_originals_first(canonical):
    fine, s = loop_subdivide(canonical, 2)
    n = canonical.n_vertices
    coarse_part = s[:n].toarray()
    assert np.array_equal(coarse_part.argmax(axis=1), np.arange(n))
    np.testing.assert_array_equal(fine.uvs[:n], canonical.uvs)
    # smoothing moves a landmark by millimetres, never to another landmark's place
    moved = np.linalg.norm(fine.vertices[:n] - canonical.vertices, axis=1)
    assert moved.max() < 0.5


def test_orientation_kept(canonical):
    fine, _ = loop_subdivide(canonical, 1)
    n = canonical.n_vertices
    dots = np.sum(fine.vertex_normals()[:n] * canonical.vertex_normals(), axis=1)
    assert dots.min() > 0.5


def test_uvs_midpoints_and_in_range(canonical):
    fine, _ = loop_subdivide(canonical, 1)
    n = canonical.n_vertices
    e = canonical.edges
    mid = 0.5 * (canonical.uvs[e[:, 0]] + canonical.uvs[e[:, 1]])
    np.testing.assert_allclose(fine.uvs[n:], mid)
    fine2, _ = loop_subdivide(canonical, 2)
    lo, hi = canonical.uvs.min(axis=0), canonical.uvs.max(axis=0)
    assert np.all(fine2.uvs >= lo - 1e-12) and np.all(fine2.uvs <= hi + 1e-12)


def test_planar_mesh_stays_planar():
    mesh = grid()
    fine, _ = loop_subdivide(mesh, 2)
    x, y, z = fine.vertices.T
    np.testing.assert_allclose(z, 0.3 * x - 0.2 * y + 1.0, atol=1e-12)
    assert euler(fine) == euler(mesh) == 1


def test_stencils():
    mesh = grid(5, 5)
    n = mesh.n_vertices
    _, s = loop_subdivide(mesh, 1)
    # centre vertex 12 of a 5x5 grid has valence 6: Loop's beta is 1/16
    row = s[12].toarray().ravel()
    assert row[12] == pytest.approx(10 / 16)
    np.testing.assert_allclose(row[mesh.neighbours(12)], 1 / 16)
    # boundary vertex 2 (bottom edge): 3/4 itself, 1/8 for boundary neighbours 1 and 3
    row = s[2].toarray().ravel()
    assert (row[2], row[1], row[3]) == pytest.approx((0.75, 0.125, 0.125))
    assert np.count_nonzero(row) == 3
    edges = [tuple(e) for e in mesh.edges]
    # boundary edge (0, 1): midpoint
    row = s[n + edges.index((0, 1))].toarray().ravel()
    assert (row[0], row[1], np.count_nonzero(row)) == pytest.approx((0.5, 0.5, 2))
    # interior edge (6, 12), opposite corners 7 and 11
    row = s[n + edges.index((6, 12))].toarray().ravel()
    assert (row[6], row[12], row[7], row[11]) == pytest.approx((3 / 8, 3 / 8, 1 / 8, 1 / 8))


def test_closed_mesh_shrinks_inside_hull():
    mesh = octahedron()
    fine, s = loop_subdivide(mesh, 3)
    assert euler(fine) == 2
    assert fine.n_vertices == 258
    # L1 norm <= 1 is the octahedron; Loop is a convex combination scheme
    assert np.abs(fine.vertices).sum(axis=1).max() <= 1.0 + 1e-12
    assert np.abs(fine.vertices).sum(axis=1).min() < 0.9


def test_levels_zero_and_bad_levels(canonical):
    fine, s = loop_subdivide(canonical, 0)
    assert fine is canonical
    assert np.array_equal(s.toarray(), np.eye(canonical.n_vertices))
    with pytest.raises(ValueError, match="non-negative integer, got -1"):
        loop_subdivide(canonical, -1)
