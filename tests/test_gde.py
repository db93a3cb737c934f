import numpy as np
import pytest

from facewire.models.gde import Expression, Gde, GdeDef, GdeSet, mouth_seam_edges, sample_evenly
from facewire.models.mesh import load_canonical

INNER = [78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 324, 318, 402, 317, 14, 87, 178, 88, 95]
UPPER_LIP = [0, 37, 267, 13, 82, 312, 11, 12]


@pytest.fixture(scope="module")
def mesh():
    return load_canonical()


@pytest.fixture(scope="module")
def seam(mesh):
    return mouth_seam_edges(mesh, INNER, 78, 308)


def rbf_direct(features, stiffness, lam, targets, points):
    """Eq. 1-2 and 5 written out with plain loops."""
    n = len(features)
    h = np.empty((n, n))
    for j in range(n):
        for i in range(n):
            h[j, i] = np.sqrt(np.sum((features[j] - features[i]) ** 2) + stiffness[i] ** 2)
    c = np.linalg.solve(h + lam * np.eye(n), targets)
    out = np.zeros((len(points), 3))
    for p, x in enumerate(points):
        for i in range(n):
            out[p] += c[i] * np.sqrt(np.sum((x - features[i]) ** 2) + stiffness[i] ** 2)
    return out


def test_zero_displacement_is_exactly_neutral(mesh):
    specs = [GdeDef("lo", 17, 3), GdeDef("corner", 61, 1.5, "euclidean"), GdeDef("brow", 105, 2)]
    gs = GdeSet(mesh, specs)
    assert np.array_equal(gs.deform(mesh.vertices, np.zeros((3, 3))), mesh.vertices)


@pytest.mark.parametrize("metric,size", [("edges", 3), ("euclidean", 1.5)])
def test_control_vertex_follows_within_lambda_bound(mesh, metric, size):
    d = np.array([0.3, -0.5, 0.2])
    exact = Gde(mesh, 17, size, metric, lam=0.0)
    assert np.allclose(exact.displacements(d)[exact.region == 17][0], d, atol=1e-9)
    lam = 0.01
    g = Gde(mesh, 17, size, metric, lam=lam)
    moved = g.displacements(d)[g.region == 17][0]
    # (H + lam I) c = y  =>  H c - y = -lam c, and |c| <= |(H + lam I)^-1| |y| with |y| = |d|.
    bound = lam * np.linalg.norm(np.linalg.inv(g.h_matrix + lam * np.eye(len(g.features))), 2)
    err = np.linalg.norm(moved - d)
    assert err <= bound * np.linalg.norm(d) + 1e-12
    assert err > 0  # lam really regularises: interpolation is not exact


def test_anchors_fixed_exactly_with_lam_zero_and_within_bound_otherwise(mesh):
    d = np.array([0.0, -0.6, 0.1])
    for lam in (0.0, 0.01):
        g = Gde(mesh, 17, 3, lam=lam)
        at_anchors = g.basis(mesh.vertices[g.anchors]) @ g.solve(d)
        tol = 1e-9 if lam == 0 else lam * np.linalg.norm(g.solve(d), axis=1)[1:].max() + 1e-12
        assert np.abs(at_anchors).max() <= tol
        gs = GdeSet(mesh, [GdeDef("a", 17, 3)], lam=lam)
        out = gs.deform(mesh.vertices, d[None])
        assert np.array_equal(out[g.anchors], mesh.vertices[g.anchors])


def test_outside_region_never_moves(mesh):
    g = Gde(mesh, 61, 2)
    gs = GdeSet(mesh, [GdeDef("c", 61, 2)])
    out = gs.deform(mesh.vertices, np.array([[0.5, 0.4, -0.3]]))
    outside = np.setdiff1d(np.arange(mesh.n_vertices), g.region)
    assert np.array_equal(out[outside], mesh.vertices[outside])
    assert np.all(np.linalg.norm(out[g.region] - mesh.vertices[g.region], axis=1) > 0)


def test_edge_metric_keeps_lips_separate(mesh, seam):
    for size in (2, 3):
        g = Gde(mesh, 17, size)
        assert not set(g.region) & set(UPPER_LIP)
    # A deeper search would leak through the triangles that close the mouth; the seam stops it.
    leaky = Gde(mesh, 17, 6)
    assert set(leaky.region) & set(UPPER_LIP)
    cut = Gde(mesh, 17, 6, cut_edges=seam)
    assert not set(cut.region) & set(UPPER_LIP)
    gs = GdeSet(mesh, [GdeDef("lo", 17, 6)], cut_edges=seam)
    out = gs.deform(mesh.vertices, np.array([[0.0, -1.0, 0.0]]))
    assert np.array_equal(out[UPPER_LIP], mesh.vertices[UPPER_LIP])


def test_euclidean_region_within_radius(mesh):
    p = mesh.vertices[105] + np.array([0.05, 0.02, 0.1])  # a point off the surface
    g = Gde(mesh, p, 2.0, "euclidean")
    assert g.root == int(np.argmin(np.linalg.norm(mesh.vertices - p, axis=1)))
    dist = np.linalg.norm(mesh.vertices[g.region] - p, axis=1)
    assert np.all(dist < 2.0)
    # Anchors are the frontier: outside the radius but adjacent to the region.
    assert np.all(np.linalg.norm(mesh.vertices[g.anchors] - p, axis=1) >= 2.0)
    assert len(g.region) > 5


