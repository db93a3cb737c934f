"""The mouth's opening: the inner lip contour, where the wires cannot put it (seed 003).

The rig's lip wires move each lip as a whole, and the inner lips' vertices lie under both
lips' wires, so no wire parameters part them: on carphone (real footage) the tracker saw the
inner lips 12.5 px apart in a shout and the wire fit kept them 1.9 px apart, the lips
stretched over the open mouth.

Seed 003's mouth model (section 3.7, :class:`facewire.models.homotopy.MouthRig`) carries what the
wires leave: the inner contour moves by the displacement of four markers on it (left, top,
right, bottom), spread around the contour by angle on the ellipse through them, and the two
rings between the inner and the outer contour take 2/3 and 1/3 of it, so the lips' body
stretches evenly while the outer contour stays where the wires put it. The four markers'
x and y (model space) are the ``lips`` channel; each frame they are the least-squares fit
of that displacement to the inner contour as tracked, against where the wires put it, the
markers' own vertices weighing most.

Two GDEs (seed 002) on the inner lips' centres did this before: they parted the centres as
far as tracked but left the sides of the lower lip under the wires, so a mouth open in an
O came out as a lens with a W for its lower edge, the lower lip stretched down over it
(docs/what-we-tried.md, "The inner lips from the mouth rig").
"""

from __future__ import annotations

import numpy as np

from facewire.models.homotopy import MouthRig
from facewire.models.mesh import FaceMesh
from facewire.models.rig import Rig

#: Values of the ``lips`` channel (models.face_channels.LIPS): x then y of the left, top,
#: right and bottom markers' displacement, cm, model space (y up).
LIPS_SIZE = 8
#: Weight of the four marker vertices in the fit against the contour's other vertices. The
#: lips' centres part as far as tracked (a plain least-squares fit left the bundled clip's
#: widest jaw 14 % short: the contour's arc is rounder than a shout's), and the sides follow.
#: 4 against 1 gave carphone's mouth 0.742 SSIM, 1 against 1 0.739, markers alone 0.741.
MARKER_WEIGHT = 4.0


class MouthOpening:
    """The inner contour's four-marker displacement on one session's mesh (the same at both
    ends)."""

    def __init__(self, mesh: FaceMesh, rig: Rig) -> None:
        self.rig = MouthRig.from_rig(mesh, rig)
        inner = np.asarray(rig.lips.contours[-1], dtype=np.int64)
        # The map is linear (the sweep's end, t = 1, is C1 plus the ring targets), and the
        # same for x, y and z: (n, 4) weights of the four markers' displacement per vertex.
        rest = np.asarray(mesh.vertices, dtype=np.float64)
        weights = np.zeros((len(rest), 4))
        for k in range(4):
            unit = np.zeros((4, 3))
            unit[k, 0] = 1.0
            weights[:, k] = (
                self.rig.deform(rest, np.zeros((4, 3)), 1.0, inner_disp=unit)[:, 0] - rest[:, 0]
            )
        self._weights = weights
        on_inner = weights[inner]
        # Weighted least squares, the four marker vertices (each the vertex its own weight
        # peaks at) weighing MARKER_WEIGHT times more: (4, len(inner)).
        weight = np.ones(len(inner))
        weight[np.argmax(np.abs(on_inner), axis=0)] = MARKER_WEIGHT
        root = np.sqrt(weight)[:, None]
        self._fit = np.linalg.pinv(on_inner * root) * root.T
        self._inner = inner

    def values(self, tracked: np.ndarray, deformed: np.ndarray) -> np.ndarray:
        """(LIPS_SIZE,) what the wires leave on the inner contour: ``tracked`` (n, 3) the face
        as tracked and ``deformed`` (n, 3) as the wires rebuild it, model space, cm."""
        offset = np.asarray(tracked, np.float64) - np.asarray(deformed, np.float64)
        markers = self._fit @ offset[self._inner, :2]  # (4, 2)
        return np.asarray(markers.T.ravel())

    def displacement(self, values: np.ndarray) -> np.ndarray:
        """(n, 3) per-vertex displacement, cm, for the channel's (LIPS_SIZE,) values."""
        v = np.asarray(values, np.float64)
        if v.shape != (LIPS_SIZE,):
            raise ValueError(f"expected ({LIPS_SIZE},) lips values, got shape {v.shape}")
        out = np.zeros((len(self._weights), 3))
        out[:, :2] = self._weights @ v.reshape(2, 4).T
        return out
