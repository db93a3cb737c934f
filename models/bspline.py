"""Clamped uniform cubic B-splines: basis matrices, fitting, closest points.

A curve with ``n_ctrl >= 4`` control points has the clamped knot vector
``[0, 0, 0, 0, 1/(n_ctrl-3), ..., 1, 1, 1, 1]``, so C(0) is the first control point and
C(1) the last. Every function is vectorised over parameters / query points. These are
the reference and wire curves of the wire deformer (seed 000, Eq. 6).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.interpolate import BSpline

logger = logging.getLogger(__name__)

DEGREE = 3


def knots(n_ctrl: int) -> np.ndarray:
    """(n_ctrl + 4,) clamped uniform knot vector on [0, 1]."""
    if n_ctrl < DEGREE + 1:
        raise ValueError(f"a cubic B-spline needs at least 4 control points, got {n_ctrl}")
    inner = np.linspace(0.0, 1.0, n_ctrl - DEGREE + 1)
    return np.concatenate([np.zeros(DEGREE), inner, np.ones(DEGREE)])


def _check_u(u: np.ndarray) -> np.ndarray:
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    if u.ndim != 1:
        raise ValueError(f"expected (k,) curve parameters, got shape {u.shape}")
    if u.size and (u.min() < 0.0 or u.max() > 1.0 or not np.all(np.isfinite(u))):
        raise ValueError(f"curve parameters must lie in [0, 1], got range [{u.min()}, {u.max()}]")
    return u


def basis_matrix(u: np.ndarray, n_ctrl: int, derivative: int = 0) -> np.ndarray:
    """(k, n_ctrl) basis values B_l(u_i) (or their ``derivative``-th u-derivative).

    u : (k,) parameters in [0, 1]. Rows of the 0th-derivative matrix sum to 1.
    """
    u = _check_u(u)
    spline = BSpline(knots(n_ctrl), np.eye(n_ctrl), DEGREE, extrapolate=False)
    if derivative:
        spline = spline.derivative(derivative)
    out = spline(u)
    # extrapolate=False gives NaN exactly at u == 1 for some SciPy versions; use the limit.
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        out[bad] = BSpline(spline.t, spline.c, spline.k, extrapolate=True)(u[bad])
    return np.asarray(out)


def evaluate(control_points: np.ndarray, u: np.ndarray, derivative: int = 0) -> np.ndarray:
    """(k, d) curve points C(u) for control_points (n_ctrl, d) and u (k,) in [0, 1]."""
    cp = _check_control_points(control_points)
    return basis_matrix(u, len(cp), derivative) @ cp


def _check_control_points(control_points: np.ndarray) -> np.ndarray:
    cp = np.asarray(control_points, dtype=np.float64)
    if cp.ndim != 2 or len(cp) < DEGREE + 1:
        raise ValueError(f"expected (n_ctrl >= 4, d) control points, got shape {cp.shape}")
    return cp


def chord_length_parameters(points: np.ndarray) -> np.ndarray:
    """(k,) parameters in [0, 1] proportional to cumulative chord length along points (k, d)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or len(p) < 2:
        raise ValueError(f"expected (k >= 2, d) points, got shape {p.shape}")
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    total = seg.sum()
    if total <= 0.0:
        raise ValueError("cannot parametrise a chain whose points all coincide")
    return np.concatenate([[0.0], np.cumsum(seg) / total]).clip(0.0, 1.0)


def fit_control_points(points: np.ndarray, n_ctrl: int) -> np.ndarray:
    """(n_ctrl, d) least-squares control points of a curve through the ordered chain points (k, d).

    Parameters by chord length. A chain of exactly n_ctrl points is interpolated; a longer
    one is approximated in the least-squares sense. Raises ValueError when the chain has
    fewer than n_ctrl points.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"expected (k, d) chain points, got shape {p.shape}")
    if len(p) < n_ctrl:
        raise ValueError(
            f"a chain of {len(p)} points cannot determine {n_ctrl} control points; "
            f"use at most {len(p)}"
        )
    u = chord_length_parameters(p)
    b = basis_matrix(u, n_ctrl)
    cp, *_ = np.linalg.lstsq(b, p, rcond=None)
    return np.asarray(cp)


def closest_points(
    control_points: np.ndarray,
    queries: np.ndarray,
    samples_per_span: int = 32,
    iterations: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point on the curve for each query.

    control_points : (n_ctrl, d); queries : (k, d).
    Returns (u (k,) parameters in [0, 1], points (k, d)). Dense sampling picks the best
    sample, then safeguarded Newton steps on (C(u) - q) . C'(u) = 0 refine it; a step is
    kept only when it does not increase the distance, so the result is never worse than
    the best sample.
    """
    cp = _check_control_points(control_points)
    q = np.asarray(queries, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != cp.shape[1]:
        raise ValueError(f"expected (k, {cp.shape[1]}) query points, got shape {q.shape}")
    n_ctrl = len(cp)
    grid = np.linspace(0.0, 1.0, samples_per_span * (n_ctrl - DEGREE) + 1)
    pts = basis_matrix(grid, n_ctrl) @ cp
    d2 = (q * q).sum(axis=1)[:, None] - 2.0 * q @ pts.T + (pts * pts).sum(axis=1)[None, :]
    u = grid[np.argmin(d2, axis=1)]
    spline = BSpline(knots(n_ctrl), cp, DEGREE)
    d1, dd = spline.derivative(1), spline.derivative(2)
    c = spline(u)
    best = ((c - q) ** 2).sum(axis=1)
    for _ in range(iterations):
        diff = c - q
        t1 = d1(u)
        g = (diff * t1).sum(axis=1)
        h = (t1 * t1).sum(axis=1) + (diff * dd(u)).sum(axis=1)
        # Newton where the second derivative is positive, else a gradient step.
        step = np.where(h > 1e-12, g / np.where(h > 1e-12, h, 1.0), g)
        step = np.clip(step, -1.0 / (n_ctrl - DEGREE), 1.0 / (n_ctrl - DEGREE))
        u_new = np.clip(u - step, 0.0, 1.0)
        c_new = spline(u_new)
        dist_new = ((c_new - q) ** 2).sum(axis=1)
        ok = dist_new <= best
        u = np.where(ok, u_new, u)
        c = np.where(ok[:, None], c_new, c)
        best = np.where(ok, dist_new, best)
    return u, np.asarray(c)
