"""Thin-plate splines in the image plane: smooth 2D displacement fields through control points.

Both the head's surroundings (models/surround.py) and the face's edge corrections
(models/edge.py) are such fields: a displacement given at a few points, spread smoothly
between them, with an affine part so that a shift or a turn of all the points is reproduced
exactly.
"""

from __future__ import annotations

import numpy as np


def _kernel(r2: np.ndarray) -> np.ndarray:
    """Thin-plate radial basis U(r) = r^2 log r^2 (U(0) = 0), from squared distances."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = r2 * np.log(r2)
    out[r2 == 0] = 0.0
    return out


def _squared_distances(a: np.ndarray, b: np.ndarray, a_sq: np.ndarray | None = None) -> np.ndarray:
    """(m, n) squared distances between the rows of ``a`` (m, 2) and ``b`` (n, 2)."""
    a_sq = (a**2).sum(1)[:, None] if a_sq is None else a_sq
    return np.maximum(a_sq + (b**2).sum(1) - 2.0 * a @ b.T, 0.0)


class ThinPlate:
    """The thin-plate spline taking ``controls`` (n, 2) to ``values`` (n, d), with
    ``smoothing`` (units of the squared coordinates) on the diagonal: it passes near the values
    rather than through them, and nearly coincident controls stay stable."""

    def __init__(self, controls: np.ndarray, values: np.ndarray, smoothing: float) -> None:
        self.controls = c = np.asarray(controls, dtype=np.float64)
        n = len(c)
        system = np.zeros((n + 3, n + 3))
        system[:n, :n] = _kernel(_squared_distances(c, c)) + smoothing * np.eye(n)
        system[:n, n] = 1.0
        system[:n, n + 1 :] = c
        system[n, :n] = 1.0
        system[n + 1 :, :n] = c.T
        rhs = np.zeros((n + 3, np.shape(values)[1]))
        rhs[:n] = values
        self._coef = np.linalg.solve(system, rhs)

    def __call__(self, points: np.ndarray, points_sq: np.ndarray | None = None) -> np.ndarray:
        """(m, d) the spline at ``points`` (m, 2); ``points_sq`` (m, 1), their squared norms,
        when the caller keeps them."""
        n, coef = len(self.controls), self._coef
        k = _kernel(_squared_distances(points, self.controls, points_sq))
        return np.asarray(k @ coef[:n] + coef[n] + points @ coef[n + 1 :])
