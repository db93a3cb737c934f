"""Receiver reconstruction: a parameter packet in, a rendered frame out.

The snapshot gives the person's mesh, texture and background; the wire deformer is built
once from that mesh and the bundled rig. Per frame: dequantise -> wire deformation (seed 000,
Eq. 1-3, a sparse matrix-vector product) -> head pose -> offscreen render over the background.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from models.mesh import load_canonical
from models.pose import Pose
from models.rig import RIG_VERSION, Rig, load_rig
from models.wires import WireDeformer
from protocol.constants import QUANT_POSE_SCALE, QUANT_POSE_TRANSLATION, QUANT_WIRE_Q, QUANT_WIRE_S
from protocol.packets import Frame, Snapshot
from protocol.quant import decode_pose, dequantise, wire_steps

logger = logging.getLogger(__name__)


class SnapshotError(ValueError):
    """A snapshot this receiver cannot use (other rig, undecodable images, bad sizes)."""


def _image(data: bytes, what: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise SnapshotError(f"snapshot {what} is not a decodable image")
    return image


class FaceDecoder:
    """Rebuilds frames of one session from its snapshot."""

    def __init__(self, snapshot: Snapshot, rig: Rig | None = None) -> None:
        if snapshot.rig_version != RIG_VERSION:
            raise SnapshotError(
                f"snapshot uses rig version {snapshot.rig_version}, this receiver has {RIG_VERSION}"
            )
        self.rig = rig or load_rig()
        layout = self.rig.wire_layout()
        if [tuple(x) for x in snapshot.wire_layout] != layout:
            raise SnapshotError("snapshot wire layout does not match this receiver's rig")
        canonical = load_canonical()
        vertices = np.asarray(snapshot.vertices, dtype=np.float64)
        if vertices.shape != canonical.vertices.shape:
            raise SnapshotError(
                f"snapshot mesh has shape {vertices.shape}, expected {canonical.vertices.shape}"
            )
        try:
            q = snapshot.quant
            self._pose_steps = (q[QUANT_POSE_SCALE], q[QUANT_POSE_TRANSLATION])
            self._steps = wire_steps(q[QUANT_WIRE_S], q[QUANT_WIRE_Q], layout)
        except KeyError as exc:
            raise SnapshotError(f"snapshot quantisation table lacks {exc}") from None
        self.mesh = canonical.with_vertices(vertices)
        self.wires = WireDeformer.from_rig(vertices, self.rig)
        self._rest = self.wires.rest_params()
        self.texture = _image(snapshot.texture, "texture")
        self.background = _image(snapshot.background, "background")
        if self.background.shape[:2] != (snapshot.height, snapshot.width):
            self.background = cv2.resize(self.background, (snapshot.width, snapshot.height))
        from receiver.render import FaceRenderer  # OpenGL only where it is needed

        self.renderer = FaceRenderer(
            snapshot.width,
            snapshot.height,
            self.mesh.triangles,
            self.mesh.uvs,
            self.texture,
            self.background,
        )
        # The first draw compiles shaders and uploads the texture: do it before frames arrive.
        self.renderer.render(self.mesh.vertices * [1.0, -1.0, -1.0])

    def parameters(self, frame: Frame) -> tuple[Pose, np.ndarray]:
        """Dequantised head pose and wire parameters of ``frame``."""
        if frame.params.shape != self._steps.shape:
            raise ValueError(
                f"frame {frame.seq} carries {frame.params.size} parameters, "
                f"expected {self._steps.size}"
            )
        wp = decode_pose(frame.pose, *self._pose_steps)
        pose = Pose.from_quaternion(wp.quaternion, wp.scale, wp.translation)
        return pose, self._rest + dequantise(frame.params, self._steps)

    def image_vertices(self, frame: Frame) -> np.ndarray:
        """(n, 3) deformed, posed vertices in the sender's image space (pixels)."""
        pose, params = self.parameters(frame)
        return pose.apply(self.wires.deform(params))

    def reconstruct(self, frame: Frame) -> np.ndarray:
        """(h, w, 3) uint8 BGR rendering of ``frame``."""
        image, _ = self.renderer.render(self.image_vertices(frame))
        return image

    def close(self) -> None:
        self.renderer.close()
