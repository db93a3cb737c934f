import numpy as np
import pytest

from facewire.models import bspline


def cox_de_boor(u: float, t: np.ndarray, i: int, p: int) -> float:
    """Textbook recursion, right end closed on the last non-empty span."""
    if p == 0:
        last = t[i + 1] == t[-1] and t[i] < t[i + 1]
        return 1.0 if (t[i] <= u < t[i + 1]) or (last and u == t[-1]) else 0.0
    a = 0.0 if t[i + p] == t[i] else (u - t[i]) / (t[i + p] - t[i]) * cox_de_boor(u, t, i, p - 1)
    b = (
        0.0
        if t[i + p + 1] == t[i + 1]
        else (t[i + p + 1] - u) / (t[i + p + 1] - t[i + 1]) * cox_de_boor(u, t, i + 1, p - 1)
    )
    return a + b


@pytest.mark.parametrize("n_ctrl", [4, 5, 7, 11])
def test_basis_matches_cox_de_boor(n_ctrl):
    t = bspline.knots(n_ctrl)
    u = np.concatenate([np.linspace(0, 1, 37), [1.0 / 3.0, 0.999999]])
    b = bspline.basis_matrix(u, n_ctrl)
    ref = np.array([[cox_de_boor(x, t, i, 3) for i in range(n_ctrl)] for x in u])
    np.testing.assert_allclose(b, ref, atol=1e-12)


def test_basis_partition_of_unity_and_clamped_ends():
    b = bspline.basis_matrix(np.linspace(0, 1, 101), 6)
    assert b.shape == (101, 6)
    assert (b >= -1e-15).all()
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(b[0], [1, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(b[-1], [0, 0, 0, 0, 0, 1])


def test_derivative_matches_finite_difference():
    cp = np.random.default_rng(0).normal(size=(6, 3))
    u = np.linspace(0.05, 0.95, 19)
    h = 1e-6
    fd = (bspline.evaluate(cp, u + h) - bspline.evaluate(cp, u - h)) / (2 * h)
    np.testing.assert_allclose(bspline.evaluate(cp, u, derivative=1), fd, atol=1e-6)


def test_fit_reproduces_a_straight_chain():
    # Evenly spaced points on a line: chord length = uniform, and B-splines reproduce lines.
    pts = np.linspace([0.0, 1.0, 2.0], [3.0, -1.0, 2.5], 9)
    cp = bspline.fit_control_points(pts, 5)
    u = bspline.chord_length_parameters(pts)
    np.testing.assert_allclose(bspline.evaluate(cp, u), pts, atol=1e-12)


def test_fit_with_as_many_control_points_as_points_interpolates():
    pts = np.random.default_rng(1).normal(size=(6, 3))
    cp = bspline.fit_control_points(pts, 6)
    np.testing.assert_allclose(
        bspline.evaluate(cp, bspline.chord_length_parameters(pts)), pts, atol=1e-10
    )


def test_fit_rejects_too_few_points():
    with pytest.raises(ValueError, match="chain of 4 points cannot determine 5"):
        bspline.fit_control_points(np.eye(4, 3), 5)


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(2)
    cp = rng.normal(size=(7, 3)) * 2.0
    q = rng.normal(size=(300, 3)) * 3.0
    u, pts = bspline.closest_points(cp, q)
    grid = np.linspace(0, 1, 100001)
    dense = bspline.evaluate(cp, grid)
    d2 = ((q[:, None, :] - dense[None]) ** 2).sum(axis=2)
    brute = np.sqrt(d2.min(axis=1))
    ours = np.linalg.norm(pts - q, axis=1)
    np.testing.assert_allclose(pts, bspline.evaluate(cp, u), atol=1e-12)
    # Never farther than the brute-force sample (to its own grid resolution).
    assert (ours <= brute + 1e-9).all()
    assert np.abs(ours - brute).max() < 1e-6


def test_closest_point_is_a_stationary_point_inside():
    cp = np.array([[0, 0, 0], [1, 2, 0], [2, -1, 0], [3, 1, 0], [4, 0, 0]], dtype=float)
    u0 = np.array([0.2, 0.45, 0.8])
    # Small offsets off the curve, so the nearest point is near u0, inside the curve.
    q = bspline.evaluate(cp, u0) + np.array([[0.05, 0.0, 0.1], [0.0, 0.05, -0.1], [0.0, 0.0, 0.2]])
    u, pts = bspline.closest_points(cp, q)
    tangent = bspline.evaluate(cp, u, derivative=1)
    assert ((u > 0) & (u < 1)).all()
    np.testing.assert_allclose(((pts - q) * tangent).sum(axis=1), 0.0, atol=1e-9)


def test_closest_point_beyond_an_end_is_the_end():
    cp = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    u, pts = bspline.closest_points(cp, np.array([[-2.0, 1.0, 0.0], [5.0, -1.0, 0.0]]))
    np.testing.assert_allclose(u, [0.0, 1.0])
    np.testing.assert_allclose(pts, [[0, 0, 0], [3, 0, 0]])


def test_bad_inputs_raise_with_the_bad_value():
    with pytest.raises(ValueError, match="at least 4 control points, got 3"):
        bspline.knots(3)
    with pytest.raises(ValueError, match=r"\[0, 1\], got range \[-0.5"):
        bspline.basis_matrix(np.array([-0.5, 0.2]), 5)
    with pytest.raises(ValueError, match=r"expected \(k, 3\) query points, got shape \(4, 2\)"):
        bspline.closest_points(np.zeros((4, 3)), np.zeros((4, 2)))
