"""Receiver reconstruction: a parameter packet in, a rendered frame out.

The snapshot gives the person's mesh, texture, background and channel table; the wire
deformer is built once from that mesh and the bundled rig. Per frame: decode the channels
(protocol.channels) -> dequantise -> wire basis coefficients to wire parameters -> wire
deformation (seed 000, Eq. 1-3, a sparse matrix-vector product) -> the inner lip contour
(seed 003's mouth rig, models/mouth_opening.py) -> head pose -> offscreen render over the
background.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from facewire.models.body import BODY, BODY_SIZE
from facewire.models.camera import CAMERA, CAMERA_SIZE, homography_from_corners
from facewire.models.edge import EDGE, EDGE_POINTS, EDGE_SIZE, correct
from facewire.models.face_channels import (
    LIPS,
    POSE_ROTATION,
    POSE_SCALE,
    POSE_TRANSLATION,
    WIRE,
    WireBasis,
    load_wire_basis,
    pose_from_channels,
    rig_hash,
)
from facewire.models.mesh import load_canonical
from facewire.models.mouth_opening import LIPS_SIZE, MouthOpening
from facewire.models.person import person_mask
from facewire.models.pose import Pose
from facewire.models.refresh import RefreshLayer
from facewire.models.rem import RemLayout
from facewire.models.rig import Rig, load_rig
from facewire.models.surround import SurroundWarp
from facewire.models.wires import WireDeformer
from facewire.protocol.channels import ChannelDecoder, ChannelSpec, FrameValues
from facewire.protocol.constants import FACE, MAX_IMAGE_SIDE
from facewire.protocol.images import ImageError, decode_image
from facewire.protocol.packets import (
    DeltaFrame,
    KeyFrame,
    PacketError,
    Refresh,
    RemPatch,
    Snapshot,
)
from facewire.protocol.quant import dequantise
from facewire.receiver.rem import RemMerger

logger = logging.getLogger(__name__)


class SnapshotError(ValueError):
    """A snapshot this receiver cannot use (other rig, undecodable images, bad sizes)."""


#: Shown where a snapshot carries no texture or background (the format allows empty images).
MISSING_IMAGE_GREY = 128
MISSING_TEXTURE_SIZE = 64
#: Width of the band inside the face outline where the rendered face fades into the
#: background, as a fraction of the face's width.
FEATHER = 0.06
#: Farthest a rebuilt vertex may be from the image origin, in pixels. Frames are at most 4096
#: px wide: a face beyond this is no picture, only a hostile or broken value (a pose scale of
#: e^700 px/cm overflows the renderer; one of e^710, or 0, is no pose at all).
MAX_VERTEX_PX = 2.0**20


def _image(
    data: bytes, what: str, fallback_size: tuple[int, int], wanted: bool = True
) -> np.ndarray:
    """Decode a snapshot image after checking its header (size limits before any pixel is
    decoded); an empty image becomes flat grey of ``fallback_size`` (height, width), said
    where the image is ``wanted``."""
    if not data:
        if wanted:
            logger.warning("snapshot has no %s: showing grey", what)
        return np.full((*fallback_size, 3), MISSING_IMAGE_GREY, np.uint8)
    try:
        return decode_image(data, f"snapshot {what}")
    except ImageError as exc:
        raise SnapshotError(str(exc)) from None


def _images(snapshot: Snapshot) -> tuple[np.ndarray, np.ndarray]:
    """The snapshot's texture and background, at the sizes the session draws them: a draft's
    smaller images are scaled up (docs/protocol.md 8.7)."""
    texture = _image(
        snapshot.texture,
        "texture",
        (MISSING_TEXTURE_SIZE, MISSING_TEXTURE_SIZE),
        wanted=shows_face(snapshot),  # a scene with no face has none
    )
    side = snapshot.meta.get("texture_size")
    if isinstance(side, int) and 0 < side <= MAX_IMAGE_SIDE and texture.shape[:2] != (side, side):
        texture = cv2.resize(texture, (side, side), interpolation=cv2.INTER_LINEAR)
    background = _image(snapshot.background, "background", (snapshot.height, snapshot.width))
    if background.shape[:2] != (snapshot.height, snapshot.width):
        background = cv2.resize(background, (snapshot.width, snapshot.height))
    return texture, background


def shows_face(snapshot: Snapshot) -> bool:
    """Whether ``snapshot``'s scene shows a face (docs/protocol.md 8.9: one that shows none
    puts its face outside the frame, and has no texture)."""
    return snapshot.meta.get(FACE) != 0


def new_scene_news(snapshot: Snapshot) -> str:
    """What a receiver says when it draws a new scene of its call from ``snapshot``."""
    alone = "" if shows_face(snapshot) else " (no face in it)"
    return f"a new scene from frame {snapshot.seq}{alone}"


class FaceDecoder:
    """Rebuilds frames of one session from its snapshot."""

    def __init__(
        self, snapshot: Snapshot, rig: Rig | None = None, basis: WireBasis | None = None
    ) -> None:
        if snapshot.rig_hash != rig_hash():
            raise SnapshotError(
                f"the sender's rig ({snapshot.rig_hash[:12]}...) differs from this receiver's "
                f"({rig_hash()[:12]}...): both ends need the same facewire rig data"
            )
        self.rig = rig or load_rig()
        self.basis = basis or load_wire_basis()
        expected = {
            POSE_ROTATION: 3,
            POSE_SCALE: 1,
            POSE_TRANSLATION: 3,
            WIRE: self.basis.size,
            LIPS: LIPS_SIZE,
            CAMERA: CAMERA_SIZE,
            EDGE: EDGE_SIZE,
            BODY: BODY_SIZE,
        }
        got = {name: size for name, size, _ in snapshot.channels}
        if got != expected:
            raise SnapshotError(f"snapshot channels {got} do not match this receiver's {expected}")
        self.specs = [ChannelSpec(*c) for c in snapshot.channels]
        self.channels = ChannelDecoder(self.specs, round(1e6 / snapshot.fps))
        canonical = load_canonical()
        vertices = np.asarray(snapshot.vertices, dtype=np.float64)
        if vertices.shape != canonical.vertices.shape:
            raise SnapshotError(
                f"snapshot mesh has shape {vertices.shape}, expected {canonical.vertices.shape}"
            )
        self.mesh = canonical.with_vertices(vertices)
        self.wires = WireDeformer.from_rig(vertices, self.rig)
        self.mouth = MouthOpening(self.mesh, self.rig)
        self._rest = self.wires.rest_params()
        self._snapshot = snapshot
        self.texture, self.background = _images(snapshot)
        reference = FrameValues(
            snapshot.seq,
            0,
            {
                s.name: np.asarray(v, np.int64)
                for s, v in zip(self.specs, snapshot.reference, strict=True)
            },
        )
        try:
            at_snapshot = self._drawable(reference)
        except PacketError as exc:
            raise SnapshotError(f"snapshot reference: {exc}") from None
        #: The snapshot frame's own values: drawn, they give the snapshot frame back.
        self.reference = reference
        #: Live patches of the eyes and the mouth's inside (None: the sender sends none).
        self.rem = self._rem(snapshot)
        #: REM patches that came without a session able to take them.
        self.rem_dropped = 0
        #: What the model does not show, as the camera saw it (models/refresh.py).
        self.refresh = RefreshLayer(snapshot.width, snapshot.height)
        #: Refreshes that could not be shown (an area outside the frame, an undecodable image).
        self.refresh_dropped = 0
        layout = self.rem.layout if self.rem is not None else None
        from facewire.receiver.render import FaceRenderer  # OpenGL only where it is needed

        self.renderer = FaceRenderer(
            snapshot.width,
            snapshot.height,
            self.mesh.triangles if layout is None else layout.triangles,
            self.mesh.uvs if layout is None else layout.uvs,
            self.texture,
            self.background,
            multisample=False,  # the face is feathered (draw_vertices): no edge to smooth
        )
        # Where the snapshot frame showed the face outline: the surroundings of the head are
        # carried from there to wherever the face is drawn.
        self._outline = self.mesh.outline
        self._outline_at_snapshot = at_snapshot[self._outline]
        self.surround = SurroundWarp(
            self.background, self._outline_at_snapshot, person_mask(self.background)
        )
        # The first draw compiles shaders and uploads the texture: do it before frames arrive.
        self.renderer.render(self._drawn(at_snapshot))

    def refine(self, snapshot: Snapshot) -> bool:
        """Take the sharper images of the full snapshot that follows a draft (the sender's
        first, small version of it on a thin link); False, and nothing changed, when
        ``snapshot`` is not this session's snapshot with other images."""
        mine = self._snapshot
        if (
            snapshot.session_id != mine.session_id
            or snapshot.seq != mine.seq
            or (snapshot.width, snapshot.height) != (mine.width, mine.height)
            or not np.array_equal(snapshot.vertices, mine.vertices)
            or list(snapshot.channels) != list(mine.channels)
            or [list(r) for r in snapshot.reference] != [list(r) for r in mine.reference]
            or snapshot.meta.get("texture_size") != mine.meta.get("texture_size")
        ):
            return False
        try:
            texture, background = _images(snapshot)
        except SnapshotError as exc:
            logger.info("refinement of the snapshot not taken: %s", exc)
            return False
        if texture.shape != self.texture.shape:
            return False
        self._snapshot, self.texture, self.background = snapshot, texture, background
        if self.rem is not None:
            self.rem.rebase(texture)
        self.renderer.set_texture(self.texture if self.rem is None else self.rem.texture)
        self.surround = SurroundWarp(background, self._outline_at_snapshot, person_mask(background))
        return True

    def _rem(self, snapshot: Snapshot) -> RemMerger | None:
        """The REM merger of a snapshot whose meta names a patch grid ("rem_patch_size"),
        or None (no REM: the sender sends no patches, or its grid does not fit the texture)."""
        patch_size = snapshot.meta.get("rem_patch_size")
        if patch_size is None:
            return None
        side = self.texture.shape[0]
        try:
            if not isinstance(patch_size, int) or self.texture.shape[1] != side:
                raise ValueError(f"patch grid {patch_size!r} for a {self.texture.shape} texture")
            layout = RemLayout(self.mesh.triangles, self.mesh.uvs, self.rig, side, patch_size)
        except ValueError as exc:
            logger.warning("no REM patches in this session: %s", exc)
            return None
        return RemMerger(layout, self.texture, snapshot.seq)

    def add_patch(self, packet: RemPatch) -> bool:
        """Keep a REM patch for the frame it belongs to (drawn by :meth:`reconstruct`);
        False, and counted, when it cannot be used (see
        :class:`facewire.receiver.rem.RemMerger`)."""
        if self.rem is None:
            self.rem_dropped += 1
            return False
        return self.rem.add(packet)

    def add_refresh(self, packet: Refresh) -> bool:
        """Keep a refresh for the frame it belongs to (shown by :meth:`reconstruct` from
        then on); False, and counted, when its area is not in the frame or its image does
        not decode."""
        image = None
        try:
            if not self.refresh.fits(packet.x, packet.y, packet.width, packet.height):
                raise ImageError(f"area {packet.width}x{packet.height} at ({packet.x}, "
                                 f"{packet.y}) outside the frame")  # fmt: skip
            if not packet.clears:
                image = decode_image(packet.data, "refresh")
        except ImageError as exc:
            logger.debug("refresh dropped: %s", exc)
            self.refresh_dropped += 1
            return False
        self.refresh.add(
            packet.seq, packet.x, packet.y, packet.width, packet.height, image, bool(packet.over)
        )
        return True

    def offer(self, packet: object) -> bool:
        """True when ``packet`` is a REM patch or a refresh, now kept (or counted and
        dropped): the receive loop hands every update here first."""
        if isinstance(packet, Refresh):
            self.add_refresh(packet)
            return True
        if not isinstance(packet, RemPatch):
            return False
        self.add_patch(packet)
        return True

    def rem_counts(self) -> dict[str, object]:
        """REM patches received, applied by region, waiting and dropped by reason."""
        if self.rem is None:
            return {
                "received": self.rem_dropped,
                "applied": {},
                "replaced": 0,
                "waiting": 0,
                "dropped": {"no REM": self.rem_dropped},
            }
        return self.rem.counts()

    def _drawn(self, vertices: np.ndarray) -> np.ndarray:
        """The renderer's vertices from the face's (the mouth's inside has its own)."""
        return vertices if self.rem is None else self.rem.layout.vertices(vertices)

    def decode(self, packet: KeyFrame | DeltaFrame) -> FrameValues:
        """Channel values of a frame packet that gives a face to draw.

        Raises ChainBroken after a gap, and PacketError for a body that does not decode or
        whose values draw no face (see :meth:`_drawable`); either way the chain waits for
        the next keyframe.
        """
        values = self.channels.decode(packet)
        try:
            self._drawable(values)
        except PacketError:
            self.channels = ChannelDecoder(self.specs, self.channels.frame_us)  # chain broken
            raise
        return values

    def _drawable(self, values: FrameValues) -> np.ndarray:
        """:meth:`image_vertices`, or PacketError when there is no face to draw: a pose
        scale of 0 or infinity, or vertices beyond MAX_VERTEX_PX (or not finite)."""
        with np.errstate(over="ignore", invalid="ignore"):
            try:
                vertices = self.image_vertices(values)
            except ValueError as exc:  # Pose refuses the scale
                raise PacketError(f"frame {values.seq}: no pose ({exc})") from None
        if not np.all(np.abs(vertices) <= MAX_VERTEX_PX):  # NaN fails too
            raise PacketError(f"frame {values.seq}: vertices beyond {MAX_VERTEX_PX:.0f} px")
        return vertices

    def parameters(self, values: FrameValues) -> tuple[Pose, np.ndarray, np.ndarray]:
        """Dequantised head pose, wire parameters and inner lips' opening (``lips``) of one
        frame's values."""
        floats = {s.name: dequantise(values.values[s.name], s.step) for s in self.specs}
        pose = pose_from_channels(floats)
        return pose, self._rest + self.basis.params(floats[WIRE]), floats[LIPS]

    def model(self, params: np.ndarray, lips: np.ndarray) -> np.ndarray:
        """(n, 3) the face in model space, cm: the wires' deformation of ``params`` with the
        inner lips' opening ``lips`` on top (models/mouth_opening.py)."""
        return self.wires.deform(params) + self.mouth.displacement(lips)

    def camera(self, values: FrameValues) -> np.ndarray:
        """(3, 3) homography of the camera's motion since the snapshot frame."""
        spec = next(s for s in self.specs if s.name == CAMERA)
        shift = dequantise(values.values[CAMERA], spec.step)
        return homography_from_corners(shift, self.background.shape[1], self.background.shape[0])

    def body(self, values: FrameValues) -> np.ndarray:
        """(3, 3) similarity of the body's own motion since the snapshot frame, before the
        camera's (models/body.py)."""
        spec = next(s for s in self.specs if s.name == BODY)
        shift = dequantise(values.values[BODY], spec.step)
        return homography_from_corners(shift, self.background.shape[1], self.background.shape[0])

    def image_vertices(self, values: FrameValues) -> np.ndarray:
        """(n, 3) deformed, posed vertices in the sender's image space (pixels)."""
        pose, params, lips = self.parameters(values)
        return pose.apply(self.model(params, lips))

    def edge(self, values: FrameValues) -> np.ndarray:
        """(EDGE_POINTS, 2) the face's edge corrections, pixels (models/edge.py)."""
        spec = next(s for s in self.specs if s.name == EDGE)
        return dequantise(values.values[EDGE], spec.step).reshape(EDGE_POINTS, 2)

    def reconstruct(self, values: FrameValues) -> np.ndarray:
        """(h, w, 3) uint8 BGR rendering of one frame's values: the face over the snapshot
        frame, whose surroundings of the head are moved along with the face, with the REM
        patches of frames up to this one in its texture."""
        if self.rem is not None and self.rem.due(values.seq):
            self.renderer.set_texture(self.rem.texture)
        self.refresh.due(values.seq)
        return self.draw_vertices(
            self.image_vertices(values), self.camera(values), self.edge(values), self.body(values)
        )

    def draw_vertices(
        self,
        vertices: np.ndarray,
        camera: np.ndarray,
        edge: np.ndarray | None = None,
        body: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`reconstruct` from the face's (n, 3) vertices in image space (pixels), the
        camera's homography of :meth:`camera`, the edge's corrections of :meth:`edge` and
        the body's motion of :meth:`body` (the playout draws pictures between two frames
        this way)."""
        outline = vertices[self._outline, :2]
        # The face first: llvmpipe rasterises it on its own threads while the surroundings
        # are warped here (FaceRenderer.draw).
        self.renderer.draw(self._drawn(vertices))
        person = None if body is None else camera @ body
        background = self.surround.warp(vertices[self._outline], camera, body=person)
        # What the model misses, as the camera saw it: over the surroundings, under the face.
        self.refresh.over(background, outline)
        # The face's edge fades into the background (the snapshot frame, carried along), which
        # shows the real face edge there: no seam at the outline.
        feather = FEATHER * float(np.ptp(outline[:, 0]))
        image, face = self.renderer.finish(background, feather)
        if edge is not None:
            # The feathered edge and the surroundings go where the sender saw them.
            image = correct(image, face, outline, edge, feather, self.renderer.depth)
        # What the camera saw in front of the face (a hand), over it.
        return self.refresh.on_top(image)

    def close(self) -> None:
        self.renderer.close()
