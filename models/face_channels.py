"""The face's per-frame parameters as protocol channels, and the steps that quantise them.

Both ends agree on what each channel means (docs/protocol.md section 6):

- ``pose.rotation`` (3): rotation vector, radians, of R relative to the frontal pose
  (R = R_rel @ diag(1, -1, -1)), so a face looking into the camera sends zeros;
- ``pose.scale`` (1): ln(scale), scale in pixels per cm;
- ``pose.translation`` (3): translation in image pixels;
- ``wire`` (K): coefficients of the rig's wire basis (:class:`WireBasis`), in cm;
- ``lips`` (8): the inner lip contour where the wires cannot put it, four markers' x and y,
  in cm (:mod:`facewire.models.mouth_opening`).

The steps are chosen from the error they may cause on screen: each channel moves no vertex by
more than ``error_px`` pixels at the call's size (see :func:`channel_steps`).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from facewire.models.mesh import data_path
from facewire.models.pose import FRONTAL, Pose

logger = logging.getLogger(__name__)

POSE_ROTATION = "pose.rotation"
POSE_SCALE = "pose.scale"
POSE_TRANSLATION = "pose.translation"
WIRE = "wire"
LIPS = "lips"
#: Hysteresis of the sender's quantiser, in steps: a value moves to a new level only when it
#: is more than 0.5 + HYSTERESIS steps from the current one, so tracker jitter below that costs
#: no bits. The quantisation error is then at most (0.5 + HYSTERESIS) steps.
HYSTERESIS = 0.25
#: Default per-channel error budget: the most one channel's quantisation moves a vertex, px.
#: Quantisation was the step of the geometry path that lost most (benchmarks/bench_ablation.py:
#: carphone's face SSIM 0.783 before it, 0.772 after at 0.4 px). Finer steps cost bits that
#: only a face that moves little can afford, so the rate cap widens the hysteresis as its
#: bucket runs low (sender/rate_cap.py): at 0.25 px five talking heads gain up to 0.010 face
#: SSIM and none loses (docs/what-we-tried.md, "A finer quantiser under the rate cap").
DEFAULT_ERROR_PX = 0.25
#: The head's pose gets this share of the budget: it moves every pixel of the face at once,
#: so a finer step there buys the most picture per bit (carphone: pose steps x0.5 gave +0.011
#: face SSIM for 0.19 kbit/s, the wires' x0.5 +0.003 for 0.27; docs/what-we-tried.md,
#: "The pose's share of the error budget").
POSE_SHARE = 0.8


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
    """SHA-256 (hex) over the rig data both ends must share: the rig, the wire basis and the
    canonical mesh (the snapshot's vertices are coded against it, protocol/mesh_code.py)."""
    paths = paths or (
        data_path("rig.json"),
        data_path("wire_basis.npz"),
        data_path("canonical_face_mesh.obj"),
    )
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


def channel_steps(
    face_radius_cm: float, scale_px_per_cm: float, error_px: float = DEFAULT_ERROR_PX
) -> dict[str, float]:
    """Quantisation steps so that each channel moves no vertex by more than ``error_px``.

    face_radius_cm : largest distance of a mesh vertex from the head's pivot (the pose origin)
    scale_px_per_cm : the face's scale at session start

    With the sender's hysteresis the error of one value is up to (0.5 + HYSTERESIS) steps:
    a rotation step d moves a vertex r * d px, a log-scale step r * d px (r the face radius in
    px), a translation step d px, and a wire coefficient (cm, max displacement 1 cm per unit)
    scale * d px, and a lips value (cm, its marker's vertex moves by it) scale * d px: its
    step is twice the budget's, the lips' parting being seen to about a pixel (at half the
    step carphone paid 0.09 kbit/s for it instead of 0.05, mostly for a shut mouth's jitter).
    The pose's three channels get POSE_SHARE of the budget.
    """
    if not (face_radius_cm > 0 and scale_px_per_cm > 0 and error_px > 0):
        raise ValueError(
            f"radius {face_radius_cm}, scale {scale_px_per_cm} and error {error_px} must be > 0"
        )
    budget = error_px / (0.5 + HYSTERESIS)
    radius_px = face_radius_cm * scale_px_per_cm
    return {
        POSE_ROTATION: POSE_SHARE * budget / radius_px,
        POSE_SCALE: POSE_SHARE * budget / radius_px,
        POSE_TRANSLATION: POSE_SHARE * budget,
        WIRE: budget / scale_px_per_cm,
        LIPS: 2 * budget / scale_px_per_cm,
    }
