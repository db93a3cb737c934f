"""Sender analysis: a video frame in, a compact parameter packet out.

Per frame: landmarks (markerless tracker) -> head pose (similarity fitted on the rig's pose
markers) -> landmarks brought back to model space -> wire parameters by the least-squares
extraction of seed 000 (pseudo-inverse computed once per session) -> coefficients of the rig's
wire basis -> channel values quantised with hysteresis -> key or delta frame packet
(protocol.channels), or no packet when nothing visible changed.

The session model (what the receiver loads once) is built from the first frame with a face:
the person's mesh (landmarks in model space), the texture unwrapped from that frame and the
frame itself as the background: the receiver carries the head's surroundings (and the face
under the rendered one) along with the face, so nothing needs filling in.
"""

from __future__ import annotations

import logging
import secrets
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.body import BODY, BODY_SIZE, body_step
from facewire.models.camera import (
    CAMERA,
    CAMERA_SIZE,
    camera_step,
    corners_from_homography,
    homography_from_corners,
)
from facewire.models.edge import EDGE, EDGE_SIZE, edge_step
from facewire.models.face_channels import (
    DEFAULT_ERROR_PX,
    HYSTERESIS,
    LIPS,
    POSE_ROTATION,
    POSE_SCALE,
    POSE_TRANSLATION,
    WIRE,
    WireBasis,
    channel_steps,
    load_wire_basis,
    pose_channels,
    pose_from_channels,
    rig_hash,
)
from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.mouth_opening import LIPS_SIZE, MouthOpening
from facewire.models.person import person_mask
from facewire.models.pose import Pose, estimate_pose
from facewire.models.rem import RemLayout
from facewire.models.rig import Rig, load_rig
from facewire.models.wires import WireDeformer
from facewire.protocol import mesh_code
from facewire.protocol.channels import ChannelEncoder, ChannelSpec
from facewire.protocol.constants import CALL, FACE, UINT32_MAX
from facewire.protocol.images import decode_image
from facewire.protocol.packets import DeltaFrame, KeyFrame, Refresh, RemPatch, Snapshot
from facewire.protocol.quant import dequantise, quantise
from facewire.sender.body_motion import BodyTracker
from facewire.sender.camera_motion import CameraTracker
from facewire.sender.capture import CapturedFrame
from facewire.sender.channel_filter import ChannelSmoother
from facewire.sender.edge import EdgeMeter
from facewire.sender.fit_residual import FitResidual
from facewire.sender.landmarks import Landmarks, LandmarkTracker, crop_from_points
from facewire.sender.lift import MarkerFaceTracker, MarkerFit
from facewire.sender.occlusion import FaceOcclusion
from facewire.sender.palms import HeldPalms, PalmDetector
from facewire.sender.rate_cap import BODY_KBPS, EDGE_KBPS, GEOMETRY_KBPS, RateCap
from facewire.sender.refresh import REFRESH_KBPS, RefreshMeter
from facewire.sender.rem import RemEncoder
from facewire.sender.scene_cut import (
    FACE_FOUND_FRAMES,
    FACE_LOST_S,
    NO_FACE_AFTER_S,
    BetterView,
    SceneCut,
    another_face,
    eye_openness,
    face_box,
)
from facewire.sender.synthesis import FaceSynthesis
from facewire.sender.texture import UvRasteriser

logger = logging.getLogger(__name__)

#: A keyframe every this many seconds (and whenever a receiver asks for one).
KEYFRAME_INTERVAL_S = 4.0
#: The face's budget is never finer than this share of a pixel of the landmark model's input
#: (a 192-px crop 1.5 times the face's height): finer steps code the tracker's noise, not the
#: face. It matters for large faces only (over about 90 px high at 0.25 px): the bundled
#: clip's 223-px face gets 0.61 px, with the same marker error and blinks against its ground
#: truth for 1.38 kbit/s instead of 1.77 (docs/what-we-tried.md, "A large face's error budget").
TRACKER_RESOLUTION_SHARE = 0.35
#: Texture side per pixel of the face's width in the snapshot frame (rounded up to a power of
#: two, within MIN/MAX_TEXTURE_SIZE). Two texels a pixel keep the round trip frame -> texture
#: -> frame sharp (carphone's face SSIM +0.004 over 1.25); below 1.25 the texture would hold
#: less than the camera saw. Between the two, the snapshot's byte budget decides.
TEXELS_PER_FACE_PIXEL = 2.0
LEAST_TEXELS_PER_FACE_PIXEL = 1.25
MIN_TEXTURE_SIZE, MAX_TEXTURE_SIZE = 64, 512
#: Bytes the snapshot's two images may take: a base plus so much per pixel of the frame
#: (with the 2.8 KB of vertices, 12 KB for a 176x144 call and 40 KB for 640x480).
IMAGE_BUDGET_BASE, IMAGE_BUDGET_PER_PIXEL = 6_380, 0.0993
#: WebP quality of the snapshot's texture and background (chosen by measurement, see
#: docs/what-we-tried.md, "The snapshot's images").
TEXTURE_QUALITY = 97
#: REM patches are cut at most this many texels per pixel of the face's width (a power of two
#: no larger than the texture): a sharper grid costs each patch bytes the camera never saw.
#: But on a grid of at least MIN_REM_PATCH_SIZE: a small face's eye is a few texels there,
#: and a patch that small is mostly header anyway (carphone's eye: 94 bytes at 64 texels,
#: 114 at 128, 2 dB better).
REM_TEXELS_PER_FACE_PIXEL = 1.25
MIN_REM_PATCH_SIZE = 128
BACKGROUND_QUALITY = 80


