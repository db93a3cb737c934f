"""Pictures between two received frames: the face's parameters blended feature by feature.

A frame's parameters are the head's pose, the rig's wire parameters, the camera's motion and
the face's edge corrections.
Between frames a and b, at t in [0, 1] (0: a, 1: b, by time):

- the wire parameters blend feature by feature (seed 000, section 5, Fig. 4-6, through
  :func:`facewire.models.blending.blend`): the eyes' curves follow sqrt(t), the mouth's t^3 and
  every other feature t, so eyes and mouth move on their own curves; the inner lips' opening
  follows the mouth's;
- the lips themselves, the mouth rig's four contours, go from frame a's contours to frame b's
  on seed 003's homotopy sweep (:meth:`facewire.models.homotopy.MouthRig.between`), with the four
  lip markers' velocities at both frames as its control vectors, and the skin around them
  follows. On real footage this puts the lips between frames 12-41% nearer where they were
  than the mouth's t^3 (BENCHMARKS.md, "The lips between frames");
- the head turns along the shortest arc between the two rotations (slerp) at an even rate,
  its scale changes geometrically and its position linearly: a rigid head, never a blend of
  matrices (which shears the face in a fast turn);
- the scene's four corners move linearly (the camera's motion as the protocol carries it),
  and so do the face's edge corrections (models/edge.py).

:class:`Painter` draws exact frames and blends through one
:class:`~facewire.receiver.decoder.FaceDecoder`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from facewire.models.blending import blend
from facewire.models.camera import corners_from_homography, homography_from_corners
from facewire.models.pose import Pose
from facewire.protocol.channels import FrameValues

if TYPE_CHECKING:
    from facewire.receiver.decoder import FaceDecoder

logger = logging.getLogger(__name__)

#: Frames whose faces the painter keeps (the lips' control vectors look one frame back).
KEPT_FACES = 4


@dataclass(frozen=True, eq=False)
class FaceState:
    """What one picture shows: the head's pose, (P,) wire parameters, the inner lips'
    opening, the camera's (3, 3) homography from the snapshot frame, the face's edge
    corrections (models/edge.py) and the body's (3, 3) motion before the camera's
    (models/body.py)."""

    pose: Pose
    wires: np.ndarray
    lips: np.ndarray
    camera: np.ndarray
    edge: np.ndarray
    body: np.ndarray


def blend_pose(a: Pose, b: Pose, t: float) -> Pose:
    """The pose a fraction ``t`` of the way from ``a`` to ``b``: rotation by slerp, scale
    geometric (log-linear), translation linear. t = 0 gives ``a``, t = 1 gives ``b``."""
    _check_t(t)
    if t == 0.0:
        return a
    if t == 1.0:
        return b
    turn = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.rotation, b.rotation])))
    rotation = turn([t]).as_matrix()[0]
    scale = float(np.exp((1.0 - t) * np.log(a.scale) + t * np.log(b.scale)))
    translation = (1.0 - t) * a.translation + t * b.translation
    return Pose(rotation, scale, translation)


def blend_camera(a: np.ndarray, b: np.ndarray, t: float, width: int, height: int) -> np.ndarray:
    """(3, 3) homography whose frame corners lie a fraction ``t`` of the way between where
    homographies ``a`` and ``b`` put them (width x height frame)."""
    _check_t(t)
    ca = corners_from_homography(a, width, height)
    cb = corners_from_homography(b, width, height)
    return homography_from_corners((1.0 - t) * ca + t * cb, width, height)


def blend_state(
    a: FaceState,
    b: FaceState,
    t: float,
    groups: dict[str, np.ndarray],
    size: tuple[int, int],
) -> FaceState:
    """The face a fraction ``t`` of the way from ``a`` to ``b``.

    groups : feature name -> indices into the wire parameters (WireDeformer.feature_groups())
    size : (width, height) of the frame, for the camera's corners
    """
    return FaceState(
        blend_pose(a.pose, b.pose, t),
        blend(a.wires, b.wires, t, groups),
        blend(a.lips, b.lips, t, {"mouth": np.arange(len(a.lips))}),  # on the mouth's curve
        blend_camera(a.camera, b.camera, t, *size),
        (1.0 - t) * a.edge + t * b.edge,
        blend_camera(a.body, b.body, t, *size),
    )


def _check_t(t: float) -> None:
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"blend time must lie in [0, 1], got {t}")


class Painter:
    """Draws a frame's own picture, or one between two frames, with one decoder.

    The last exact picture is kept: a frame written to the recording and then shown on
    screen (or the reverse) is rendered once. The faces of the last few frames are kept too:
    the lips' control vectors at frame a need the frame before it.
    """

    def __init__(self, decoder: FaceDecoder) -> None:
        self.decoder = decoder
        self.groups = decoder.wires.feature_groups()
        self.mouth = decoder.mouth.rig  # the decoder's own: the same rig, built once
        height, width = decoder.background.shape[:2]
        self.size = (width, height)
        self._last: tuple[FrameValues, np.ndarray] | None = None
        # seq -> (values, its face in model space once asked for) of the last frames seen.
        self._faces: dict[int, tuple[FrameValues, np.ndarray | None]] = {}

    def state(self, values: FrameValues) -> FaceState:
        pose, params, lips = self.decoder.parameters(values)
        decoder = self.decoder
        return FaceState(
            pose, params, lips, decoder.camera(values), decoder.edge(values), decoder.body(values)
        )

    def exact(self, values: FrameValues) -> np.ndarray:
        """(h, w, 3) uint8 BGR picture of one frame, as :meth:`FaceDecoder.reconstruct`."""
        if self._last is not None and self._last[0] is values:
            return self._last[1]
        self._keep(values, None)
        image = self.decoder.reconstruct(values)
        self._last = (values, image)
        return image

    def between(self, a: FrameValues, b: FrameValues, t: float) -> np.ndarray:
        """(h, w, 3) uint8 BGR picture a fraction ``t`` of the way from frame a to frame b."""
        if t == 0.0:
            return self.exact(a)
        if t == 1.0:
            return self.exact(b)
        state, model = self.face_between(a, b, t)
        return self.decoder.draw_vertices(
            state.pose.apply(model), state.camera, state.edge, state.body
        )

    def face_between(
        self, a: FrameValues, b: FrameValues, t: float
    ) -> tuple[FaceState, np.ndarray]:
        """What the picture a fraction ``t`` of the way from frame a to frame b shows, and
        its (n, 3) face in model space."""
        s = blend_state(self.state(a), self.state(b), t, self.groups, self.size)
        base = self.decoder.model(s.wires, s.lips)
        model = self.mouth.between(base, self.face(a), self.face(b), t, self._before(a, b))
        return s, model

    def face(self, values: FrameValues) -> np.ndarray:
        """(n, 3) frame ``values``' face in model space (kept for the next few frames)."""
        kept = self._faces.get(values.seq)
        if kept is not None and kept[0] is values and kept[1] is not None:
            return kept[1]
        _, params, lips = self.decoder.parameters(values)
        model = self.decoder.model(params, lips)
        self._keep(values, model)
        return model

    def _keep(self, values: FrameValues, model: np.ndarray | None) -> None:
        self._faces[values.seq] = (values, model)
        for seq in sorted(self._faces)[:-KEPT_FACES]:
            del self._faces[seq]

    def _before(self, a: FrameValues, b: FrameValues) -> np.ndarray | None:
        """The face one interval (b - a) before frame a, from the newest kept frame before
        it, or None if there is none near enough (a start, or after a gap)."""
        earlier = [seq for seq in self._faces if a.seq - KEPT_FACES <= seq < a.seq]
        if not earlier:
            return None
        seq = max(earlier)
        face_a, face_before = self.face(a), self.face(self._faces[seq][0])
        return face_a - (face_a - face_before) * ((b.seq - a.seq) / (a.seq - seq))
