"""Markers lifted to 3D and spread over the face: the sender's chain for a marked face.

Seed 002's chain (sections 2.2 and 3): 2D marker -> ray cast onto the posed mesh -> 3D
control point displacement -> GDE RBFs -> a displacement of every vertex. Here:

1. The head pose comes from the pose markers (``MarkerTracker`` fits it on their layout).
2. Each marker's ray (orthographic camera: along the view axis through its pixel) is cast
   onto the session mesh under this pose, as in the seed. (Casting onto the face as the
   last frame left it instead feeds each frame's depth into the next: on the bundled clip
   the depth drifted by 4-15 mm at the brows, chin and mouth corners, against 0.1-1 mm
   this way.) A ray that misses, or meets the face at a grazing angle or far from where the
   marker was (a silhouette), gives the point of the ray nearest the marker's last place
   (seed 002's "direct specification" for points off the mesh) at a lower confidence.
3. The displacement of each deform and mouth marker from its rest point (where the
   calibration frame put it on the mesh) is blended with its last one by confidence: a hidden
   marker holds, a doubtful one moves part way; in depth, the surface's confidence counts
   too (a grazing hit moves the depth less, a point off the mesh keeps its depth).
4. The rig's GDEs (one per deform/mouth marker, ``facewire.models.gde``) spread those displacements
   over the mesh. Overlapping elements (the two lids of an eye, chin and lower lip) would
   add up and miss their own markers, so the control displacements are solved for first,
   from the small matrix of each element's weight at every marker's vertex: the field then
   passes through every marker exactly.

:class:`MarkerFaceTracker` puts it behind the landmark tracker's interface for
``facewire.sender.encoder.FaceEncoder``: landmarks for the session's first frame (the mesh and
texture come from them), then a :class:`MarkerFit` per frame, whose dense displacement the
encoder fits wires to.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RBFInterpolator

from facewire.models.gde import GdeSet
from facewire.models.mesh import FaceMesh
from facewire.models.pose import Pose
from facewire.models.raycast import RayCaster, orthographic_rays
from facewire.models.rig import Rig, load_rig
from facewire.sender.landmarks import Landmarks, LandmarkTracker
from facewire.sender.markers import Markers, MarkerTracker

logger = logging.getLogger(__name__)

# Surface confidence: full when the hit faces the camera at least this much (cosine),
# falling to 0 at the silhouette.
FULL_FACING = 0.3
# A hit whose depth moved more than this (cm) plus MAX_SLOPE times its move across the
# image since the last frame, or that is more than MAX_JUMP_CM from the marker's last point,
# is on another part of the face: the point is taken off the mesh.
MIN_DEPTH_STEP_CM = 0.15
MAX_SLOPE = 3.0
MAX_JUMP_CM = 1.2
# Confidence from which a marker is followed all the way, and up to which not at all.
TRUST_FULL = 0.7
TRUST_NONE = 0.1
# Confidence factor of a point off the mesh (its x, y are measured, its depth is a guess).
OFF_MESH = 0.3


def trust(confidence: np.ndarray) -> np.ndarray:
    """How far a marker of this confidence moves from its last place to its measured one:
    all the way from ``TRUST_FULL``, not at all up to ``TRUST_NONE``. (Moving part way
    every frame is a lag: a blink is over in five frames.)"""
    return np.clip((confidence - TRUST_NONE) / (TRUST_FULL - TRUST_NONE), 0.0, 1.0)


@dataclass(frozen=True)
class MarkerFit:
    """A frame's face from its markers.

    pose : head pose (model -> image)
    displacement : (n, 3) cm, model space: every vertex's displacement from the session mesh
    markers : the 2D markers it came from
    points : (k, 3) cm, model space: each marker lifted onto the face
    marker_displacement : (k, 3) cm, from each marker's rest point, as used (blended)
    confidence : (k,) 0..1, the 2D confidence times how well the ray met the face
    on_mesh : (k,) bool, the ray met the face where expected
    """

    pose: Pose
    displacement: np.ndarray
    markers: Markers
    points: np.ndarray
    marker_displacement: np.ndarray
    confidence: np.ndarray
    on_mesh: np.ndarray


class MarkerLifter:
    """Lifts a frame's 2D markers onto the session's mesh and spreads them over it.

    mesh : the session mesh (model space, cm, canonical topology)
    rest : (k, 3) cm, where each of the rig's markers sits on ``mesh`` at rest
    rig : markers (names and roles, in ``rest``'s order) and GDEs
    """

    def __init__(self, mesh: FaceMesh, rest: np.ndarray, rig: Rig) -> None:
        self.mesh = mesh
        self.rest = np.asarray(rest, dtype=np.float64)
        if self.rest.shape != (len(rig.markers), 3):
            raise ValueError(f"expected ({len(rig.markers)}, 3) rest points, got {self.rest.shape}")
        self.caster = RayCaster(mesh.triangles, mesh.vertices)
        gdes = GdeSet.from_rig(mesh, rig)
        by_vertex = {g.control_vertex: i for i, g in enumerate(rig.gdes)}
        # The deform and mouth markers that drive an element, and which element each drives.
        self.driving = np.array(
            [i for i, m in enumerate(rig.markers) if m.role != "pose" and m.vertex in by_vertex],
            dtype=np.int64,
        )
        if not len(self.driving):
            raise ValueError("the rig has no GDE on any deform or mouth marker")
        elements = np.array([by_vertex[rig.markers[i].vertex] for i in self.driving])
        weights = gdes.matrix.toarray()[:, elements]  # (n, d): element j's weight at vertex v
        at_markers = weights[[rig.markers[i].vertex for i in self.driving]]  # (d, d)
        # field = weights @ controls with at_markers @ controls = marker displacements.
        self.spread = weights @ np.linalg.inv(at_markers)  # (n, d)
        logger.debug(
            "lifter: %d driving markers, interpolation condition %.2f",
            len(self.driving),
            np.linalg.cond(at_markers),
        )
        self.reset()

    def reset(self) -> None:
        """Back to the rest face."""
        self.field = np.zeros_like(self.mesh.vertices)
        self.marker_displacement = np.zeros_like(self.rest)

    def lift(self, markers: Markers) -> MarkerFit:
        """The face of one frame from its 2D markers (``MarkerTracker.track``)."""
        pose = markers.pose
        last = self.rest + self.marker_displacement
        origins, directions = orthographic_rays(pose, markers.xy)
        hits = self.caster.cast(origins, directions)
        # The point of each ray nearest the marker's last place: used off the mesh.
        along = np.einsum("ij,ij->i", last - origins, directions)
        nearest = origins + along[:, None] * directions
        # A hit whose depth jumped more than the surface's slope allows for the step across
        # the image is on another part of the face (the ray slid past a silhouette, or onto
        # a lip in front of the mouth's corner).
        moved = (np.where(hits.hit[:, None], hits.points, last) - last) @ pose.rotation.T
        across = np.linalg.norm(moved[:, :2], axis=1)
        on_mesh = (
            hits.hit
            & (np.abs(moved[:, 2]) <= MIN_DEPTH_STEP_CM + MAX_SLOPE * across)
            & (np.linalg.norm(moved, axis=1) <= MAX_JUMP_CM)
        )
        facing = np.nan_to_num(hits.facing, nan=0.0)
        surface = np.where(on_mesh, np.clip(facing / FULL_FACING, 0.0, 1.0), OFF_MESH)
        points = np.where(on_mesh[:, None], hits.points, nearest)
        confidence = markers.confidence * surface
        # A doubtful marker moves part of the way from where it was; a hidden one holds.
        # Across the image its 2D confidence decides; in depth, which only the surface
        # tells, that times the surface's (a point off the mesh keeps its last depth).
        step = (points - last) @ pose.rotation.T  # camera axes: x, y in the image, z depth
        step[:, :2] *= trust(markers.confidence)[:, None]
        step[:, 2] *= trust(confidence)
        shown = self.marker_displacement + step @ pose.rotation
        self.field = self.spread @ shown[self.driving]
        self.marker_displacement = shown
        return MarkerFit(
            pose=pose,
            displacement=self.field,
            markers=markers,
            points=points,
            marker_displacement=shown,
            confidence=confidence,
            on_mesh=on_mesh,
        )


def landmarks_on_markers(
    points: np.ndarray, xy: np.ndarray, seen: np.ndarray, vertices: np.ndarray
) -> np.ndarray:
    """(468, 3) landmarks moved in x, y so that each seen marker's vertex lies on its marker.

    The landmark model is a few pixels off; a sticker's centre is a fraction of a pixel
    off. The correction at the markers (``xy`` (k, 2) px of the markers on ``vertices``)
    is spread over the face by a thin-plate spline over the landmarks' own positions (with
    its affine part, so an overall shift or stretch moves every point). Depth is kept.
    """
    use = np.asarray(seen, dtype=bool)
    if use.sum() < 4:
        return np.array(points, dtype=np.float64)
    where = points[vertices[use]]
    # The spline's distances in the face's own frame: image x, y and depth alike (px).
    interp = RBFInterpolator(where, xy[use] - where[:, :2], kernel="thin_plate_spline")
    out = np.array(points, dtype=np.float64)
    out[:, :2] += interp(out)
    return out


class MarkerFaceTracker:
    """The sender's tracker for a face wearing the rig's markers.

    Before the session (``FaceEncoder.start``) :meth:`track` calibrates the markers on the
    frame and returns that frame's landmarks, from which the session mesh and texture are
    made; :meth:`begin` then takes the session mesh, and from there on :meth:`track` returns
    a :class:`MarkerFit` per frame (None when the markers are lost). :attr:`state` is the
    marker tracker's (``facewire.sender.markers.STATES``).
    """

    def __init__(
        self,
        rig: Rig | None = None,
        markers: MarkerTracker | None = None,
        landmarks: LandmarkTracker | None = None,
    ) -> None:
        self.rig = rig or load_rig()
        self.markers = markers or MarkerTracker(self.rig, landmarks)
        self.lifter: MarkerLifter | None = None
        #: The last frame's 2D markers (None when lost).
        self.last: Markers | None = None

    @property
    def state(self) -> str:
        return self.markers.state

    def track(
        self, frame_bgr: np.ndarray, timestamp_s: float | None = None
    ) -> Landmarks | MarkerFit | None:
        """Landmarks before :meth:`begin` (calibrating on this frame), a MarkerFit after."""
        if self.lifter is None:
            self.markers.reset()
            self.last = self.markers.track(frame_bgr)
            found = self.markers.last_landmarks
            if self.last is None or found is None:
                return None
            # The session mesh is made from these: put its marker vertices on the markers.
            points = landmarks_on_markers(
                found.points, self.last.xy, self.last.seen, self.markers.vertices
            )
            self.markers.recalibrate_layout(points)
            return Landmarks(points, found.presence)
        self.last = self.markers.track(frame_bgr)
        if self.last is None:
            return None
        return self.lifter.lift(self.last)

    def begin(self, mesh: FaceMesh) -> None:
        """The session's mesh (made from the landmarks :meth:`track` returned): markers are
        lifted onto it from the next frame on."""
        if not self.markers.calibrated:
            raise RuntimeError("the markers are not calibrated: track a frame first")
        self.lifter = MarkerLifter(mesh, self.markers.layout, self.rig)

    def end(self) -> None:
        """The session is over: the next frame calibrates again."""
        self.lifter = None
