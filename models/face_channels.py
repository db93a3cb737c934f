"""The face's per-frame parameters as protocol channels, and the steps that quantise them.

Both ends agree on what each channel means (docs/protocol.md section 6):

- ``pose.rotation`` (3): rotation vector, radians, of R relative to the frontal pose
  (R = R_rel @ diag(1, -1, -1)), so a face looking into the camera sends zeros;
- ``pose.scale`` (1): ln(scale), scale in pixels per cm;
- ``pose.translation`` (3): translation in image pixels;
- ``wire`` (K): coefficients of the rig's wire basis (:class:`WireBasis`), in cm.

The steps are chosen from the error they may cause on screen: each channel moves the face's
vertices by at most ``error_px`` pixels RMS at the call's size, and no vertex by more than a
few times that (see :func:`channel_steps`).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from models.mesh import data_path
from models.pose import FRONTAL, Pose

logger = logging.getLogger(__name__)

POSE_ROTATION = "pose.rotation"
POSE_SCALE = "pose.scale"
POSE_TRANSLATION = "pose.translation"
WIRE = "wire"
#: Hysteresis of the sender's quantiser, in steps: a value moves to a new level only when it
#: is more than 0.5 + HYSTERESIS steps from the current one, so tracker jitter below that costs
#: no bits. The quantisation error is then at most (0.5 + HYSTERESIS) steps.
HYSTERESIS = 0.25
#: Default per-channel error budget, px at the call's size: the RMS, over the face's vertices,
#: of the displacement one channel's quantisation may cause (with hysteresis: see
#: :func:`channel_steps`). The RMS, not the largest displacement, is what the picture's error
#: follows: a step of the head's position moves every vertex, one of a wire coefficient a few.
#: benchmarks/bench_ablation.py names quantisation the largest loss on the geometry path; with
#: the budget split this way carphone's face loses less for fewer bits (BENCHMARKS.md, "the
#: error budget").
DEFAULT_ERROR_PX = 0.2
#: ... and no vertex moves more than this many times the budget: a blink's or a lip's few
#: vertices keep their precision.
PEAK_FACTOR = 3.0
#: The sender's One Euro filters (sender/channel_filter.py) count a value's speed in units that
#: move no vertex by more than this, px: their settings were tuned in such units.
FILTER_UNIT_PX = 0.4 / (0.5 + HYSTERESIS)


@dataclass(frozen=True)
class WireBasis:
    """A reduced basis of wire parameters shared by both ends (part of the rig).

    vectors : (K, P) float64, each a wire parameter offset from rest whose largest vertex
        displacement on the canonical mesh is 1 cm, so a coefficient is in cm
    """

    vectors: np.ndarray
    sources: tuple[str, ...] = ()

    @property
    def size(self) -> int:
        return len(self.vectors)

    def params(self, coefficients: np.ndarray) -> np.ndarray:
        """(K,) coefficients -> (P,) wire parameter offsets from rest."""
        c = np.asarray(coefficients, dtype=np.float64)
        if c.shape != (self.size,):
            raise ValueError(f"expected ({self.size},) coefficients, got shape {c.shape}")
        return np.asarray(c @ self.vectors)

    def projector(self, displacement_matrix: sp.spmatrix | np.ndarray) -> np.ndarray:
        """(K, P) matrix taking parameter offsets to the coefficients whose vertex
        displacements are closest (least squares over all vertices) to theirs."""
        m = displacement_matrix
        mb = np.asarray(m @ self.vectors.T)  # (3n, K)
        return np.asarray(np.linalg.solve(mb.T @ mb, np.asarray(m.T @ mb).T))


def load_wire_basis(path: str | Path | None = None) -> WireBasis:
    """The bundled basis (``models/data/wire_basis.npz``, made by tools/make_wire_basis.py)."""
    path = data_path("wire_basis.npz") if path is None else Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            vectors = np.asarray(data["vectors"], dtype=np.float64)
            sources = tuple(str(s) for s in data["sources"])
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"cannot read wire basis {path}: {exc}") from exc
    if vectors.ndim != 2 or not np.all(np.isfinite(vectors)):
        raise ValueError(f"wire basis {path}: expected a finite (K, P) array")
    return WireBasis(vectors, sources)


def rig_hash(paths: tuple[Path, ...] | None = None) -> str:
    """SHA-256 (hex) over the rig data both ends must share: the rig and the wire basis."""
    paths = paths or (data_path("rig.json"), data_path("wire_basis.npz"))
    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()


def pose_channels(pose: Pose) -> dict[str, np.ndarray]:
    """Pose -> float channel values (radians, ln px/cm, px)."""
    relative = pose.rotation @ FRONTAL.T
    return {
        POSE_ROTATION: Rotation.from_matrix(relative).as_rotvec(),
        POSE_SCALE: np.array([np.log(pose.scale)]),
        POSE_TRANSLATION: np.asarray(pose.translation, dtype=np.float64).copy(),
    }


def pose_from_channels(values: dict[str, np.ndarray]) -> Pose:
    """Inverse of :func:`pose_channels`."""
    relative = Rotation.from_rotvec(np.asarray(values[POSE_ROTATION], np.float64)).as_matrix()
    scale = float(np.exp(np.asarray(values[POSE_SCALE], np.float64)[0]))
    return Pose(relative @ FRONTAL, scale, np.asarray(values[POSE_TRANSLATION], np.float64))


@dataclass(frozen=True)
class ChannelReach:
    """How far one unit of each channel moves the face on screen, px.

    rms : RMS over the face's vertices, for the channel's value that moves them most
    peak : the most any vertex moves, for the value that moves one most
    """

    rms: dict[str, float]
    peak: dict[str, float]


def channel_reach(
    vertices_cm: np.ndarray, wire_displacements_cm: np.ndarray, scale_px_per_cm: float
) -> ChannelReach:
    """The reach of each channel for a face at session start.

    vertices_cm : (n, 3) the snapshot's mesh in the head's frame (about the pose origin)
    wire_displacements_cm : (K, n, 3) each wire basis coefficient's unit displacement
    scale_px_per_cm : the face's scale at session start

    The view is orthographic: only x and y of a displacement move a pixel. A rotation by d
    rad about axis a moves vertex v by d (a x v), a log-scale step d by d v, a translation
    step d px by d px, a wire coefficient d by d times its displacement.
    """
    v = np.asarray(vertices_cm, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not scale_px_per_cm > 0:
        raise ValueError(f"vertices {v.shape}, scale {scale_px_per_cm}: no face to measure")

    def moved(displacements: np.ndarray) -> tuple[float, float]:
        """(RMS over vertices, largest) on screen, px, for the worst of (m, n, 3)."""
        px = np.linalg.norm(displacements[..., :2], axis=-1) * scale_px_per_cm
        return float(np.sqrt((px**2).mean(axis=-1)).max()), float(px.max())

    axes = np.eye(3)
    rotation = np.stack([np.cross(a, v) for a in axes])
    wires = np.asarray(wire_displacements_cm, np.float64).reshape(-1, len(v), 3)
    reach = {
        POSE_ROTATION: moved(rotation),
        POSE_SCALE: moved(v[None]),
        POSE_TRANSLATION: (1.0, 1.0),  # in pixels already: a unit moves every vertex 1 px
        WIRE: moved(wires),
    }
    return ChannelReach(
        rms={k: r for k, (r, _) in reach.items()}, peak={k: p for k, (_, p) in reach.items()}
    )


def channel_steps(
    reach: ChannelReach, error_px: float = DEFAULT_ERROR_PX, peak_factor: float = PEAK_FACTOR
) -> dict[str, float]:
    """Quantisation steps so that each channel moves the face's vertices by at most
    ``error_px`` RMS and no vertex by more than ``peak_factor * error_px``.

    With the sender's hysteresis the error of one value is up to (0.5 + HYSTERESIS) steps.
    """
    if not (error_px > 0 and peak_factor >= 1):
        raise ValueError(f"error {error_px} must be > 0 and peak factor {peak_factor} >= 1")
    budget = error_px / (0.5 + HYSTERESIS)
    return {
        name: min(budget / reach.rms[name], peak_factor * budget / reach.peak[name])
        for name in reach.rms
    }


def filter_units(reach: ChannelReach) -> dict[str, float]:
    """The units of :data:`FILTER_UNIT_PX` for each channel (see sender/channel_filter.py)."""
    return {name: FILTER_UNIT_PX / peak for name, peak in reach.peak.items()}
