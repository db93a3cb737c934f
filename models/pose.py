"""Head pose: the similarity transform from model space to image space.

``image = scale * R @ model + t`` with R a proper rotation (det +1). Model space is the
canonical mesh's (cm, x to the face's left, y up, z towards the viewer); image space is
pixels (x right, y down, z away from the camera, same scale as x). A frontal, upright
face therefore has R = diag(1, -1, -1), and ``scale`` is pixels per centimetre.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)

FRONTAL = np.diag([1.0, -1.0, -1.0])


def _points(name: str, points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"expected {name} as (n, 3) float array, got {p.shape}")
    return p


@dataclass(frozen=True, eq=False)
class Pose:
    """A similarity transform model -> image.

    rotation : (3, 3) float64, proper rotation
    scale : float, image units per model unit (pixels per cm)
    translation : (3,) float64, image units
    """

    rotation: np.ndarray
    scale: float
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation, dtype=np.float64)
        if r.shape != (3, 3):
            raise ValueError(f"expected (3, 3) rotation, got {r.shape}")
        if t.shape != (3,):
            raise ValueError(f"expected (3,) translation, got {t.shape}")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ValueError(f"rotation is not a proper rotation: det {np.linalg.det(r):.6g}")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"expected positive finite scale, got {self.scale}")
        r.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def frontal(cls, scale: float = 1.0, translation: np.ndarray | None = None) -> Pose:
        """An upright face looking into the camera: R = diag(1, -1, -1)."""
        t = np.zeros(3) if translation is None else translation
        return cls(FRONTAL.copy(), scale, t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) model points (cm) -> (n, 3) image points (px)."""
        p = _points("model points", points)
        return self.scale * p @ self.rotation.T + self.translation

    def inverse(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) image points (px) -> (n, 3) model points (cm)."""
        p = _points("image points", points)
        return (p - self.translation) @ self.rotation / self.scale

    def as_matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix [[scale * R, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Pose:
        """Inverse of ``as_matrix``: the scale is the cube root of det of the 3x3 block."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"expected (4, 4) matrix, got {m.shape}")
        a = m[:3, :3]
        det = np.linalg.det(a)
        if det <= 0:
            raise ValueError(f"matrix block has det {det:.6g}, not a proper similarity")
        s = float(np.cbrt(det))
        return cls(a / s, s, m[:3, 3].copy())

    def as_quaternion(self) -> np.ndarray:
        """(4,) unit quaternion of the rotation, scalar last (x, y, z, w) as in scipy."""
        return Rotation.from_matrix(self.rotation).as_quat()

    @classmethod
    def from_quaternion(cls, q: np.ndarray, scale: float, translation: np.ndarray) -> Pose:
        """Pose from a (4,) quaternion (x, y, z, w; normalised here), scale and (3,) t."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (4,):
            raise ValueError(f"expected (4,) quaternion, got {q.shape}")
        return cls(Rotation.from_quat(q).as_matrix(), scale, translation)

    def __repr__(self) -> str:
        rotvec = np.degrees(Rotation.from_matrix(self.rotation).as_rotvec())
        return (
            f"Pose(rotvec_deg={np.round(rotvec, 2)}, scale={self.scale:.4g}, "
            f"t={np.round(self.translation, 3)})"
        )


def estimate_pose(
    model_points: np.ndarray, image_points: np.ndarray, weights: np.ndarray | None = None
) -> Pose:
    """Weighted least-squares similarity (Umeyama 1991) with ``apply(model) ~= image``.

    model_points : (k, 3) cm, model space; image_points : (k, 3) px, image space;
    weights : (k,) non-negative, default all ones. Minimises
    sum_i w_i |scale R m_i + t - p_i|^2 over proper rotations R (det +1), scale > 0 and t.
    """
    m = _points("model points", model_points)
    p = _points("image points", image_points)
    if len(m) != len(p):
        raise ValueError(f"model and image point counts differ: {len(m)} vs {len(p)}")
    w = np.ones(len(m)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(m),):
        raise ValueError(f"expected ({len(m)},) weights, got {w.shape}")
    if (w < 0).any() or w.sum() <= 0:
        raise ValueError("weights must be non-negative with a positive sum")
    if np.count_nonzero(w) < 3:
        raise ValueError(f"need at least 3 weighted points, got {np.count_nonzero(w)}")
    w = w / w.sum()
    mu_m = w @ m
    mu_p = w @ p
    x = m - mu_m
    y = p - mu_p
    cov = (y * w[:, None]).T @ x  # (3, 3) sum w_i y_i x_i^T
    u, d, vt = np.linalg.svd(cov)
    # Flip the weakest axis if needed so the result is a rotation, not a reflection.
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    r = (u * sign) @ vt
    var_m = float(w @ (x * x).sum(axis=1))
    if var_m <= 0:
        raise ValueError("model points are all coincident")
    scale = float((d * sign).sum() / var_m)
    if scale <= 0:
        raise ValueError(f"degenerate correspondence: estimated scale {scale:.6g}")
    t = mu_p - scale * r @ mu_m
    return Pose(r, scale, t)


def residual_rms(pose: Pose, model_points: np.ndarray, image_points: np.ndarray) -> float:
    """RMS distance in model units (cm) between ``inverse(image_points)`` and the model."""
    diff = pose.inverse(image_points) - _points("model points", model_points)
    return float(np.sqrt((diff**2).sum(axis=1).mean()))
