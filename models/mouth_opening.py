"""The mouth's opening: two GDEs on the inner lips, where the wires cannot part them.

The rig's lip wires move each lip as a whole, and the inner lips' vertices lie under both
lips' wires, so no wire parameters part them: on carphone (real footage) the tracker saw the
inner lips 12.5 px apart in a shout and the wire fit kept them 1.9 px apart, the lips
stretched over the open mouth. Two geometry deformation elements (seed 002,
:mod:`models.gde`), centred on the upper and the lower inner lip and kept apart by the mouth's
seam, carry what the wires leave: the vertical offset of each centre from where the wires put
it (the lips part up and down; sideways the wires follow them, and x cost bits for jitter).
They reach the inner lips' own band only, so the outer lips stay the wires'. On the same
frame the call parts them 10.5 px.
"""

from __future__ import annotations

import numpy as np

from models.gde import GdeDef, GdeSet, rig_mouth_seam
from models.mesh import FaceMesh
from models.rig import Rig

#: Canonical mesh vertices (MediaPipe's topology): the upper and the lower inner lip's centre.
INNER_LIP_VERTICES = (13, 14)
#: Radius of each element, cm: the inner lips' own band. At 1.5 cm the outer lips move too.
SIZE_CM = 1.0
#: Values of the ``lips`` channel (models.face_channels.LIPS): y of each centre's offset, cm,
#: model space (y up).
LIPS_SIZE = len(INNER_LIP_VERTICES)


class MouthOpening:
    """The two inner-lip elements on one session's mesh (the same at both ends)."""

    def __init__(self, mesh: FaceMesh, rig: Rig) -> None:
        specs = [GdeDef(f"inner_lip_{v}", v, SIZE_CM, "euclidean") for v in INNER_LIP_VERTICES]
        self.gdes = GdeSet(mesh, specs, cut_edges=rig_mouth_seam(mesh, rig.lips))
        self._centres = np.array(INNER_LIP_VERTICES, dtype=np.int64)

    def values(self, tracked: np.ndarray, deformed: np.ndarray) -> np.ndarray:
        """(LIPS_SIZE,) what the wires leave at the inner lips' centres: ``tracked`` (n, 3)
        the face as tracked and ``deformed`` (n, 3) as the wires rebuild it, model space, cm."""
        offset = np.asarray(tracked, np.float64) - np.asarray(deformed, np.float64)
        return np.asarray(offset[self._centres, 1])

    def displacement(self, values: np.ndarray) -> np.ndarray:
        """(n, 3) per-vertex displacement, cm, for the channel's (LIPS_SIZE,) values."""
        v = np.asarray(values, np.float64)
        if v.shape != (LIPS_SIZE,):
            raise ValueError(f"expected ({LIPS_SIZE},) lips values, got shape {v.shape}")
        control = np.zeros((len(self._centres), 3))
        control[:, 1] = v
        return self.gdes.displacement_field(control)
