"""Wire deformation (Singh & Fiume) and wire extraction (seed 000, Pyun et al.).

Every wire j has a reference curve R_j (a cubic B-spline through a vertex chain of the
base mesh), a range r_j (cm) and a radial scale s_j; the wire W_j has the control points
of R_j displaced by q_j (n_ctrl_j, 3). For a base vertex p_i with nearest point p_iRj on
R_j, x = |p_i - p_iRj| / r_j and f_ij = f(x) = (x^2 - 1)^2 for x < 1, else 0. Eq. 2-3:

    dp_i = sum_j w_ij [(s_j - 1)(p_i - p_iRj) + sum_l B_l(u_ij) q_jl],
    w_ij = f_ij^(k+1) / sum_j f_ij^k.

Written that way (rather than with the paper's c_i of Eq. 9-10, whose sign disagrees
with Eq. 8) the displacement is linear in x = (s - 1, q): dp = A x, with A the
(3n, P) matrix of Eq. 12, so s = 1, q = 0 gives exactly no displacement. Everything that
depends only on the base mesh (closest points, f, w, A, the pseudo-inverse of Eq. 13) is
computed once; deform is one sparse product and fit one dense product.

Parameter layout: ``params`` (P,) = s (one per curve, in curve order), then every
curve's q (n_ctrl_j, 3) flattened row-major, curves in order.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp

from facewire.models import bspline

logger = logging.getLogger(__name__)

DEFAULT_RCOND = 1e-10


class CurveLike(Protocol):
    """Anything shaped like a rig wire curve (models.rig.WireCurve fits)."""

    name: str
    vertices: Sequence[int]
    control_points: int
    range: float
    feature: str


@dataclass(frozen=True)
class WireCurveSpec:
    """One wire's reference curve, as named in the rig.

    vertices : ordered vertex indices of the base mesh that the curve follows
    control_points : number of B-spline control points (>= 4, <= len(vertices))
    range : r_j, the distance in cm at which the wire's influence falls to zero
    feature : "eyes", "brows", "mouth", ... (the blending group)
    """

    name: str
    vertices: tuple[int, ...]
    control_points: int
    range: float
    feature: str = "other"


def falloff(x: np.ndarray) -> np.ndarray:
    """f(x) = (x^2 - 1)^2 for 0 <= x < 1, else 0 (seed 000, section 3)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x < 1.0, (x * x - 1.0) ** 2, 0.0)


def _as_vertices(v: Any, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"expected (n, 3) {what}, got shape {a.shape}")
    return a


