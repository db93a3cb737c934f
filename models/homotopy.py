"""Homotopy sweep of the lip contours (Tanaka, Ishizawa, Adachi, seed 003 section 3).

A point A of contour C1 travels to its partner B on contour C2 as t goes 0 -> 1 along
a path written in a cylindrical frame at A around the mouth centre O (Eq. 3):
U_r from O toward A (perpendicular to the mouth axis), U_z the mouth axis, U_theta
= U_z x U_r; in that frame A = [C1r, 0, C1z], B = [C2r, C2theta, C2z]. Each coordinate
is blended with R (Eq. 7) and bent by scaling functions of 3D control vectors (Eq. 8-9).

Two traps in the printed formulas, fixed here:

* Eq. 7 as printed, R_n(v) = (1+n)v^2 / ((1+n)v^2 + (1-n)^2), gives R_n(1) =
  (1+n) / ((1+n) + (1-n)^2), which is 1/2 for the paper's own n = 0, so the sweep
  would never reach C2. The blending function of Tai, Loe and Kunii (the paper's [10]) is
  R_n(v) = (1+n)v^2 / ((1+n)v^2 + (1-n)(1-v)^2): R(0) = 0, R(1) = 1, zero slope at both
  ends (the G1 property the paper cites), monotone for -1 < n < 1 (Fig. 7 plots
  n = -0.9..0.9); the printed form lost the (1-v) factor.
* Eq. 9 divides the control vectors by C1r, C1z, N and C2theta + N, and Eq. 4-6 multiply
  them back: (1 + S_c1) C1z = C1z + sigma1(t) v1z with sigma1 = t(t-1)(t/k1 - 1). The
  quotients are singular exactly where lip points lie level with O (C1z = 0), while the
  products are not, so we evaluate the cancelled form. The offset N of Eq. 5 then cancels
  as well: given v, the path does not depend on N, and no N parameter is needed.
  Eq. 8 also needs k1 > 0 and k2 < 1 (the paper writes 0 <= k), else it divides by zero.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from facewire.models.mesh import FaceMesh

logger = logging.getLogger(__name__)


def blend(v: float | np.ndarray, n: float | np.ndarray = 0.0) -> np.ndarray:
    """Blending function R_n(v) for v in [0, 1], -1 < n < 1 (Eq. 7, corrected; see module doc).

    Larger n moves the transition earlier; n = 0 is the symmetric v^2 / (v^2 + (1-v)^2).
    ``n`` may be an array (one per value, broadcast against ``v``).
    """
    n = np.asarray(n, dtype=np.float64)
    if not np.all((n > -1.0) & (n < 1.0)):
        raise ValueError(f"blending parameter n must be in (-1, 1), got {n}")
    v = np.asarray(v, dtype=np.float64)
    a = (1.0 + n) * v * v
    return a / (a + (1.0 - n) * (1.0 - v) ** 2)


def scaling_factors(t: float, k1: float = 0.5, k2: float = 0.5) -> tuple[float, float]:
    """(sigma1, sigma2) with S_c1 = sigma1 * p1 and S_c2 = sigma2 * p2 (Eq. 8).

    sigma1 = t(t-1)(t/k1 - 1), sigma2 = -t(t-1)(t/(1-k2) - 1); both vanish at t = 0 and 1.
    """
    if not k1 > 0.0 or not k2 < 1.0:
        raise ValueError(f"scaling weights need k1 > 0 and k2 < 1, got k1={k1}, k2={k2}")
    s = t * (t - 1.0)
    return s * (t / k1 - 1.0), -s * (t / (1.0 - k2) - 1.0)


def cylindrical_frames(points: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(m, 3, 3) local frames, rows U_r, U_theta, U_z, at ``points`` (m, 3) around ``centre``.

    U_z = unit ``axis``; U_r = the component of (point - centre) perpendicular to it,
    normalised (an arbitrary perpendicular for a point on the axis); U_theta = U_z x U_r.
    """
    uz = np.asarray(axis, dtype=np.float64)
    uz = uz / np.linalg.norm(uz)
    rel = points - centre
    ur = rel - np.outer(rel @ uz, uz)
    norm = np.linalg.norm(ur, axis=1)
    on_axis = norm < 1e-12
    if on_axis.any():
        helper = np.array([1.0, 0.0, 0.0]) if abs(uz[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        spare = np.cross(uz, helper)
        ur[on_axis] = spare
        norm[on_axis] = np.linalg.norm(spare)
    ur = ur / norm[:, None]
    ut = np.cross(uz[None], ur)
    return np.stack([ur, ut, np.broadcast_to(uz, ur.shape)], axis=1)


def _check_points(name: str, a: np.ndarray, m: int | None = None) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (m is not None and len(a) != m):
        want = "(m, 3)" if m is None else f"({m}, 3)"
        raise ValueError(f"expected {name} {want} float array, got {a.shape}")
    return a


def sweep(
    c1: np.ndarray,
    c2: np.ndarray,
    t: float,
    centre: np.ndarray,
    axis: np.ndarray,
    n: float | Sequence[float] | np.ndarray = 0.0,
    k: float | Sequence[float] = 0.5,
    v1: np.ndarray | None = None,
    v2: np.ndarray | None = None,
) -> np.ndarray:
    """Points of the homotopy between contours at time ``t`` in [0, 1] (Eq. 3-9).

    c1, c2 : (m, 3) corresponding contour points, cm, model space
    centre : (3,) mouth centre O; axis : (3,) mouth axis (U_z)
    n : blending parameter for r, theta and z alike, or (n_r, n_theta, n_z) (the
        paper's n, m, k of Eq. 4-6), or an (m, 3) array: one per point and axis (a
        contour of its own n, :class:`MouthRig`)
    k : scaling weight for both contours, or (k1, k2) (Eq. 8; the paper used 0.5)
    v1, v2 : (m, 3) control vectors along C1 and C2 in model space, cm (their local
        components are the paper's v of Eq. 9); None means no bending

    Returns (m, 3): ``c1`` exactly at t = 0 and ``c2`` (to rounding) at t = 1. With no
    control vectors and one n this is c1 + R_n(t) (c2 - c1): the frame only matters for
    per-axis blending and for bending by v.
    """
    c1 = _check_points("c1", c1)
    m = len(c1)
    c2 = _check_points("c2", c2, m)
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"t must be in [0, 1], got {t}")
    n_arr = np.asarray(n, dtype=np.float64)
    if n_arr.ndim == 2 and n_arr.shape != (m, 3):
        raise ValueError(f"expected n of shape (), (3,) or ({m}, 3), got {n_arr.shape}")
    k1, k2 = np.broadcast_to(np.asarray(k, dtype=np.float64), (2,))
    frames = cylindrical_frames(c1, np.asarray(centre, dtype=np.float64), axis)
    r = blend(t, n_arr if n_arr.ndim == 2 else np.broadcast_to(n_arr, (3,)))
    # Local coordinates of B minus those of A: [C2r - C1r, C2theta, C2z - C1z].
    step = r * np.einsum("mij,mj->mi", frames, c2 - c1)
    if v1 is not None or v2 is not None:
        s1, s2 = scaling_factors(t, float(k1), float(k2))
        if v1 is not None:
            step += (1.0 - r) * s1 * np.einsum("mij,mj->mi", frames, _check_points("v1", v1, m))
        if v2 is not None:
            step += r * s2 * np.einsum("mij,mj->mi", frames, _check_points("v2", v2, m))
    return c1 + np.einsum("mji,mj->mi", frames, step)


MARKER_ORDER = ("left", "top", "right", "bottom")
RING_LEVELS = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)  # outer, ring, ring, inner (section 3.7.1)
MARKER_ANGLES = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])  # left, top, right, bottom


