from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import brentq

from facewire.models import bspline
from facewire.models.mesh import load_canonical
from facewire.models.wires import WireCurveSpec, WireDeformer, falloff

LIP = (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291)
BROW = (70, 63, 105, 66, 107)


# -- direct, slow evaluation of seed 000 Eq. 1-3, one vertex and one wire at a time -----


def nearest_parameter(cp: np.ndarray, p: np.ndarray) -> float:
    """Best of a dense grid, then the root of (C(u) - p) . C'(u) in its bracket (Brent)."""
    grid = np.linspace(0.0, 1.0, 2001)
    i = int(np.argmin(((bspline.evaluate(cp, grid) - p) ** 2).sum(axis=1)))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]

    def g(u: float) -> float:
        uu = np.array([u])
        return float((bspline.evaluate(cp, uu)[0] - p) @ bspline.evaluate(cp, uu, 1)[0])

    if g(lo) < 0.0 < g(hi):
        return float(brentq(g, lo, hi, xtol=1e-15))
    return float(grid[i])  # the nearest point is a curve end


def direct_deform(base, ref_cps, wire_cps, ranges, s, k):
    out = base.copy()
    for i, p in enumerate(base):
        num = np.zeros(3)
        den = 0.0
        for r_cp, w_cp, r, s_j in zip(ref_cps, wire_cps, ranges, s, strict=True):
            u = np.array([nearest_parameter(r_cp, p)])
            p_r = bspline.evaluate(r_cp, u)[0]
            p_w = bspline.evaluate(w_cp, u)[0]
            x = np.linalg.norm(p - p_r) / r
            f = (x * x - 1.0) ** 2 if x < 1.0 else 0.0
            if f == 0.0:
                continue
            dp_j = (s_j - 1.0) * (p - p_r) * f + (p_w - p_r) * f  # Eq. 2
            num += dp_j * f**k  # Eq. 3
            den += f**k
        if den > 0.0:
            out[i] = p + num / den
    return out


def random_params(w: WireDeformer, rng, scale=0.3):
    p = w.rest_params()
    p[w.s_slice] += rng.uniform(-0.5, 0.5, w.n_curves)
    for qs in w.q_slices:
        p[qs] = rng.normal(scale=scale, size=qs.stop - qs.start)
    return p


# -- fixtures --------------------------------------------------------------------------


def toy_mesh():
    """A gently curved 21 x 21 grid, 4 cm across, with two crossing chains."""
    xs = np.linspace(-2.0, 2.0, 21)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    z = 0.3 * np.cos(gx) * np.cos(0.5 * gy)
    verts = np.stack([gx, gy, z], axis=-1).reshape(-1, 3)
    horizontal = tuple(int(i * 21 + 10) for i in range(3, 18))  # y = 0, x from -1.4 to 1.4
    vertical = tuple(int(15 * 21 + j) for j in range(2, 16))  # x = 1.0
    curves = [
        WireCurveSpec("h", horizontal, 6, 0.9, "mouth"),
        WireCurveSpec("v", vertical, 5, 0.7, "eyes"),
    ]
    return verts, curves


def canonical_curves():
    return [
        WireCurveSpec("lip", LIP, 6, 1.2, "mouth"),
        WireCurveSpec("brow", BROW, 4, 1.5, "brows"),
    ]


@pytest.fixture(scope="module")
def canonical():
    return load_canonical().vertices


# -- tests -----------------------------------------------------------------------------


def test_falloff():
    np.testing.assert_allclose(falloff(np.array([0.0, 0.5, 1.0, 2.0])), [1.0, 0.5625, 0.0, 0.0])


@pytest.mark.parametrize("k", [0.0, 1.0, 2.5])
def test_matches_direct_evaluation_on_toy_mesh(k):
    verts, curves = toy_mesh()
    w = WireDeformer(verts, curves, k)
    p = random_params(w, np.random.default_rng(int(k * 10)))
    s, _ = w.split_params(p)
    ref = direct_deform(verts, w.reference_control_points, w.wire_control_points(p), w.ranges, s, k)
    np.testing.assert_allclose(w.deform(p), ref, atol=1e-9)
    # The toy mesh has vertices reached by both wires, by one, and by none.
    reached = (w.falloff > 0).sum(axis=1)
    assert {0, 1, 2} <= set(reached.tolist())