class WireDeformer:
    """Affine wire deformation of one base mesh, with its least-squares inverse.

    base_vertices : (n, 3) float, cm, model space
    curves : reference curve specs (vertex chains into base_vertices)
    k : localizing parameter (>= 0) of Eq. 3
    rcond : singular values of A below rcond * max are dropped in the pseudo-inverse
    """

    def __init__(
        self,
        base_vertices: np.ndarray,
        curves: Sequence[CurveLike],
        k: float,
        rcond: float = DEFAULT_RCOND,
    ) -> None:
        base = _as_vertices(base_vertices, "base vertices")
        if not curves:
            raise ValueError("a wire deformer needs at least one curve")
        ref = []
        for c in curves:
            chain = np.asarray(c.vertices, dtype=np.int64)
            if chain.ndim != 1 or len(chain) < 2:
                raise ValueError(f"curve {c.name!r}: expected a chain of >= 2 vertices")
            if chain.min() < 0 or chain.max() >= len(base):
                raise ValueError(
                    f"curve {c.name!r}: vertex index {int(chain.max())} "
                    f"out of range 0..{len(base) - 1}"
                )
            try:
                ref.append(bspline.fit_control_points(base[chain], int(c.control_points)))
            except ValueError as exc:
                raise ValueError(f"curve {c.name!r}: {exc}") from exc
        self.chains = [tuple(int(i) for i in c.vertices) for c in curves]
        self._setup(
            base,
            [str(c.name) for c in curves],
            [str(c.feature) for c in curves],
            ref,
            [float(c.range) for c in curves],
            k,
            rcond,
        )

    @classmethod
    def from_rig(cls, vertices: np.ndarray, rig: Any, rcond: float = DEFAULT_RCOND) -> WireDeformer:
        """Deformer for ``vertices`` (n, 3) from a models.rig.Rig (its curves and localize_k)."""
        return cls(vertices, list(rig.curves), float(rig.localize_k), rcond)

    @classmethod
    def from_control_points(
        cls,
        base_vertices: np.ndarray,
        reference_control_points: Sequence[np.ndarray],
        ranges: Sequence[float],
        k: float,
        names: Sequence[str] | None = None,
        features: Sequence[str] | None = None,
        rcond: float = DEFAULT_RCOND,
    ) -> WireDeformer:
        """Deformer whose reference curves are given directly by control points (n_ctrl_j, 3)."""
        m = len(reference_control_points)
        names = list(names) if names is not None else [f"wire{j}" for j in range(m)]
        features = list(features) if features is not None else ["other"] * m
        if not (len(ranges) == len(names) == len(features) == m) or m == 0:
            raise ValueError(
                f"expected matching non-empty lists, got {m} control point sets, "
                f"{len(ranges)} ranges, {len(names)} names, {len(features)} features"
            )
        self = cls.__new__(cls)
        self.chains = []
        cps = [np.asarray(c, dtype=np.float64) for c in reference_control_points]
        self._setup(
            _as_vertices(base_vertices, "base vertices"),
            [str(n) for n in names],
            [str(f) for f in features],
            cps,
            [float(r) for r in ranges],
            k,
            rcond,
        )
        return self

    def _setup(
        self,
        base: np.ndarray,
        names: list[str],
        features: list[str],
        ref_cps: list[np.ndarray],
        ranges: list[float],
        k: float,
        rcond: float,
    ) -> None:
        if len(set(names)) != len(names):
            raise ValueError(f"curve names must be unique, got {names}")
        if not k >= 0.0:
            raise ValueError(f"localizing parameter k must be >= 0, got {k}")
        for name, cp, r in zip(names, ref_cps, ranges, strict=True):
            if cp.ndim != 2 or cp.shape[1] != 3 or len(cp) < 4:
                raise ValueError(
                    f"curve {name!r}: expected (>= 4, 3) control points, got {cp.shape}"
                )
            if not r > 0.0:
                raise ValueError(f"curve {name!r}: range must be > 0 cm, got {r}")
        self.base_vertices = base
        self.names = names
        self.features = features
        self.reference_control_points = ref_cps
        self.ranges = np.asarray(ranges)
        self.k = float(k)
        self.rcond = float(rcond)
        n, m = len(base), len(names)
        sizes = [3 * len(cp) for cp in ref_cps]
        offsets = m + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
        self.q_slices = [slice(int(o), int(o) + s) for o, s in zip(offsets, sizes, strict=True)]
        self.n_params = m + int(sum(sizes))

        u = np.zeros((n, m))
        closest = np.zeros((m, n, 3))
        for j, cp in enumerate(ref_cps):
            u[:, j], closest[j] = bspline.closest_points(cp, base)
        dist = np.linalg.norm(base[None, :, :] - closest, axis=2).T  # (n, m)
        f = falloff(dist / self.ranges[None, :])
        # Wires that do not reach a vertex take no part in its blend (also for k = 0).
        fk = np.where(f > 0.0, f**self.k, 0.0)
        denom = fk.sum(axis=1, keepdims=True)
        w = np.divide(f * fk, denom, out=np.zeros_like(f), where=denom > 0.0)
        self.curve_parameters = u
        self.closest_points = closest
        self.falloff = f
        self.weights = w
        self.reached = np.flatnonzero((w > 0.0).any(axis=1))
        self.matrix = self._assemble(base, closest, u, w)
        logger.debug(
            "wire deformer: %d vertices (%d reached), %d curves, %d params, nnz(A) = %d",
            n,
            len(self.reached),
            m,
            self.n_params,
            self.matrix.nnz,
        )

    def _assemble(
        self, base: np.ndarray, closest: np.ndarray, u: np.ndarray, w: np.ndarray
    ) -> sp.csr_matrix:
        rows, cols, vals = [], [], []
        for j, cp in enumerate(self.reference_control_points):
            idx = np.flatnonzero(w[:, j] > 0.0)
            if not len(idx):
                logger.warning("wire %r reaches no vertex", self.names[j])
                continue
            wj = w[idx, j]
            # s_j column: w_ij (p_i - p_iRj), rows 3i + c.
            off = (base[idx] - closest[j, idx]) * wj[:, None]
            rows.append((3 * idx[:, None] + np.arange(3)).ravel())
            cols.append(np.full(3 * len(idx), j))
            vals.append(off.ravel())
            # q_jl columns: w_ij B_l(u_ij) on each coordinate.
            b = bspline.basis_matrix(u[idx, j], len(cp)) * wj[:, None]  # (r, n_ctrl)
            ii, ll = np.nonzero(b)
            for c in range(3):
                rows.append(3 * idx[ii] + c)
                cols.append(self.q_slices[j].start + 3 * ll + c)
                vals.append(b[ii, ll])
        a = sp.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(3 * len(base), self.n_params),
        ).tocsr()
        a.sum_duplicates()
        return a

    # -- parameters -------------------------------------------------------------------

    @property
    def n_curves(self) -> int:
        return len(self.names)

    @property
    def n_vertices(self) -> int:
        return len(self.base_vertices)

    @property
    def s_slice(self) -> slice:
        return slice(0, self.n_curves)

    @cached_property
    def param_names(self) -> list[str]:
        """(P,) names: "<curve>.s", then "<curve>.q<l>.<x|y|z>"."""
        out = [f"{n}.s" for n in self.names]
        for n, cp in zip(self.names, self.reference_control_points, strict=True):
            out += [f"{n}.q{i}.{c}" for i in range(len(cp)) for c in "xyz"]
        return out

    def curve_param_indices(self, j: int) -> np.ndarray:
        """Indices into params of curve j: its s, then its q."""
        qs = self.q_slices[j]
        return np.concatenate([[j], np.arange(qs.start, qs.stop)])

    def feature_groups(self) -> dict[str, np.ndarray]:
        """feature name -> sorted param indices of all curves with that feature."""
        groups: dict[str, list[np.ndarray]] = {}
        for j, feat in enumerate(self.features):
            groups.setdefault(feat, []).append(self.curve_param_indices(j))
        return {f: np.sort(np.concatenate(v)) for f, v in groups.items()}

    def rest_params(self) -> np.ndarray:
        """(P,) s = 1, q = 0: the base mesh exactly."""
        p = np.zeros(self.n_params)
        p[self.s_slice] = 1.0
        return p

    def _check_params(self, params: np.ndarray) -> np.ndarray:
        p = np.asarray(params, dtype=np.float64)
        if p.shape != (self.n_params,):
            raise ValueError(f"expected ({self.n_params},) wire params, got shape {p.shape}")
        return p

    def split_params(self, params: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """params (P,) -> (s (m,), [q_j (n_ctrl_j, 3)])."""
        p = self._check_params(params)
        return p[self.s_slice].copy(), [p[qs].reshape(-1, 3).copy() for qs in self.q_slices]

    def join_params(self, s: np.ndarray, q: Sequence[np.ndarray]) -> np.ndarray:
        """Inverse of split_params."""
        s = np.asarray(s, dtype=np.float64)
        if s.shape != (self.n_curves,) or len(q) != self.n_curves:
            raise ValueError(
                f"expected {self.n_curves} scales and {self.n_curves} q arrays, "
                f"got shape {s.shape} and {len(q)}"
            )
        parts = [s]
        for j, qj in enumerate(q):
            qj = np.asarray(qj, dtype=np.float64)
            if qj.shape != self.reference_control_points[j].shape:
                raise ValueError(
                    f"curve {self.names[j]!r}: expected q of shape "
                    f"{self.reference_control_points[j].shape}, got {qj.shape}"
                )
            parts.append(qj.ravel())
        return np.concatenate(parts)

    def wire_control_points(self, params: np.ndarray) -> list[np.ndarray]:
        """Control points (n_ctrl_j, 3) of every wire curve W_j = R_j + q_j."""
        _, q = self.split_params(params)
        return [r + qj for r, qj in zip(self.reference_control_points, q, strict=True)]

    # -- deformation and extraction ---------------------------------------------------

    def displacement(self, params: np.ndarray) -> np.ndarray:
        """(n, 3) vertex displacements, cm, for params (P,)."""
        x = self._check_params(params).copy()
        x[self.s_slice] -= 1.0
        return (self.matrix @ x).reshape(-1, 3)

    def deform(self, params: np.ndarray) -> np.ndarray:
        """(n, 3) deformed vertices, cm, model space (Eq. 2-3)."""
        return self.base_vertices + self.displacement(params)

    @cached_property
    def _solver(self) -> tuple[np.ndarray, int, float]:
        # Eq. 13: (A^T A)^+ A^T = A^+; the SVD of A itself avoids squaring its condition
        # number. Rows of vertices no wire reaches are zero, so they are left out.
        rows = (3 * self.reached[:, None] + np.arange(3)).ravel()
        a = self.matrix[rows].toarray()
        u, sv, vt = np.linalg.svd(a, full_matrices=False)
        keep = sv > self.rcond * (sv[0] if len(sv) else 0.0)
        rank = int(keep.sum())
        if rank < self.n_params:
            logger.warning(
                "wire system is rank deficient (%d of %d); fit returns the least-change solution",
                rank,
                self.n_params,
            )
        condition = float(sv[0] / sv[keep][-1]) if rank else float("inf")
        pinv = np.asarray((vt[keep].T / sv[keep]) @ u[:, keep].T)
        return pinv, rank, condition

    @property
    def rank(self) -> int:
        """Numerical rank of A (n_params when every parameter is determined by a fit)."""
        return self._solver[1]

    @property
    def condition(self) -> float:
        """Condition number of A over the kept singular values."""
        return self._solver[2]

    def prepare_fit(self) -> None:
        """Compute the pseudo-inverse now (otherwise on the first fit)."""
        _ = self._solver

    def fit_displacement(self, displacement: np.ndarray) -> np.ndarray:
        """(P,) least-squares params for vertex displacements (n, 3), cm (Eq. 12-13)."""
        d = _as_vertices(displacement, "displacements")
        if len(d) != self.n_vertices:
            raise ValueError(f"expected ({self.n_vertices}, 3) displacements, got {d.shape}")
        x = self._solver[0] @ d[self.reached].ravel()
        x[self.s_slice] += 1.0
        return np.asarray(x)

    def fit(self, target_vertices: np.ndarray) -> np.ndarray:
        """(P,) least-squares params so that deform(params) ~ target_vertices (n, 3), cm."""
        t = _as_vertices(target_vertices, "target vertices")
        if len(t) != self.n_vertices:
            raise ValueError(f"expected ({self.n_vertices}, 3) target vertices, got {t.shape}")
        return self.fit_displacement(t - self.base_vertices)

    def rms_error(self, params: np.ndarray, target_vertices: np.ndarray) -> float:
        """Root mean square vertex distance, cm, between deform(params) and the target."""
        t = _as_vertices(target_vertices, "target vertices")
        return float(np.sqrt(((self.deform(params) - t) ** 2).sum(axis=1).mean()))
