"""Thin-plate splines: through their controls, and exact for an affine map."""

from __future__ import annotations

import numpy as np

from facewire.models.thin_plate import ThinPlate


def test_the_spline_passes_through_its_controls() -> None:
    rng = np.random.default_rng(0)
    controls = rng.uniform(0, 100, (20, 2))
    values = rng.normal(0, 3, (20, 2))
    assert np.allclose(ThinPlate(controls, values, 0.0)(controls), values, atol=1e-6)
    # Smoothing lets it pass near them instead, and only near.
    smooth = ThinPlate(controls, values, 50.0)(controls)
    assert 0.0 < np.abs(smooth - values).max() < np.abs(values).max()


def test_an_affine_map_is_reproduced_everywhere() -> None:
    rng = np.random.default_rng(1)
    controls = rng.uniform(0, 100, (12, 2))
    matrix, shift = np.array([[1.1, -0.2], [0.3, 0.9]]), np.array([4.0, -7.0])
    spline = ThinPlate(controls, controls @ matrix.T + shift, 1.0)
    points = rng.uniform(-50, 150, (200, 2))
    assert np.allclose(spline(points), points @ matrix.T + shift, atol=1e-6)


def test_many_points_at_once_are_each_where_the_spline_puts_them_alone() -> None:
    # Points are evaluated in blocks (models/thin_plate.py): a frame's grid has thousands.
    rng = np.random.default_rng(2)
    controls = rng.uniform(0, 1280, (90, 2))
    spline = ThinPlate(controls, rng.normal(0, 3, (90, 2)), 1e-3)
    points = rng.uniform(0, 1280, (1000, 2))
    alone = np.vstack([spline(p[None]) for p in points])
    assert np.allclose(spline(points), alone, rtol=0.0, atol=1e-9)


def test_controls_that_fix_no_plane_give_a_constant_not_a_singular_system() -> None:
    # The surroundings' warp keeps only the controls that do not fold the picture: a hostile
    # camera value left one, and the solve raised instead of drawing (or refusing) the frame.
    points = np.random.default_rng(3).uniform(-500, 500, (50, 2))
    one = ThinPlate(np.array([[10.0, 20.0]]), np.array([[3.0, -4.0]]), 1.0)
    assert np.allclose(one(points), [3.0, -4.0])
    assert np.array_equal(ThinPlate(np.zeros((0, 2)), np.zeros((0, 2)), 1.0)(points), 0 * points)
    line = np.c_[np.linspace(0, 100, 5), np.linspace(0, 50, 5)]
    along = ThinPlate(line, np.c_[np.full(5, 2.0), np.full(5, 7.0)], 1.0)
    assert np.allclose(along(points), [2.0, 7.0], atol=1e-9)  # a constant stays one
