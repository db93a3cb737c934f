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


def _spans_the_plane(controls: np.ndarray) -> bool:
    """Whether the points (n, 2) fix an affine map of the plane: three not on one line."""
    if len(controls) < 3:
        return False
    centred = controls - controls.mean(0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return bool(singular[1] > 1e-9 * max(singular[0], 1.0))


class ThinPlate:
    """The thin-plate spline taking ``controls`` (n, 2) to ``values`` (n, d), with
    ``smoothing`` (units of the squared coordinates) on the diagonal: it passes near the values
    rather than through them, and nearly coincident controls stay stable.

    Controls that do not span the plane (fewer than three, or all on one line) leave the
    affine part's slopes undetermined: the spline then has a constant part only (one control
    gives its value everywhere, none gives 0) instead of a singular system."""

    def __init__(self, controls: np.ndarray, values: np.ndarray, smoothing: float) -> None:
        self.controls = c = np.asarray(controls, dtype=np.float64).reshape(-1, 2)
        n, d = len(c), np.shape(values)[1]
        affine = np.c_[np.ones(n), c] if _spans_the_plane(c) else np.ones((n, 1))
        k = affine.shape[1]
        system = np.zeros((n + k, n + k))
        system[:n, :n] = _kernel(squared_distances(c, c)) + smoothing * np.eye(n)
        system[:n, n:] = affine
        system[n:, :n] = affine.T
        rhs = np.zeros((n + k, d))
        rhs[:n] = values
        coef = np.zeros((n + 3, d))  # no slopes where the controls do not give them
        coef[: n + k] = np.linalg.solve(system, rhs) if n else 0.0
        self._coef = coef

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(m, d) the spline at ``points`` (m, 2)."""
        n, coef = len(self.controls), self._coef
        points = np.asarray(points, dtype=np.float64)
        out = points @ coef[n + 1 :] + coef[n]
        for i in range(0, len(points), _BLOCK):
            block = points[i : i + _BLOCK]
            out[i : i + _BLOCK] += _kernel(squared_distances(block, self.controls)) @ coef[:n]
        return out
