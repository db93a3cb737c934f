"""Sender analysis: a video frame in, a compact parameter packet out.

Per frame: landmarks (markerless tracker) -> head pose (similarity fitted on the rig's pose
markers) -> landmarks brought back to model space -> wire parameters by the least-squares
extraction of seed 000 (pseudo-inverse computed once per session) -> quantised Frame packet.

The session model (what the receiver loads once) is built from the first frame with a face:
the person's mesh (landmarks in model space), the texture unwrapped from that frame and the
background with the face removed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from models.mesh import FaceMesh, load_canonical
from models.pose import Pose, estimate_pose
from models.rig import RIG_VERSION, Rig, load_rig
from models.wires import WireDeformer
from protocol.constants import (
    QUANT_POSE_SCALE,
    QUANT_POSE_TRANSLATION,
    QUANT_WIRE_Q,
    QUANT_WIRE_S,
)
from protocol.packets import Frame, Snapshot
from protocol.quant import Pose as WirePose
from protocol.quant import encode_pose, quantise, wire_steps
from sender.capture import CapturedFrame
from sender.landmarks import LandmarkTracker
from sender.texture import UvRasteriser, make_background

logger = logging.getLogger(__name__)

#: Quantisation steps sent in the snapshot (receiver reads them from there).
QUANT_STEPS = {
    QUANT_POSE_SCALE: 1e-4,  # ln units: 0.01 % of scale
    QUANT_POSE_TRANSLATION: 0.05,  # image pixels
    QUANT_WIRE_S: 1e-3,
    QUANT_WIRE_Q: 0.005,  # cm: 0.05 mm
}
TEXTURE_SIZE = 512
JPEG_QUALITY = 90


@dataclass(frozen=True)
class SessionModel:
    """What the receiver needs once: the person's mesh, texture and background.

    mesh : person-specific mesh, model space (cm), canonical topology and UVs
    texture : (TEXTURE_SIZE, TEXTURE_SIZE, 3) uint8 BGR, v = 0 at the top row
    background : (h, w, 3) uint8 BGR, the first frame with the face filled in
    """

    mesh: FaceMesh
    texture: np.ndarray
    background: np.ndarray


def _jpeg(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


class FaceEncoder:
    """Turns frames into Frame packets for one session.

    Call :meth:`start` with frames until it returns a Snapshot (the first frame with a face),
    then :meth:`encode` for every frame. A frame where tracking fails repeats the last
    parameters, so the receiver still shows frame i for input frame i.
    """

    def __init__(
        self,
        width: int,
        height: int,
        fps: float,
        tracker: LandmarkTracker | None = None,
        rig: Rig | None = None,
        session_id: int = 1,
    ) -> None:
        self.width, self.height, self.fps = width, height, fps
        self.tracker = tracker or LandmarkTracker()
        self.rig = rig or load_rig()
        self.canonical = load_canonical()
        self.session_id = session_id
        self._pose_vertices = np.array(
            sorted({m.vertex for m in self.rig.markers_with_role("pose")}), dtype=np.int64
        )
        self.session: SessionModel | None = None
        self.wires: WireDeformer | None = None
        self._steps: np.ndarray | None = None
        self._rest: np.ndarray | None = None
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self.frames_untracked = 0
        self.values_clipped = 0

    def start(self, frame: CapturedFrame, seq: int | None = None) -> Snapshot | None:
        """Build the session model from ``frame``; None if it shows no face.

        ``seq`` is the first frame number the snapshot is valid for (default: this frame's);
        frames between it and this one are sent at this frame's pose with rest parameters.
        """
        found = self.tracker.track(frame.image)
        if found is None:
            return None
        points = found.points
        pose = estimate_pose(
            self.canonical.vertices[self._pose_vertices], points[self._pose_vertices]
        )
        mesh = self.canonical.with_vertices(pose.inverse(points))
        texture, _ = UvRasteriser(mesh.triangles, mesh.uvs, TEXTURE_SIZE).unwrap(
            frame.image, points
        )
        # Fill only the face itself: a wider fill shows as a blurred ring around the head.
        background = make_background(frame.image, points, mesh.triangles, dilate_fraction=0.02)
        self.session = SessionModel(mesh, texture, background)
        self.wires = WireDeformer.from_rig(mesh.vertices, self.rig)
        self.wires.prepare_fit()
        self._rest = self.wires.rest_params()
        layout = self.rig.wire_layout()
        self._steps = wire_steps(QUANT_STEPS[QUANT_WIRE_S], QUANT_STEPS[QUANT_WIRE_Q], layout)
        self._last = (self._quantise_pose(pose), np.zeros(self.wires.n_params, np.int16))
        logger.info(
            "session model from frame %d: face %.0f px wide, %d wire parameters",
            frame.index,
            np.ptp(points[:, 0]),
            self.wires.n_params,
        )
        return Snapshot(
            session_id=self.session_id,
            seq=frame.index if seq is None else seq,
            width=self.width,
            height=self.height,
            fps=self.fps,
            vertices=mesh.vertices.astype(np.float32),
            texture=_jpeg(texture),
            background=_jpeg(background),
            quant=dict(QUANT_STEPS),
            wire_layout=layout,
            rig_version=RIG_VERSION,
            meta={"tracker": "mediapipe-landmarks", "texture_size": TEXTURE_SIZE},
        )

    def analyse(self, image: np.ndarray) -> tuple[Pose, np.ndarray] | None:
        """Head pose and wire parameters of one frame, or None when no face is tracked."""
        assert self.session is not None and self.wires is not None, "start() first"
        found = self.tracker.track(image)
        if found is None:
            return None
        points = found.points
        base = self.session.mesh.vertices
        pose = estimate_pose(base[self._pose_vertices], points[self._pose_vertices])
        params = self.wires.fit(pose.inverse(points))
        return pose, params

    def _quantise_pose(self, pose: Pose) -> np.ndarray:
        wire_pose = WirePose(pose.as_quaternion(), pose.scale, pose.translation)
        pose_q, clipped = encode_pose(
            wire_pose, QUANT_STEPS[QUANT_POSE_SCALE], QUANT_STEPS[QUANT_POSE_TRANSLATION]
        )
        self.values_clipped += clipped
        return pose_q

    def encode(self, frame: CapturedFrame) -> Frame:
        """The Frame packet for ``frame`` (``seq`` = frame index)."""
        assert self._steps is not None and self._rest is not None, "start() first"
        result = self.analyse(frame.image)
        assert self._last is not None
        if result is None:
            self.frames_untracked += 1
            pose_q, params_q = self._last
        else:
            pose, params = result
            pose_q = self._quantise_pose(pose)
            params_q, clipped = quantise(params - self._rest, self._steps)
            self.values_clipped += clipped
            self._last = (pose_q, params_q)
        return Frame(
            seq=frame.index,
            capture_us=frame.capture_us,
            key=True,
            pose=pose_q,
            params=params_q,
        )