def _falloff(x: np.ndarray) -> np.ndarray:
    """(1 - x^2)^2 for x < 1, else 0: 1 at the ring, zero value and slope at the edge."""
    return np.where(x < 1.0, (1.0 - np.minimum(x, 1.0) ** 2) ** 2, 0.0)


class MouthRig:
    """The four nested lip contours of the mouth model, driven by four marker displacements.

    mesh : the face mesh at rest
    markers : {"left", "right", "top", "bottom"} -> vertex index
    contours : four closed vertex loops, outer ring, two middle rings, inner ring
    n : the blending parameter of :func:`sweep`, one for all contours or one per contour
        (outer .. inner): a contour with a larger n moves earlier (the paper used 0)
    k : the scaling weight of :func:`sweep` (the paper used 0.5)
    falloff : cm; mesh vertices outside the rings within this distance of a ring
        vertex follow the rings with weight (1 - (d/falloff)^2)^2

    Marker displacements are spread around each ring by angle on an ellipse: a
    trigonometric interpolant in 1, cos, sin, cos 2 of the angle (the paper models fibres
    with a cosine curve) through the four markers at 0, pi/2, pi and -pi/2, whose weights
    sum to one, so a common displacement moves every ring vertex by exactly that
    displacement. Each ring's angles are on its own ellipse (:meth:`_ring_angles`), the
    shut mouth's flat inner ring included. The outer ring follows ``marker_disp``, the
    inner ring ``inner_disp`` (the same by default) and the middle rings 1/3 and 2/3 of
    the way between (section 3.7.1).

    Vertices outside the rings do not stay put: the outer lip line can move a
    centimetre, and skin pinned right next to it would fold. They take the sweep
    displacement of their three nearest ring vertices (inverse-distance weights) times
    the falloff above, which is linear, exactly zero beyond ``falloff`` and at zero
    displacement, and also covers the extra vertices of a subdivided mesh.

    The 3D control vectors of Eq. 8-9 come from the four markers too: a marker velocity (cm
    per key frame interval) is spread around the rings by the same interpolant. With the
    velocities at both key frames as control vectors (:meth:`between`), the lips leave one
    key frame and reach the next at the speed the markers had there, so the in-between
    contours join the key frames without the stop that the blending function alone makes
    (its slope is zero at both ends).
    """

    def __init__(
        self,
        mesh: FaceMesh,
        markers: dict[str, int],
        contours: Sequence[Sequence[int]],
        n: float | Sequence[float] = 0.0,
        k: float = 0.5,
        falloff: float = 1.0,
    ) -> None:
        verts = mesh.vertices
        if set(markers) != set(MARKER_ORDER):
            raise ValueError(f"expected markers {sorted(MARKER_ORDER)}, got {sorted(markers)}")
        if len(contours) != 4:
            raise ValueError(f"expected 4 lip contours (outer .. inner), got {len(contours)}")
        if not falloff > 0:
            raise ValueError(f"falloff must be > 0 cm, got {falloff}")
        contour_n = np.broadcast_to(np.asarray(n, dtype=np.float64), (4,))
        blend(0.0, contour_n)  # validate early
        scaling_factors(0.0, k, k)
        self.n, self.k, self.falloff = contour_n, k, falloff
        self.n_vertices = len(verts)
        self.marker_vertices = np.array([markers[m] for m in MARKER_ORDER], dtype=np.int64)
        rings = [np.asarray(c, dtype=np.int64) for c in contours]
        for i, ring in enumerate(rings):
            if len(ring) < 3 or ring.min() < 0 or ring.max() >= len(verts):
                raise ValueError(f"contour {i} must hold >= 3 vertices in 0..{len(verts) - 1}")

        ring_all = np.concatenate(rings)
        self.axis = self._mouth_axis(*verts[self.marker_vertices])
        basis_inv = np.linalg.inv(self._trig_basis(MARKER_ANGLES))

        # Unique ring vertices; a vertex on several rings averages its levels.
        self.ring_vertices, inverse = np.unique(ring_all, return_inverse=True)
        levels = np.concatenate(
            [np.full(len(r), lv) for r, lv in zip(rings, RING_LEVELS, strict=True)]
        )
        count = np.bincount(inverse)
        alpha = np.bincount(inverse, weights=levels) / count
        per_ring = np.concatenate(
            [np.full(len(r), value) for r, value in zip(rings, contour_n, strict=True)]
        )
        # (u, 3) blending parameter of each ring vertex (a vertex on several rings: the mean).
        self.ring_n = np.repeat((np.bincount(inverse, weights=per_ring) / count)[:, None], 3, 1)
        phi = np.zeros(len(self.ring_vertices))
        for ring in rings:  # a vertex on several rings: the last (innermost) ring's angle
            phi[np.searchsorted(self.ring_vertices, ring)] = self._ring_angles(verts, ring)
        marker_rows = np.searchsorted(self.ring_vertices, self.marker_vertices)
        found = self.ring_vertices[np.minimum(marker_rows, len(self.ring_vertices) - 1)]
        markers_on_rings = found == self.marker_vertices
        phi[marker_rows[markers_on_rings]] = MARKER_ANGLES[markers_on_rings]
        w = self._trig_basis(phi) @ basis_inv
        # (u, 4) weights of marker_disp and of inner_disp for each ring vertex.
        self.outer_weights = (1.0 - alpha)[:, None] * w
        self.inner_weights = alpha[:, None] * w
        self.outer_ring = rings[0]

        others = np.setdiff1d(np.arange(len(verts)), self.ring_vertices)
        ring_pos = verts[self.ring_vertices]
        dist = np.linalg.norm(verts[others][:, None] - ring_pos[None], axis=2)
        near = np.argsort(dist, axis=1)[:, :3]
        dn = np.take_along_axis(dist, near, axis=1)
        keep = dn[:, 0] < falloff
        inv = 1.0 / dn[keep]
        self.follow_vertices = others[keep]
        self.follow_rings = near[keep]  # indices into ring_vertices
        self.follow_weights = (
            inv / inv.sum(axis=1, keepdims=True) * _falloff(dn[keep, :1] / falloff)
        )
        logger.debug(
            "MouthRig: %d ring vertices, %d follow within %.2f cm",
            len(self.ring_vertices),
            len(self.follow_vertices),
            falloff,
        )

    @classmethod
    def from_rig(cls, mesh: FaceMesh, rig: Any, **kwargs: float) -> MouthRig:
        """From a ``facewire.models.rig.Rig`` (its ``lips``) or a ``LipRig`` directly."""
        lips = getattr(rig, "lips", rig)
        return cls(mesh, dict(lips.markers), list(lips.contours), **kwargs)

    @staticmethod
    def _mouth_axis(
        left: np.ndarray, top: np.ndarray, right: np.ndarray, bottom: np.ndarray
    ) -> np.ndarray:
        """Unit mouth axis (left - right) x (top - bottom), pointing toward +z (the viewer).

        Taken from the markers rather than a plane fit: the nested rings form a curved,
        receding surface whose best-fit plane tilts far from the mouth's opening direction.
        """
        axis = np.cross(left - right, top - bottom)
        norm = np.linalg.norm(axis)
        if norm < 1e-9:
            raise ValueError("degenerate lip markers: left-right and top-bottom are parallel")
        axis /= norm
        return axis if axis[2] >= 0 else -axis

    def _ring_angles(self, verts: np.ndarray, ring: np.ndarray) -> np.ndarray:
        """Angles of a ring's vertices on its own ellipse (left = 0, top = pi/2, right = pi,
        bottom = -pi/2): the cosine is the vertex's place from the ring's right to its left
        end (-1 .. 1), and the arc between the two ends that reaches highest is the upper
        lip's (positive angles).

        From the ring itself, not from the markers' ellipse: the inner ring of a shut mouth
        is a flat line through that ellipse's centre, where angles from the markers would
        jump from 0 to pi/2 and pi between neighbours.
        """
        left, top, right, bottom = verts[self.marker_vertices]
        u = left - right
        u -= (u @ self.axis) * self.axis
        u /= np.linalg.norm(u)
        w = np.cross(self.axis, u)
        x, y = verts[ring] @ u, verts[ring] @ w
        lo, hi = int(np.argmin(x)), int(np.argmax(x))
        half = 0.5 * (x[hi] - x[lo])
        if not half > 0:
            raise ValueError("degenerate lip contour: its ends coincide")
        cosine = np.clip((x - 0.5 * (x[hi] + x[lo])) / half, -1.0, 1.0)
        # The two arcs of the loop between its ends.
        order = np.arange(len(ring))
        a, b = sorted((lo, hi))
        one = (order > a) & (order < b)
        other = (order < a) | (order > b)
        if not other.any() or (one.any() and y[one].max() >= y[other].max()):
            upper = one
        else:
            upper = other
        return np.where(upper, 1.0, -1.0) * np.arccos(cosine)

    @staticmethod
    def _trig_basis(phi: np.ndarray) -> np.ndarray:
        return np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi), np.cos(2 * phi)], axis=1)

    def _check_disp(self, name: str, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, dtype=np.float64)
        if d.shape != (4, 3):
            raise ValueError(f"expected {name} (4, 3) (left, top, right, bottom), got {d.shape}")
        return d

    def ring_targets(
        self, marker_disp: np.ndarray, inner_disp: np.ndarray | None = None
    ) -> np.ndarray:
        """(u, 3) target displacement of each of ``ring_vertices`` in cm.

        marker_disp, inner_disp : (4, 3) displacements of the left, top, right and bottom
        markers (outer contour; inner contour, default the same), cm, model space
        """
        d = self._check_disp("marker_disp", marker_disp)
        e = d if inner_disp is None else self._check_disp("inner_disp", inner_disp)
        return self.outer_weights @ d + self.inner_weights @ e

    def control_vectors(self, velocity: np.ndarray) -> np.ndarray:
        """(u, 3) control vectors along the rings from the (4, 3) velocities of the left,
        top, right and bottom markers (cm per key frame interval)."""
        return self.ring_targets(velocity)

    def deform(
        self,
        vertices: np.ndarray,
        marker_disp: np.ndarray,
        t: float = 1.0,
        inner_disp: np.ndarray | None = None,
        velocities: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """(n, 3) ``vertices`` with the lips swept a fraction ``t`` toward their targets.

        vertices : (n, 3) current positions, cm; the rings in it are C1
        marker_disp : (4, 3) marker displacements from ``vertices`` to the target (C2)
        t : sweep time in [0, 1]; 1 reaches the target contours
        velocities : the four markers' (4, 3) velocities at C1 and at C2 (cm per sweep), which
            the lips leave C1 and reach C2 with (the control vectors); None: at rest
        """
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"expected ({self.n_vertices}, 3) vertices, got {v.shape}")
        c1 = v[self.ring_vertices]
        c2 = c1 + self.ring_targets(marker_disp, inner_disp)
        start, end = (None, None) if velocities is None else velocities
        moved = self._sweep(c1, c2, t, v[self.outer_ring].mean(axis=0), start, end) - c1
        return self._carry(v, moved)

    def between(
        self,
        base: np.ndarray,
        a: np.ndarray,
        b: np.ndarray,
        t: float,
        before: np.ndarray | None = None,
        control: bool = True,
    ) -> np.ndarray:
        """(n, 3) ``base`` with the lips on the homotopy from key frame ``a`` to ``b`` at ``t``.

        base : (n, 3) the face at t by other means (blended parameters): the lip rings are
            put on the sweep and the skin around them carried along
        a, b : (n, 3) the face at the two key frames (their rings are C1 and C2)
        before : (n, 3) the face at the key frame before ``a``, or None (a start: the lips
            leave ``a`` from rest)
        control : False sweeps without control vectors (the blending function alone)

        The control vectors are the markers' velocities, from one key frame to the next: at
        ``a`` (a - before), at ``b`` (b - a). With k = 0.5 and no per-axis n the sweep
        leaves C1 at the first and reaches C2 at the second, so consecutive in-betweens join
        at each key frame with the same velocity.
        """
        if not 0.0 <= t <= 1.0:
            raise ValueError(f"t must be in [0, 1], got {t}")
        arrays = [np.asarray(x, dtype=np.float64) for x in (base, a, b)]
        if before is not None:
            arrays.append(np.asarray(before, dtype=np.float64))
        for x in arrays:
            if x.shape != (self.n_vertices, 3):
                raise ValueError(f"expected ({self.n_vertices}, 3) vertices, got {x.shape}")
        base, a, b = arrays[:3]
        markers, rings = self.marker_vertices, self.ring_vertices
        start = end = None
        if control:
            if before is not None:
                start = a[markers] - arrays[3][markers]
            end = b[markers] - a[markers]
        centre = a[self.outer_ring].mean(axis=0)
        swept = self._sweep(a[rings], b[rings], t, centre, start, end)
        return self._carry(base, swept - base[rings])

    def _sweep(
        self,
        c1: np.ndarray,
        c2: np.ndarray,
        t: float,
        centre: np.ndarray,
        start: np.ndarray | None,
        end: np.ndarray | None,
    ) -> np.ndarray:
        """The rings' points from C1 to C2 at ``t``, leaving at the markers' (4, 3) velocity
        ``start`` and arriving at ``end`` (None: at rest)."""
        v1 = None if start is None else self.control_vectors(start)
        # sigma2 has slope -1 at t = 1 (k = 0.5): the end velocity enters negated.
        v2 = None if end is None else -self.control_vectors(end)
        return sweep(c1, c2, t, centre, self.axis, self.ring_n, self.k, v1, v2)

    def _carry(self, vertices: np.ndarray, moved: np.ndarray) -> np.ndarray:
        """``vertices`` with the rings moved by ``moved`` (u, 3), the skin around following."""
        out = vertices.copy()
        out[self.ring_vertices] += moved
        out[self.follow_vertices] += np.einsum(
            "fk,fkj->fj", self.follow_weights, moved[self.follow_rings]
        )
        return out