def test_matches_direct_evaluation_on_canonical_mesh(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    p = random_params(w, np.random.default_rng(7))
    s, _ = w.split_params(p)
    ref = direct_deform(
        canonical, w.reference_control_points, w.wire_control_points(p), w.ranges, s, 2.0
    )
    np.testing.assert_allclose(w.deform(p), ref, atol=1e-9)
    assert np.abs(ref - canonical).max() > 0.1


def test_rest_params_give_the_base_mesh_exactly(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    rest = w.rest_params()
    np.testing.assert_array_equal(rest[w.s_slice], 1.0)
    np.testing.assert_array_equal(np.delete(rest, np.arange(w.n_curves)), 0.0)
    np.testing.assert_array_equal(w.deform(rest), canonical)
    for r, wc in zip(w.reference_control_points, w.wire_control_points(rest), strict=True):
        np.testing.assert_array_equal(r, wc)


def test_vertices_beyond_every_range_do_not_move(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    p = random_params(w, np.random.default_rng(3), scale=2.0)
    dist = np.linalg.norm(canonical[None] - w.closest_points, axis=2).T  # (n, m)
    far = (dist >= w.ranges[None, :]).all(axis=1)
    assert far.sum() > 300
    out = w.deform(p)
    np.testing.assert_array_equal(out[far], canonical[far])
    assert (np.abs(out[~far] - canonical[~far]).max(axis=1) > 0).all()


@pytest.mark.parametrize("case", ["toy", "canonical"])
def test_fit_recovers_random_params(case, canonical):
    if case == "toy":
        verts, curves = toy_mesh()
    else:
        verts, curves = canonical, canonical_curves()
    w = WireDeformer(verts, curves, 2.0)
    rng = np.random.default_rng(11)
    for _ in range(5):
        p = random_params(w, rng)
        got = w.fit(w.deform(p))
        assert np.abs(got - p).max() <= 1e-6 * np.abs(p).max()
        np.testing.assert_allclose(w.fit_displacement(w.displacement(p)), got, atol=1e-12)
    assert w.rank == w.n_params


def test_no_displacement_iff_rest_params(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    np.testing.assert_allclose(w.fit(canonical), w.rest_params(), atol=1e-12)
    # Full column rank: any other parameter vector moves the mesh by at least
    # sigma_min * |x|, so "no displacement" happens for s = 1, q = 0 only.
    sv = np.linalg.svd(w.matrix.toarray(), compute_uv=False)
    assert sv[-1] > 1e-3 * sv[0]
    x = np.zeros(w.n_params)
    x[0] = 1e-3  # a slightly different scale alone already moves vertices
    assert np.abs(w.displacement(w.rest_params() + x)).max() > 0


def test_corrected_equation_9_sign(canonical):
    """With s itself as unknown, Eq. 8 gives [B|C](s, q) = dp + c, not dp - c."""
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    p = random_params(w, np.random.default_rng(5))
    dp = w.displacement(p)
    offsets = canonical[None] - w.closest_points  # (m, n, 3)
    c = (w.weights.T[:, :, None] * offsets).sum(axis=0)  # c_i = sum_j w_ij (p_i - p_iRj)
    bc = (w.matrix @ p).reshape(-1, 3)  # A applied to (s, q) rather than (s - 1, q)
    np.testing.assert_allclose(bc, dp + c, atol=1e-12)
    assert np.abs(c).max() > 1e-3  # so the printed "dp - c" would be wrong


def test_larger_k_localises_each_vertex_to_its_nearest_wire():
    verts, curves = toy_mesh()
    both = None
    ratios = []
    for k in (0.0, 1.0, 4.0):
        w = WireDeformer(verts, curves, k)
        if both is None:
            f = w.falloff
            both = np.flatnonzero((f > 0).all(axis=1) & (np.abs(f[:, 0] - f[:, 1]) > 0.05))
            assert len(both) > 5
            near = np.argmax(f[both], axis=1)
        ratios.append(w.weights[both, near] / w.weights[both, 1 - near])
        # Vertices reached by one wire only get weight f whatever k is.
        single = (w.falloff > 0).sum(axis=1) == 1
        np.testing.assert_allclose(w.weights[single].sum(axis=1), w.falloff[single].sum(axis=1))
    assert (ratios[1] > ratios[0]).all() and (ratios[2] > ratios[1]).all()


def test_parameter_bookkeeping(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    assert w.n_params == 2 + 3 * 6 + 3 * 4
    assert len(w.param_names) == w.n_params
    assert w.param_names[:2] == ["lip.s", "brow.s"]
    assert w.param_names[w.q_slices[1].start] == "brow.q0.x"
    groups = w.feature_groups()
    assert set(groups) == {"mouth", "brows"}
    np.testing.assert_array_equal(groups["brows"], np.r_[1, w.q_slices[1].start : w.n_params])
    p = random_params(w, np.random.default_rng(0))
    s, q = w.split_params(p)
    np.testing.assert_array_equal(w.join_params(s, q), p)
    cps = w.wire_control_points(p)
    np.testing.assert_allclose(cps[0] - w.reference_control_points[0], q[0])


def test_from_control_points_and_from_rig_agree(canonical):
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    w2 = WireDeformer.from_control_points(
        canonical, w.reference_control_points, w.ranges, 2.0, w.names, w.features
    )
    rig = SimpleNamespace(curves=canonical_curves(), localize_k=2.0)
    w3 = WireDeformer.from_rig(canonical, rig)
    p = random_params(w, np.random.default_rng(1))
    np.testing.assert_array_equal(w2.deform(p), w.deform(p))
    np.testing.assert_array_equal(w3.deform(p), w.deform(p))


def test_bundled_rig_if_present(canonical):
    rig_mod = pytest.importorskip("facewire.models.rig")
    w = WireDeformer.from_rig(canonical, rig_mod.load_rig())
    p = random_params(w, np.random.default_rng(2), scale=0.1)
    np.testing.assert_array_equal(w.deform(w.rest_params()), canonical)
    got = w.fit(w.deform(p))
    assert np.abs(got - p).max() <= 1e-6 * np.abs(p).max()


def test_bad_input_raises_with_the_bad_value(canonical):
    with pytest.raises(ValueError, match=r"expected \(n, 3\) base vertices, got shape \(468, 2\)"):
        WireDeformer(canonical[:, :2], canonical_curves(), 2.0)
    with pytest.raises(ValueError, match="k must be >= 0, got -1"):
        WireDeformer(canonical, canonical_curves(), -1.0)
    with pytest.raises(ValueError, match="'x': vertex index 500 out of range"):
        WireDeformer(canonical, [WireCurveSpec("x", (1, 2, 3, 500), 4, 1.0)], 2.0)
    with pytest.raises(ValueError, match="'x': a chain of 4 points cannot determine 5"):
        WireDeformer(canonical, [WireCurveSpec("x", (1, 2, 3, 4), 5, 1.0)], 2.0)
    with pytest.raises(ValueError, match="range must be > 0 cm, got 0.0"):
        WireDeformer(canonical, [WireCurveSpec("x", LIP, 5, 0.0)], 2.0)
    w = WireDeformer(canonical, canonical_curves(), 2.0)
    with pytest.raises(ValueError, match=r"expected \(32,\) wire params, got shape \(31,\)"):
        w.deform(np.zeros(31))
    with pytest.raises(ValueError, match=r"expected \(468, 3\) target vertices, got \(10, 3\)"):
        w.fit(np.zeros((10, 3)))


def test_rank_deficient_system_returns_the_least_change_solution(caplog):
    # Every vertex lies on the curve, so p - p_R = 0 and the scale s has no effect.
    verts = np.linspace([0.0, 0.0, 0.0], [4.0, 1.0, 0.0], 9)
    w = WireDeformer(verts, [WireCurveSpec("line", tuple(range(9)), 4, 1.0)], 2.0)
    p = w.rest_params()
    p[0] = 1.7
    p[w.q_slices[0]] = np.random.default_rng(4).normal(scale=0.2, size=12)
    with caplog.at_level("WARNING", logger="facewire.models.wires"):
        got = w.fit(w.deform(p))
    assert w.rank == w.n_params - 1
    assert "rank deficient (12 of 13)" in caplog.text
    assert got[0] == pytest.approx(1.0)  # the undetermined scale stays at rest
    np.testing.assert_allclose(got[1:], p[1:], atol=1e-10)