@dataclass(frozen=True)
class SessionModel:
    """What the receiver needs once: the person's mesh, texture and background.

    mesh : person-specific mesh, model space (cm), canonical topology and UVs
    texture : (T, T, 3) uint8 BGR, v = 0 at the top row (T from :func:`texture_size`)
    background : (h, w, 3) uint8 BGR, the snapshot frame itself
    """

    mesh: FaceMesh
    texture: np.ndarray
    background: np.ndarray


def _webp(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, quality])
    if not ok:
        raise RuntimeError("WebP encoding failed")
    return buf.tobytes()


def texture_size(face_width_px: float, texels_per_pixel: float = TEXELS_PER_FACE_PIXEL) -> int:
    """Side of the session's texture for a face this wide in the snapshot frame."""
    wanted = max(float(face_width_px) * texels_per_pixel, 1.0)
    side = 1 << int(np.ceil(np.log2(wanted)))
    return int(np.clip(side, MIN_TEXTURE_SIZE, MAX_TEXTURE_SIZE))


class FaceEncoder:
    """Turns frames into frame packets for one session.

    Call :meth:`start` with frames until it returns a Snapshot (the first frame with a face),
    then :meth:`encode` for every frame. A frame where tracking fails repeats the last
    parameters. ``error_px`` is the most one channel's quantisation may move a vertex, in
    pixels at the call's size, raised for a large face to what the landmark tracker resolves
    (:data:`TRACKER_RESOLUTION_SHARE`). With ``smoothing`` (the default) the channel values are
    filtered over time before quantisation (:mod:`facewire.sender.channel_filter`): the tracker's
    jitter is most of what would otherwise be sent. With ``synthesis`` (the default) the
    tracked landmarks are moved to where the face the receiver draws matches the frame before
    they are fitted (:mod:`facewire.sender.synthesis`). With ``edge`` (the default) each packet
    carries the corrections that put the face's edge and surroundings where the frame shows
    them (:mod:`facewire.sender.edge`); without, they stay zero. With ``body`` (the default)
    the person's body below the head is followed (:mod:`facewire.sender.body_motion`), and
    the receiver moves it so; without, it moves with the scene. With ``refresh`` (the default)
    what the receiver's picture misses for a while around the face (a hand, an object, the
    scene uncovered) is sent as it is (:mod:`facewire.sender.refresh`).
    """

    def __init__(
        self,
        width: int,
        height: int,
        fps: float,
        tracker: LandmarkTracker | MarkerFaceTracker | None = None,
        rig: Rig | None = None,
        session_id: int | None = None,
        error_px: float = DEFAULT_ERROR_PX,
        basis: WireBasis | None = None,
        smoothing: bool = True,
        rem: bool = True,
        geometry_kbps: float | None = GEOMETRY_KBPS,
        synthesis: bool = True,
        edge: bool = True,
        edge_kbps: float | None = EDGE_KBPS,
        scenes: bool = True,
        body: bool = True,
        body_kbps: float | None = BODY_KBPS,
        refresh: bool = True,
        refresh_kbps: float = REFRESH_KBPS,
    ) -> None:
        self.width, self.height, self.fps = width, height, fps
        self.tracker: LandmarkTracker | MarkerFaceTracker = tracker or LandmarkTracker()
        self.rig = rig or load_rig()
        self.basis = basis or load_wire_basis()
        self.canonical = load_canonical()
        # A new random id per session, so a restarted sender is told apart from the old one.
        self.session_id = secrets.randbelow(UINT32_MAX) + 1 if session_id is None else session_id
        self.error_px = error_px
        self.budget_px = error_px
        self._pose_vertices = np.array(
            sorted({m.vertex for m in self.rig.markers_with_role("pose")}), dtype=np.int64
        )
        self.session: SessionModel | None = None
        self.wires: WireDeformer | None = None
        self.mouth: MouthOpening | None = None
        self.rest_params = np.zeros(0)
        self.steps: dict[str, float] = {}
        self._projector = np.zeros((0, 0))
        self._channels: ChannelEncoder | None = None
        self._last_values: dict[str, np.ndarray] | None = None
        self.camera: CameraTracker | None = None
        self._camera_shift = np.zeros(CAMERA_SIZE)
        #: Follows the scene and the body beside the tracker (:meth:`analyse`).
        self._beside = ThreadPoolExecutor(max_workers=1, thread_name_prefix="facewire-motion")
        self.use_body = body
        #: The body's motion below the head (None: not followed, it moves with the scene).
        self.body: BodyTracker | None = None
        self._body_shift = np.zeros(BODY_SIZE)
        #: The body's own rate cap (None: its values change whenever they are measured).
        self.body_cap = None if body_kbps is None else RateCap(body_kbps, fps)
        #: Bytes of the frame packets that were the body's share.
        self.body_bytes = 0.0
        self.frames_untracked = 0
        self.values_clipped = 0
        self.smoothing = smoothing
        self._smoother: ChannelSmoother | None = None
        self._depth = 0.0
        #: The float channel values the last tracked frame was quantised from (after
        #: smoothing): what the receiver rebuilds, within the quantisation budget.
        self.intended: dict[str, np.ndarray] | None = None
        self.use_rem = rem
        #: Live patches of the eyes and the mouth's inside (None: not sent).
        self.rem: RemEncoder | None = None
        #: (n, 3) the face as the last :meth:`analyse` tracked it, image space (pixels).
        self.points: np.ndarray | None = None
        #: Per tracked frame, the wire fit's and the sent face's distance to the tracked face.
        self.residual = FitResidual()
        self._patches: list[RemPatch | Refresh] = []
        self.use_refresh, self.refresh_kbps = refresh, refresh_kbps
        #: What the receiver's picture misses, sent as it is (None: off).
        self.refresh: RefreshMeter | None = None
        #: Finds hands held up near the face for the refreshes (made at the first session).
        self._palms: PalmDetector | None = None
        self._refresh_again = False  # a receiver asked for a keyframe: send them again
        #: The frame packets' rate cap (None: every frame that changed sends).
        self.rate_cap = None if geometry_kbps is None else RateCap(geometry_kbps, fps)
        self.use_synthesis = synthesis
        #: The receiver's drawing of the face, to move the tracked landmarks by (None: off).
        self.synthesis: FaceSynthesis | None = None
        self.use_edge = edge
        #: The face's edge corrections' measure (None: off, they stay zero).
        self.edge: EdgeMeter | None = None
        #: The edge corrections' own rate cap (None: they change whenever they are measured).
        self.edge_cap = None if edge_kbps is None else RateCap(edge_kbps, fps)
        self._edge_smoother: ChannelSmoother | None = None
        #: Bytes of the frame packets that were the edge corrections' share.
        self.edge_bytes = 0.0
        #: Cuts to another scene, each starting a session (None: one session, whatever comes).
        self.scene_cut = SceneCut(fps) if scenes else None
        #: Sessions started for a new scene, and the session that began the call (0: none yet).
        self.scenes = 0
        self.call_id = 0
        self._face_box: tuple[float, float, float] | None = None
        #: Where the session's face was when a face jump began a new scene (None: none did).
        self._jumped_from: tuple[float, float, float] | None = None
        #: Whether the face is seen far better than the session's snapshot saw it (None:
        #: no scenes looked for), and whether that began the new scene looked for.
        self.better_view: BetterView | None = None
        self._better = False
        self._new_scene = False  # a cut or another face seen, and no session from it yet
        self._left: tuple[np.ndarray, np.ndarray] | None = None  # the scene before the cut
        self._cut_at = 0  # the frame of the last cut
        #: Whether the session's scene shows no face (:meth:`start_scene`): its face is kept
        #: outside the frame, and a face that comes begins a session of its own.
        self.faceless = False
        self._untracked_run = 0  # frames running without the session's face
        self._found_run = 0  # frames running with a face, in a session without one
        self._specs: list[ChannelSpec] = []

    def start(
        self,
        frame: CapturedFrame,
        seq: int | None = None,
        call: int | None = None,
        fit_now: bool = True,
    ) -> Snapshot | None:
        """Build the session model from ``frame``; None if it shows no face.

        ``seq`` is the first frame number the snapshot is valid for (default: this frame's);
        ``call``: the session that began the call this one goes on (a new scene's). Without
        ``fit_now`` the wire fit's pseudo-inverse, which the snapshot does not need, waits for
        :meth:`prepare_fit` (or the first frame).
        """
        found = self.tracker.track(frame.image)
        if not isinstance(found, Landmarks):  # a marker tracker gives landmarks here too
            return None
        if self.scene_cut is not None:
            self.scene_cut.begin(frame.image)
        points = found.points
        self._face_box = None  # the next frame's face is this one's: no jump to look for
        self._jumped_from = None
        pose = estimate_pose(
            self.canonical.vertices[self._pose_vertices], points[self._pose_vertices]
        )
        # Rounded as the snapshot carries them (protocol/mesh_code.py), so both ends deform
        # the same mesh.
        vertices = mesh_code.quantise(pose.inverse(points))
        mesh = self.canonical.with_vertices(vertices.astype(np.float64))
        background = frame.image.copy()
        background_webp = _webp(background, BACKGROUND_QUALITY)
        budget = IMAGE_BUDGET_BASE + IMAGE_BUDGET_PER_PIXEL * self.width * self.height
        side = texture_size(np.ptp(points[:, 0]))
        least = texture_size(np.ptp(points[:, 0]), LEAST_TEXELS_PER_FACE_PIXEL)
        while True:
            texture, _ = UvRasteriser(mesh.triangles, mesh.uvs, side).unwrap(frame.image, points)
            texture_webp = _webp(texture, TEXTURE_QUALITY)
            if side <= least or len(texture_webp) + len(background_webp) <= budget:
                break
            side //= 2
        if self.scene_cut is not None:
            share = self.canonical.facing_share(points)
            sharp = side / LEAST_TEXELS_PER_FACE_PIXEL if side < MAX_TEXTURE_SIZE else np.inf
            self.better_view = BetterView(
                share, face_box(points), self.fps, sharp, eye_openness(points)
            )
            self._better = False
        meta: dict[str, str | int | float] = {
            "tracker": "markers"
            if isinstance(self.tracker, MarkerFaceTracker)
            else "mediapipe-landmarks",
            "texture_size": side,
            mesh_code.VERTEX_STEP: mesh_code.STEP_CM,
        }
        if self.use_rem:
            face = np.ptp(points[:, 0])
            wanted = max(MIN_REM_PATCH_SIZE, texture_size(face, REM_TEXELS_PER_FACE_PIXEL))
            patch_side = min(side, wanted)
            layout = RemLayout(mesh.triangles, mesh.uvs, self.rig, side, patch_side)
            first = frame.index if seq is None else seq
            self.rem = RemEncoder(layout, texture, first, self.fps)
            # The mouth's inside gets its own rectangle of texture, as this frame shows it.
            self.rem.fill_atlas(texture, frame.image, points)
            texture_webp = _webp(texture, TEXTURE_QUALITY)
            meta["rem_patch_size"] = patch_side
        self._patches = []
        self.session = SessionModel(mesh, texture, background)
        shown_texture = decode_image(texture_webp, "snapshot texture")  # as the receiver does
        if self.use_synthesis and not isinstance(self.tracker, MarkerFaceTracker):
            self.synthesis = FaceSynthesis(mesh, shown_texture, float(np.ptp(points[:, 0])))
        if isinstance(self.tracker, MarkerFaceTracker):
            self.tracker.begin(mesh)  # markers are lifted onto this mesh from now on
        budget_px = max(
            self.error_px, TRACKER_RESOLUTION_SHARE * crop_from_points(points).pixel_size
        )
        self._face_model(mesh, pose, budget_px, fit_now)
        assert self.wires is not None
        self.faceless, self._untracked_run = False, 0
        people = person_mask(frame.image)
        outline = points[self.canonical.outline, :2]
        self.camera = CameraTracker(frame.image, outline, people)
        self._camera_shift = np.zeros(CAMERA_SIZE)
        self.body = BodyTracker(frame.image, outline, people) if self.use_body else None
        self._body_shift = np.zeros(BODY_SIZE)
        self._last_values = self._quantise(self.channel_values(pose, self.rest_params), None)
        self._last_values[EDGE] = np.zeros(EDGE_SIZE, np.int64)
        self.refresh = None
        if self.use_edge or self.use_refresh:
            # The receiver's surroundings, rebuilt from what it decodes.
            shown = decode_image(background_webp, "snapshot background")
            shown_people = person_mask(shown)
            at_snapshot = self.rebuilt_vertices(self._last_values)[self.canonical.outline]
        if self.use_edge:
            self.edge = EdgeMeter(shown, at_snapshot, shown_people, float(np.ptp(points[:, 0])))
            if self.smoothing:
                self._edge_smoother = ChannelSmoother({EDGE: self.steps[EDGE]})
        if self.use_refresh:
            if self._palms is None:
                self._palms = PalmDetector()
            self.refresh = RefreshMeter(
                shown, at_snapshot, shown_people, self.fps, self.refresh_kbps,
                self._occlusion(mesh, shown_texture), HeldPalms(self._palms),
            )  # fmt: skip
        self._smoother = ChannelSmoother(self.steps) if self.smoothing else None
        self.intended = None
        self._depth = float(self._last_values[POSE_TRANSLATION][2] * self.steps[POSE_TRANSLATION])
        logger.info(
            "session model from frame %d: face %.0f px wide, %d wire parameters in %d "
            "basis coefficients",
            frame.index,
            np.ptp(points[:, 0]),
            self.wires.n_params,
            self.basis.size,
        )
        return self._snapshot(
            frame.index if seq is None else seq, vertices, texture_webp, background_webp, meta,
            call,
        )  # fmt: skip

    def _snapshot(
        self,
        seq: int,
        vertices: np.ndarray,
        texture: bytes,
        background: bytes,
        meta: dict[str, str | int | float],
        call: int | None,
    ) -> Snapshot:
        """The Snapshot of the session just set up (its channels, and its values now as the
        reference), valid from frame ``seq``, with a fresh coder for its frames; ``call``:
        the session that began the call it goes on (``meta["call"]``), if any."""
        interval = max(1, round(KEYFRAME_INTERVAL_S * self.fps))
        self._channels = ChannelEncoder(
            self._specs, round(1e6 / self.fps), self.session_id, keyframe_interval=interval
        )
        assert self._last_values is not None
        return Snapshot(
            session_id=self.session_id,
            seq=seq,
            width=self.width,
            height=self.height,
            fps=self.fps,
            vertices=vertices,
            texture=texture,
            background=background,
            channels=[(s.name, s.size, s.step) for s in self._specs],
            rig_hash=rig_hash(),
            keyframe_interval=interval,
            reference=[tuple(int(v) for v in self._last_values[s.name]) for s in self._specs],
            meta=meta if call is None else {**meta, CALL: call},
        )

    def _face_model(self, mesh: FaceMesh, pose: Pose, budget_px: float, fit_now: bool) -> None:
        """Set up the wires, the lips and the channels (their steps) of a session's ``mesh``,
        seen at ``pose`` in its snapshot frame with an error budget of ``budget_px``."""
        self.wires = WireDeformer.from_rig(mesh.vertices, self.rig)
        if fit_now:
            self.wires.prepare_fit()
        self.mouth = MouthOpening(mesh, self.rig)
        self.rest_params = self.wires.rest_params()
        self._projector = self.basis.projector(self.wires.matrix)
        radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
        #: The error budget this session's steps were chosen for, px (see error_px).
        self.budget_px = budget_px
        self.steps = channel_steps(radius, pose.scale, budget_px)
        # The background may move twice the face's budget: at 0.5 px its estimate's noise
        # alone cost 0.3 kbit/s on a still studio camera (akiyo), at 1 px 0.15.
        self.steps[CAMERA] = camera_step(2 * budget_px)
        self.steps[EDGE] = edge_step(budget_px)
        self.steps[BODY] = body_step(budget_px)
        self._specs = [
            ChannelSpec(name, len(v), self.steps[name]) for name, v in pose_channels(pose).items()
        ] + [
            ChannelSpec(WIRE, self.basis.size, self.steps[WIRE]),
            ChannelSpec(LIPS, LIPS_SIZE, self.steps[LIPS]),
            ChannelSpec(CAMERA, CAMERA_SIZE, self.steps[CAMERA]),
            ChannelSpec(EDGE, EDGE_SIZE, self.steps[EDGE]),
            ChannelSpec(BODY, BODY_SIZE, self.steps[BODY]),
        ]

    def _occlusion(self, mesh: FaceMesh, texture: np.ndarray) -> FaceOcclusion | None:
        """What looks for a hand in front of the face (sender/occlusion.py) on ``texture``,
        the snapshot's as the receiver decoded it, leaving out the regions the REM patches
        show as they are; None without them."""
        if self.rem is None:
            return None
        left_out = np.zeros(texture.shape[:2], bool)
        for box in self.rem.layout.boxes.values():
            left_out[box.texture_slices] = True
        return FaceOcclusion(mesh.triangles, mesh.uvs, texture, left_out)

    def scene_changed(self, frame: CapturedFrame) -> bool:
        """Whether ``frame`` shows another scene than the session's (a cut, another face, or
        the face far better than its snapshot saw it: sender/scene_cut.py), and no session has
        been started from it yet. Look at every frame before encoding it; while True,
        :meth:`start_scene` starts one (the frame packets until then would draw the face over
        a scene it does not belong to).
        """
        if self.scene_cut is None or self.session is None:
            return False
        cut = self.scene_cut.changed(frame.image)
        if self._new_scene and self._left is not None and self.scene_cut.like(self._left):
            # No session came of it, and the scene left is back: the cut was a black frame,
            # a flash, a hand over the lens.
            self._new_scene, self._left = False, None
            return False
        if cut and not self._new_scene:
            self._left, self._cut_at = self.scene_cut.before, frame.index
        self._new_scene |= cut
        self._better &= not cut  # a cut's new face is looked for over the whole frame
        return self._new_scene

    def prepare_fit(self) -> None:
        """Compute the session's wire fit now (see :meth:`start`'s ``fit_now``)."""
        assert self.wires is not None, "start() first"
        self.wires.prepare_fit()

    def start_scene(self, frame: CapturedFrame, fit_now: bool = True) -> Snapshot | None:
        """The snapshot of a new session from ``frame``, which follows on this one (a new
        scene of the call). Where the frame shows no face: a session without one
        (:meth:`start_without_face`) once the new scene has shown none for NO_FACE_AFTER_S
        after its cut, or the face has been lost for FACE_LOST_S; before that None (the old
        session goes on, its receiver keeps the old picture; try again on a later frame).
        None too where, after a face jump and no cut, the old session's face is back where it
        was (the old session goes on, and no new scene is looked for). ``fit_now``: as
        :meth:`start`'s.
        """
        if isinstance(self.tracker, LandmarkTracker) and not self._better:
            # It would look where the old face was: look over the whole frame.
            self.tracker.reset()
        if self._left is None and self._jumped_from is not None and self._own_face_back(frame):
            return None
        old = self.session_id
        self.call_id = self.call_id or old
        self.session_id = secrets.randbelow(UINT32_MAX) + 1
        snapshot = self.start(frame, call=self.call_id, fit_now=fit_now)
        if snapshot is None:
            # Its frames are not sent meanwhile: with no cut (a far better view of the face,
            # which turned away; another face, gone), the old face is lost as surely as in
            # a frame not tracked. (Not counted, foreman's pan away after a better view sent
            # nothing for its last 4 s, and the receiver refused the Bye so far on.)
            self._untracked_run += 1
        if snapshot is None and self.scenes_without_face and self._no_face_for_long(frame):
            snapshot = self.start_without_face(frame, call=self.call_id)
        if snapshot is None:
            self.session_id = old
            if self.faceless and self._left is None:
                # The face seen in the scene without one is gone already (someone passing,
                # a face on a poster seen a moment): that session goes on, its frames sent.
                self._new_scene, self._found_run = False, 0
            return None
        self._new_scene, self._left = False, None
        self.scenes += 1
        logger.info("another scene at frame %d: session %d of call %d", frame.index,
                    self.session_id, self.call_id)  # fmt: skip
        return snapshot

    @property
    def scenes_without_face(self) -> bool:
        """Whether a scene with no face gets a session (with the landmark tracker: markers
        are looked for on a face)."""
        return isinstance(self.tracker, LandmarkTracker)

    def _no_face_for_long(self, frame: CapturedFrame) -> bool:
        """Whether a new scene that shows no face in ``frame`` gets a session without one: its
        cut was NO_FACE_AFTER_S ago, or no cut came and the face is lost (FACE_LOST_S)."""
        if self.faceless:
            return self._left is not None and frame.index - self._cut_at >= round(
                NO_FACE_AFTER_S * self.fps
            )  # one without a face cut to another
        if self._left is None:
            return self._untracked_run >= round(FACE_LOST_S * self.fps)
        return frame.index - self._cut_at >= round(NO_FACE_AFTER_S * self.fps)

    def start_without_face(
        self, frame: CapturedFrame, seq: int | None = None, call: int | None = None
    ) -> Snapshot:
        """A session of a scene that shows no face (docs/protocol.md 8.9): its snapshot frame
        is ``frame``, drawn alone, with the camera's motion and the refreshes over it; valid
        from frame ``seq`` (default: this frame's); ``call``: as :meth:`start`'s. Its face
        (the last session's, or the canonical one's when the call begins with no face) is
        kept outside the frame, so every receiver draws the scene alone whatever it knows
        of this, and its texture is empty. A face that comes begins a session of it
        (:meth:`analyse`). Only with the landmark tracker (markers are looked for on a face).
        """
        assert isinstance(self.tracker, LandmarkTracker), "a scene with no face needs landmarks"
        if self.session is None:  # the call begins with no face: the canonical one stands in
            mesh = self.canonical.with_vertices(
                mesh_code.quantise(self.canonical.vertices).astype(np.float64)
            )
            scale = self.width / 4 / float(np.ptp(mesh.vertices[:, 0]))  # any size will do
            pose = pose_from_channels(
                {POSE_ROTATION: np.zeros(3), POSE_SCALE: np.log([scale]),
                 POSE_TRANSLATION: np.zeros(3)}
            )  # fmt: skip
            self._face_model(mesh, pose, self.error_px, fit_now=False)
            self.session = SessionModel(mesh, np.zeros((0, 0, 3), np.uint8), frame.image)
            self._last_values = self._quantise(self.channel_values(pose, self.rest_params), None)
            self._last_values[EDGE] = np.zeros(EDGE_SIZE, np.int64)
        if self.scene_cut is not None:
            self.scene_cut.begin(frame.image)
        assert self._last_values is not None
        values = {name: np.zeros_like(v) for name, v in self._last_values.items()}
        for name in (POSE_ROTATION, POSE_SCALE, WIRE):
            values[name] = self._last_values[name].copy()
        # Its right edge a frame's width left of the frame: no part of it drawn, nor of what
        # is carried with it (the body below it, models/surround.py).
        right = float(self.rebuilt_vertices(values)[:, 0].max())
        values[POSE_TRANSLATION][0] -= int(
            np.ceil((right + self.width) / self.steps[POSE_TRANSLATION])
        )
        values[POSE_TRANSLATION][1] = round(self.height / 2 / self.steps[POSE_TRANSLATION])
        background = frame.image.copy()
        background_webp = _webp(background, BACKGROUND_QUALITY)
        self.faceless, self._found_run, self._untracked_run = True, 0, 0
        self.session = SessionModel(self.session.mesh, self.session.texture, background)
        self.rem = self.synthesis = self.edge = self.body = self.better_view = None
        self._edge_smoother = self._smoother = None
        self._face_box = self._jumped_from = None
        self._camera_shift, self._body_shift = np.zeros(CAMERA_SIZE), np.zeros(BODY_SIZE)
        self._patches = []
        self._last_values = values
        self.intended = None
        outline = self.rebuilt_vertices(values)[self.canonical.outline]
        self.camera = CameraTracker(frame.image, outline[:, :2], person_mask(frame.image))
        self.refresh = None
        if self.use_refresh:
            shown = decode_image(background_webp, "snapshot background")
            self.refresh = RefreshMeter(
                shown, outline, person_mask(shown), self.fps, self.refresh_kbps
            )
        logger.info("frame %d shows no face: a session of the scene alone", frame.index)
        meta: dict[str, str | int | float] = {mesh_code.VERTEX_STEP: mesh_code.STEP_CM, FACE: 0}
        return self._snapshot(
            frame.index if seq is None else seq, self.session.mesh.vertices, b"",
            background_webp, meta, call,
        )  # fmt: skip

    def _own_face_back(self, frame: CapturedFrame) -> bool:
        """Whether ``frame`` shows the session's own face where it was before a face jump
        began a new scene: the tracker had strayed to another face while it had lost this
        one (a mother bowing her head, her daughter's face found), and the session goes on.
        Started from there, the new session's texture was her hair, and the face she raised
        again was drawn from it."""
        assert self._jumped_from is not None
        found = self.tracker.track(frame.image)
        if found is None or another_face(self._jumped_from, face_box(found.points)):
            return False
        self._new_scene, self._jumped_from, self._face_box = False, None, face_box(found.points)
        logger.info("frame %d: the session's face is back, no new scene", frame.index)
        return True

    def analyse(self, image: np.ndarray) -> tuple[Pose, np.ndarray] | None:
        """Head pose and wire parameters of one frame, or None when no face is tracked (or
        the face tracked is another face: :meth:`start_scene` starts its session)."""
        assert self.session is not None and self.wires is not None, "start() first"
        if self._new_scene:
            return None  # not this session's scene
        # The scene's and the body's motion need no face: followed on another thread while
        # the tracker looks for it (OpenCV lets the GIL go), 2-3 ms of a 1280x720 frame.
        beside = None if self.camera is None else self._beside.submit(self._motion, image)
        if self.faceless:
            self._look_for_face(image)
            assert beside is not None and self.camera is not None
            homography = self.camera.settle(image.shape, None, beside.result()[0])
            self._camera_shift = corners_from_homography(homography, self.width, self.height)
            return None
        face = self._face(image)
        followed, body = (None, None) if beside is None else beside.result()
        if face is None:
            return None
        pose, params, points = face
        self.points = points
        if self.camera is not None:
            outline = points[self.canonical.outline, :2]
            homography = self.camera.settle(image.shape, outline, followed)
            self._camera_shift = corners_from_homography(homography, self.width, self.height)
            if body is not None:
                # Sent relative to the scene's motion: a person sitting still sends nothing.
                own = np.linalg.solve(homography, body)
                self._body_shift = corners_from_homography(own, self.width, self.height)
        return pose, params

    def _look_for_face(self, image: np.ndarray) -> None:
        """In a session without a face: a face tracked FACE_FOUND_FRAMES running is a new
        scene, begun with the next frame (:meth:`start_scene`)."""
        found = self.tracker.track(image)
        self._found_run = self._found_run + 1 if isinstance(found, Landmarks) else 0
        if self._found_run >= FACE_FOUND_FRAMES:
            self._new_scene, self._left = True, None
            logger.info("a face in the scene without one: a session of it")

    def _motion(
        self, image: np.ndarray
    ) -> tuple[tuple[np.ndarray, np.ndarray] | None, np.ndarray | None]:
        """The background's corners followed into ``image`` (CameraTracker.follow) and the
        body's motion (BodyTracker.update, None without a body followed)."""
        assert self.camera is not None
        return self.camera.follow(image), None if self.body is None else self.body.update(image)

    def _face(self, image: np.ndarray) -> tuple[Pose, np.ndarray, np.ndarray] | None:
        """(pose, wire parameters, (n, 3) points in image space) of the face tracked in
        ``image``, or None (no face, or another face: a new scene)."""
        assert self.session is not None and self.wires is not None
        found = self.tracker.track(image)
        if found is None:
            return None
        box = face_box(found.points)
        before, self._face_box = self._face_box, box
        if self.scene_cut is not None and before is not None and another_face(before, box):
            self._new_scene, self._jumped_from = True, before
            return None
        base = self.session.mesh.vertices
        eyes = None  # the lids' opening, as the tracker saw it (markers have no lids)
        if isinstance(found, MarkerFit):
            # Markers: pose and a dense displacement, lifted and spread by the tracker.
            pose = found.pose
            params = self.wires.fit_displacement(found.displacement)
            points = pose.apply(base + found.displacement)
        else:
            points, eyes = found.points, eye_openness(found.points)
            if self.synthesis is not None:
                points = self.synthesis.refine(image, points)
            pose = estimate_pose(base[self._pose_vertices], points[self._pose_vertices])
            params = self.wires.fit(pose.inverse(points))
        if self.better_view is not None and self.better_view.seen(
            self.canonical.facing_share(points), face_box(points), eyes
        ):
            # This frame is drawn as it is; the next one begins a session of this face.
            self._new_scene = self._better = True
            logger.info("the face is seen far better than in its snapshot: a new one")
        return pose, params, points

    def projected(self, params: np.ndarray) -> np.ndarray:
        """(K,) wire basis coefficients (cm) closest to wire parameters ``params``."""
        return np.asarray(self._projector @ (params - self.rest_params))

    def channel_values(
        self, pose: Pose, params: np.ndarray, points: np.ndarray | None = None
    ) -> dict[str, np.ndarray]:
        """Float channel values of a pose and wire parameters (before quantisation), with the
        camera's and the body's motion measured by the last :meth:`analyse`, the inner lips' opening
        that the wires leave on ``points`` (n, 3), the tracked face in image space (none
        without them)."""
        assert self.wires is not None and self.mouth is not None, "start() first"
        values = pose_channels(pose)
        values[WIRE] = self.projected(params)
        values[LIPS] = np.zeros(LIPS_SIZE)
        if points is not None:
            deformed = self.wires.deform(self.rest_params + self.basis.params(values[WIRE]))
            values[LIPS] = self.mouth.values(pose.inverse(points), deformed)
        values[CAMERA] = self._camera_shift
        values[BODY] = self._body_shift
        return values

    @property
    def coded_bits(self) -> dict[str, float]:
        """Bits coded in frame bodies so far, by channel (see ChannelEncoder.coded_bits)."""
        return {} if self._channels is None else dict(self._channels.coded_bits)

    def request_keyframe(self) -> None:
        """The next packet is a keyframe (a receiver asked for one), with every REM patch
        sent so far and every refresh shown again."""
        if self._channels is not None:
            self._channels.request_keyframe()
        if self.rem is not None:
            self.rem.request_refresh()
        self._refresh_again = True

    def take_patches(self) -> list[RemPatch | Refresh]:
        """The REM patches and refreshes of the last encoded frame (publish them before its
        frame packet)."""
        patches, self._patches = self._patches, []
        return patches

    def rebuilt(self, values: dict[str, np.ndarray]) -> tuple[Pose, np.ndarray]:
        """The head pose and the (n, 3) deformed face in model space (cm) that the receiver
        rebuilds from quantised channel ``values``."""
        assert self.wires is not None and self.mouth is not None, "start() first"
        floats = {name: dequantise(v, self.steps[name]) for name, v in values.items()}
        params = self.rest_params + self.basis.params(floats[WIRE])
        opening = self.mouth.displacement(floats[LIPS])
        return pose_from_channels(floats), self.wires.deform(params) + opening

    def rebuilt_vertices(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """(n, 3) the face as the receiver rebuilds quantised channel ``values``, image
        space (pixels)."""
        pose, model = self.rebuilt(values)
        return pose.apply(model)

    @property
    def values(self) -> dict[str, np.ndarray] | None:
        """The quantised channel values of the last frame encoded (None before start)."""
        return self._last_values

    def encode(self, frame: CapturedFrame) -> KeyFrame | DeltaFrame | None:
        """The packet for ``frame`` (``seq`` = frame index), or None when nothing changed."""
        return self.encode_analysed(frame, self.analyse(frame.image))

    def encode_analysed(
        self, frame: CapturedFrame, result: tuple[Pose, np.ndarray] | None
    ) -> KeyFrame | DeltaFrame | None:
        """:meth:`encode` for a frame already analysed (``result`` of :meth:`analyse`)."""
        assert self._channels is not None and self._last_values is not None, "start() first"
        sent = self._last_values
        vertices = None
        if result is None and self.faceless:
            # The scene alone: its camera's motion, and the refreshes over it.
            values = dict(sent)
            values[CAMERA] = self._quantise_own(CAMERA, self._camera_shift, sent[CAMERA], None)
            vertices = self.rebuilt_vertices(values)
            motion = self._homographies(values)
            self._last_values = values
        elif result is None:
            self.frames_untracked += 1  # repeat the last values
            self._untracked_run += 1
            lost = self._untracked_run >= round(FACE_LOST_S * self.fps)
            if self.scene_cut is not None and self.scenes_without_face and lost:
                self._new_scene = True  # the face has gone: the scene alone from now on
        else:
            self._untracked_run = 0
            floats = self.channel_values(*result, self.points)
            if self._smoother is not None:
                # Frame numbers, not capture times, time the filter: a file read faster than
                # real time is filtered as it would be in a call.
                floats = self._smoother(floats, frame.index / self.fps)
            # The head's depth (translation z) moves nothing on screen: the receiver's camera
            # is orthographic and placed from the vertices' own depth range. Sending its
            # jitter would cost bits for nothing, so it keeps the snapshot frame's level.
            floats[POSE_TRANSLATION] = floats[POSE_TRANSLATION].copy()
            floats[POSE_TRANSLATION][2] = self._depth
            values = self._quantise(floats, self._last_values)
            values[BODY] = self._quantise_own(BODY, floats[BODY], sent[BODY], self.body_cap)
            vertices = self.rebuilt_vertices(values)
            # The surroundings the receiver warps: the camera's and the person's motion.
            motion = self._homographies(values)
            floats[EDGE] = self._edge(frame, vertices, motion)
            values[EDGE] = self._quantise_own(EDGE, floats[EDGE], sent[EDGE], self.edge_cap)
            self.intended = floats
            self._last_values = values
        patches: list[RemPatch] = []
        if vertices is not None and self.rem is not None:
            assert self.points is not None
            patches = self.rem.changed(frame.index, frame.image, vertices, self.points)
        # A refresh gets a frame packet to be drawn with while the geometry's cap allows, and
        # no more (it would take the geometry past its cap): held, it shows with the next.
        refreshes: list[Refresh] = []
        if self.refresh is not None:
            if self._refresh_again:
                refreshes += self.refresh.again(frame.index)
                self._refresh_again = False
            if vertices is not None:
                camera, body = motion
                outline = vertices[self.canonical.outline]
                refreshes += self.refresh.measure(
                    frame.index, frame.image, outline, camera, body, vertices
                )
        may_send = self.rate_cap is None or self.rate_cap.next_frame()
        if not (may_send or patches or self._channels.keyframe_due(frame.index)):
            # Over the rate cap: the receiver keeps what it has (sender/rate_cap.py).
            assert self.rate_cap is not None
            moved = any(not np.array_equal(v, sent[n]) for n, v in self._last_values.items())
            self.rate_cap.held += int(moved)
            self._last_values = sent
            if vertices is not None:
                vertices = self.rebuilt_vertices(sent)
            packet = None
        else:
            # A patch (or a refresh) is drawn with its frame: that frame needs a packet even if
            # nothing moved.
            coded = dict(self._channels.coded_bits)
            packet, _ = self._channels.encode(
                frame.index, frame.capture_us, self._last_values, force=bool(patches or refreshes)
            )
            if packet is not None:
                self._spend(len(bytes(packet)), coded)
        if result is not None and vertices is not None:
            assert self.points is not None and self.wires is not None  # as vertices were made
            pose, params = result
            self.residual.add(
                frame.index, self.points, pose.apply(self.wires.deform(params)), vertices
            )
        if self.rem is not None and isinstance(packet, KeyFrame):
            patches = self.rem.keyframe(frame.index, patches) + patches
        self._patches = [*patches, *refreshes]
        return packet

    def _edge(
        self,
        frame: CapturedFrame,
        vertices: np.ndarray,
        motion: tuple[np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """(EDGE_SIZE,) the face's edge corrections for ``frame`` (smoothed over time), where
        the receiver draws the face at ``vertices`` (n, 3) and warps the surroundings with
        ``motion``, the camera's and the person's homographies (:meth:`_homographies`); zeros
        when they are off."""
        if self.edge is None:
            return np.zeros(EDGE_SIZE)
        camera, body = motion
        outline = vertices[self.canonical.outline]
        edge = self.edge.measure(frame.image, outline, camera, body).ravel()
        if self._edge_smoother is None:
            return edge
        return self._edge_smoother({EDGE: edge}, frame.index / self.fps)[EDGE]

    def _homographies(self, values: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The camera's and the person's (3, 3) homographies the receiver makes of quantised
        channel ``values`` (models/camera.py, models/body.py)."""
        shift = dequantise(values[CAMERA], self.steps[CAMERA])
        camera = homography_from_corners(shift, self.width, self.height)
        body = dequantise(values[BODY], self.steps[BODY])
        return camera, camera @ homography_from_corners(body, self.width, self.height)

    def _quantise_own(
        self, name: str, floats: np.ndarray, sent: np.ndarray, cap: RateCap | None
    ) -> np.ndarray:
        """The values of a channel with a bucket of its own (the edge's corrections, the
        body's motion): ``sent`` kept while it is empty, and a wider hysteresis as it runs
        low (as the face's under the geometry's cap)."""
        if cap is None:
            return quantise(floats, self.steps[name], sent, HYSTERESIS)[0]
        if not cap.next_frame():
            return sent
        return quantise(floats, self.steps[name], sent, HYSTERESIS + cap.slack())[0]

    def _spend(self, nbytes: int, coded_before: dict[str, float]) -> None:
        """Take a sent frame packet's ``nbytes`` from the rate caps: the edge corrections'
        and the body's shares of the bits coded in it (``coded_before``: the channel coder's
        counts before it) from their buckets, the rest from the geometry's."""
        assert self._channels is not None  # a packet was coded
        added = {k: v - coded_before.get(k, 0.0) for k, v in self._channels.coded_bits.items()}
        total = sum(added.values())
        edge = nbytes * added.get(EDGE, 0.0) / total if total > 0 else 0.0
        body = nbytes * added.get(BODY, 0.0) / total if total > 0 else 0.0
        self.edge_bytes += edge
        self.body_bytes += body
        if self.edge_cap is not None:
            self.edge_cap.spend(edge)
        if self.body_cap is not None:
            self.body_cap.spend(body)
        if self.rate_cap is not None:
            self.rate_cap.spend(nbytes - edge - body)

    def _quantise(
        self, floats: dict[str, np.ndarray], previous: dict[str, np.ndarray] | None
    ) -> dict[str, np.ndarray]:
        values = {}
        # Under the rate cap the bucket's level widens the hysteresis (sender/rate_cap.py).
        slack = 0.0 if self.rate_cap is None or previous is None else self.rate_cap.slack()
        for name, x in floats.items():
            prev = None if previous is None else previous[name]
            values[name], clipped = quantise(x, self.steps[name], prev, HYSTERESIS + slack)
            self.values_clipped += clipped
        return values