def test_anchors_at_most_20_and_spread_along_boundary(mesh):
    g = Gde(mesh, 4, 5)  # large region around the nose: long boundary
    assert len(g.boundary) > 20
    assert 10 <= len(g.anchors) <= 20
    assert set(g.anchors) <= set(g.boundary)
    loop = mesh.vertices[g.boundary]
    seg = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    pos = np.sort(cum[[list(g.boundary).index(a) for a in g.anchors]])
    gaps = np.diff(np.concatenate([pos, [pos[0] + cum[-1]]]))
    assert gaps.max() <= cum[-1] / 20 + seg.max() + 1e-9
    # Ordered by angle: consecutive boundary vertices are near each other on the face.
    assert np.median(seg) < 0.25 * np.ptp(loop[:, 0])


def test_sample_evenly_on_uniform_circle():
    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    pts = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    assert np.array_equal(sample_evenly(pts, 20), np.arange(0, 100, 5))
    assert np.array_equal(sample_evenly(pts[:7], 20), np.arange(7))


def test_matches_equations_1_2_directly(mesh):
    p = mesh.vertices[61] + np.array([0.1, 0.0, 0.05])
    g = Gde(mesh, p, 1.5, "euclidean")
    d = np.array([-0.2, 0.3, 0.1])
    targets = np.zeros((len(g.features), 3))
    targets[0] = d
    f = g.features
    s = np.array(
        [min(np.linalg.norm(f[j] - f[i]) for j in range(len(f)) if j != i) for i in range(len(f))]
    )
    assert np.allclose(g.stiffness, s)
    want = rbf_direct(g.features, s, 0.01, targets, mesh.vertices[g.region])
    assert np.allclose(g.displacements(d), want, atol=1e-10)


def test_solve_and_precomputed_weights_agree(mesh, seam):
    specs = [GdeDef("lo", 17, 3), GdeDef("corner", 291, 1.5, "euclidean"), GdeDef("up", 0, 2)]
    gs = GdeSet(mesh, specs, cut_edges=seam)
    rng = np.random.default_rng(3)
    d = rng.normal(scale=0.3, size=(3, 3))
    want = mesh.vertices.copy()
    for g, di in zip(gs.elements, d, strict=True):
        want[g.region] += g.displacements(di)
        rhs = np.vstack([di, np.zeros((len(g.anchors), 3))])
        assert np.allclose(g.solve(di), np.linalg.solve(g.h_matrix + 0.01 * np.eye(len(rhs)), rhs))
    assert np.allclose(gs.deform(mesh.vertices, d), want, atol=1e-12)
    flat = (gs.as_flat_matrix() @ d.ravel()).reshape(-1, 3)
    assert np.allclose(mesh.vertices + flat, want, atol=1e-12)


def test_expressions(mesh):
    gs = GdeSet(mesh, [GdeDef("l", 291, 2), GdeDef("r", 61, 2), GdeDef("jaw", 17, 3)])
    smile = Expression("smile", {"l": np.array([0.4, 0.3, 0.0]), "r": np.array([-0.4, 0.3, 0.0])})
    open_ = Expression("open", {"jaw": np.array([0.0, -1.0, 0.0])})
    d = gs.expression_displacements([smile, open_], {"smile": 0.5, "open": 1.0})
    assert np.allclose(d, [[0.2, 0.15, 0], [-0.2, 0.15, 0], [0, -1, 0]])
    assert np.array_equal(gs.expression_displacements([smile], {"smile": 0.0}), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"weight must be in \[0, 1\], got 1.5"):
        gs.expression_displacements([smile], {"smile": 1.5})
    with pytest.raises(ValueError, match="unknown GDE 'nose'"):
        gs.expression_displacements([Expression("x", {"nose": np.zeros(3)})], {"x": 1.0})


def test_bad_inputs(mesh):
    with pytest.raises(ValueError, match="metric must be"):
        Gde(mesh, 17, 2, "geodesic")
    with pytest.raises(ValueError, match=r"got \(2,\)"):
        Gde(mesh, np.zeros(2), 2)
    gs = GdeSet(mesh, [GdeDef("a", 17, 2)])
    with pytest.raises(ValueError, match=r"expected \(1, 3\) displacements, got \(3,\)"):
        gs.deform(mesh.vertices, np.zeros(3))
    with pytest.raises(ValueError, match=r"expected \(468, 3\) vertices, got \(2, 3\)"):
        gs.deform(np.zeros((2, 3)), np.zeros((1, 3)))


def test_from_rig_uses_plain_attributes(mesh):
    class Lips:
        markers = {"left": 291, "right": 61, "top": 0, "bottom": 17}
        contours = [(), (), (), tuple(INNER)]

    class Rig:
        gdes = [GdeDef("lo", 17, 6)]
        lips = Lips()

    gs = GdeSet.from_rig(mesh, Rig())
    assert not set(gs.elements[0].region) & set(UPPER_LIP)


def test_bundled_rig(mesh):
    from facewire.models.rig import load_rig

    gs = GdeSet.from_rig(mesh, load_rig())
    assert len(gs) > 0 and all(len(g.anchors) <= 20 for g in gs.elements)
    d = np.zeros((len(gs), 3))
    assert np.array_equal(gs.deform(mesh.vertices, d), mesh.vertices)
