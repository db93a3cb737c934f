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


#: Points evaluated at once: (block, n) arrays stay in the cache. The whole (m, n) at once,
#: a 1280x720 frame's 3,600 grid nodes by 90 controls, took three times as long.
_BLOCK = 256


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m, n) squared distances between the rows of ``a`` (m, 2) and ``b`` (n, 2)."""
    dx = a[:, 0, None] - b[:, 0]
    dy = a[:, 1, None] - b[:, 1]
    return dx * dx + dy * dy


class ThinPlate:
    """The thin-plate spline taking ``controls`` (n, 2) to ``values`` (n, d), with
    ``smoothing`` (units of the squared coordinates) on the diagonal: it passes near the values
    rather than through them, and nearly coincident controls stay stable."""

    def __init__(self, controls: np.ndarray, values: np.ndarray, smoothing: float) -> None:
        self.controls = c = np.asarray(controls, dtype=np.float64)
        n = len(c)
        system = np.zeros((n + 3, n + 3))
        system[:n, :n] = _kernel(squared_distances(c, c)) + smoothing * np.eye(n)
        system[:n, n] = 1.0
        system[:n, n + 1 :] = c
        system[n, :n] = 1.0
        system[n + 1 :, :n] = c.T
        rhs = np.zeros((n + 3, np.shape(values)[1]))
        rhs[:n] = values
        self._coef = np.linalg.solve(system, rhs)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(m, d) the spline at ``points`` (m, 2)."""
        n, coef = len(self.controls), self._coef
        points = np.asarray(points, dtype=np.float64)
        out = points @ coef[n + 1 :] + coef[n]
        for i in range(0, len(points), _BLOCK):
            block = points[i : i + _BLOCK]
            out[i : i + _BLOCK] += _kernel(squared_distances(block, self.controls)) @ coef[:n]
        return out
