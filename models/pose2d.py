"""Head pose from 2D image points of known model points, under our orthographic camera.

``facewire.models.pose.estimate_pose`` needs 3D image points (landmarks carry a depth); coloured
markers give only x, y. With the camera of ``facewire.models.pose`` (image = scale R model + t, the
image's x and y are a scaled orthographic projection), k >= 4 points not all in one plane
fix an affine camera in closed form; its nearest scaled rotation starts Gauss-Newton on
the rotation, the scale and the in-image translation. With a previous pose to start from,
3 points suffice. The depth of the translation is not observable and is kept from the start
pose (or 0).
"""

from __future__ import annotations

import logging

import numpy as np

from facewire.models.pose import Pose

logger = logging.getLogger(__name__)

ITERATIONS = 8
# Gauss-Newton stops when the update's largest part is below this (rad, log scale, px).
STEP_TOLERANCE = 1e-7
# With a start pose, the closed form is tried too when the start misses the points by more
# than this RMS (px): a head that moved a lot since.
RESTART_PX = 3.0


def _skew(v: np.ndarray) -> np.ndarray:
    """(k, 3, 3) cross-product matrices of (k, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], axis=1),
            np.stack([v[:, 2], z, -v[:, 0]], axis=1),
            np.stack([-v[:, 1], v[:, 0], z], axis=1),
        ],
        axis=1,
    )


def affine_start(model: np.ndarray, image_xy: np.ndarray, w: np.ndarray) -> Pose | None:
    """Closed-form start: the weighted least-squares affine camera x = A m + b, its two rows
    replaced by the nearest pair of orthonormal rows with one common scale. None when the
    points do not fix an affine camera (fewer than 4, or all in a plane)."""
    if np.count_nonzero(w) < 4:
        return None
    wn = w / w.sum()
    mu_m, mu_x = wn @ model, wn @ image_xy
    x, y = model - mu_m, image_xy - mu_x
    sw = np.sqrt(wn)[:, None]
    a_t, _, rank, sv = np.linalg.lstsq(x * sw, y * sw, rcond=None)
    if rank < 3 or sv[-1] < 1e-6 * sv[0]:
        return None
    a = a_t.T  # (2, 3)
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    scale = float(s.mean())
    if not scale > 0:
        return None
    rows = u @ vt  # (2, 3), orthonormal rows
    rotation = np.vstack([rows, np.cross(rows[0], rows[1])])
    t = np.zeros(3)
    t[:2] = mu_x - scale * rows @ mu_m
    return Pose(rotation, scale, t)


def estimate_pose_2d(
    model_points: np.ndarray,
    image_xy: np.ndarray,
    weights: np.ndarray | None = None,
    initial: Pose | None = None,
) -> Pose:
    """Weighted least-squares pose with ``pose.apply(model)[:, :2] ~= image_xy``.

    model_points : (k, 3) cm, model space; image_xy : (k, 2) px; weights : (k,) >= 0.
    initial : where Gauss-Newton starts (the previous frame's pose); without it the affine
    closed form starts it, which needs 4 weighted points not in one plane. ValueError when
    the points cannot fix a pose.
    """
    m = np.asarray(model_points, dtype=np.float64)
    x = np.asarray(image_xy, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"expected model points as (k, 3) float array, got {m.shape}")
    if x.shape != (len(m), 2):
        raise ValueError(f"expected image points as ({len(m)}, 2) float array, got {x.shape}")
    w = np.ones(len(m)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(m),) or (w < 0).any() or not np.isfinite(w).all():
        raise ValueError(f"expected ({len(m)},) non-negative weights, got {w}")
    if np.count_nonzero(w) < 3:
        raise ValueError(f"need at least 3 weighted points, got {np.count_nonzero(w)}")
    start = initial
    if initial is None or _cost(initial, m, x, w) > (RESTART_PX**2) * w.sum():
        # No start, or the head moved a lot since: the closed form, if it fits better.
        closed = affine_start(m, x, w)
        if closed is not None and (
            initial is None or _cost(closed, m, x, w) < _cost(initial, m, x, w)
        ):
            start = closed
    if start is None:
        raise ValueError("the points do not fix a pose: need 4 not in one plane, or a start pose")
    rotation = np.array(start.rotation)
    log_scale = np.log(start.scale)
    t2 = np.array(start.translation[:2])
    depth = float(start.translation[2])
    sw = np.sqrt(w)
    for _ in range(ITERATIONS):
        s = np.exp(log_scale)
        rm = m @ rotation.T  # (k, 3)
        r = (s * rm[:, :2] + t2 - x) * sw[:, None]
        # Derivatives of s * P exp([dw]x) R m + t: rotation dw (left), log scale, t.
        j_rot = -s * _skew(rm)[:, :2, :]  # (k, 2, 3)
        j_scale = s * rm[:, :2, None]  # (k, 2, 1)
        j_t = np.broadcast_to(np.eye(2), (len(m), 2, 2))
        jac = np.concatenate([j_rot, j_scale, j_t], axis=2) * sw[:, None, None]
        jac = jac.reshape(-1, 6)
        # Normal equations, with a trace-scaled ridge against a rank-deficient set (three
        # points in a line leave a rotation free: it then stays where it started).
        jtj = jac.T @ jac
        jtj += 1e-9 * np.trace(jtj) * np.eye(6)
        step = np.linalg.solve(jtj, -jac.T @ r.ravel())
        rotation = _rodrigues(step[:3]) @ rotation
        log_scale += step[3]
        t2 += step[4:]
        if np.abs(step).max() < STEP_TOLERANCE:
            break
    # Re-orthonormalise away the rounding of repeated products.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    return Pose(rotation, float(np.exp(log_scale)), np.array([t2[0], t2[1], depth]))


def _rodrigues(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad)."""
    theta = float(np.linalg.norm(v))
    if theta < 1e-12:
        return np.eye(3)
    k = v / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def _cost(pose: Pose, m: np.ndarray, x: np.ndarray, w: np.ndarray) -> float:
    return float(w @ ((pose.apply(m)[:, :2] - x) ** 2).sum(axis=1))


def residuals_2d(pose: Pose, model_points: np.ndarray, image_xy: np.ndarray) -> np.ndarray:
    """(k,) image distances (px) between the posed model points and the image points."""
    return np.asarray(np.linalg.norm(pose.apply(model_points)[:, :2] - image_xy, axis=1))
