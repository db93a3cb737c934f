"""The face's edge corrections: measured by the sender, drawn by the receiver."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facewire.models.edge import (
    EDGE_POINTS,
    FADE_REACH,
    INNER_REACH,
    OUTER_REACH,
    correct,
    edge_field,
    edge_points,
    move,
    outline_ring,
)
from facewire.models.surround import SurroundWarp

H, W = 240, 320
FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def ellipse(centre=(160.0, 120.0), radius=(40.0, 52.0), k=36) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    return np.c_[centre[0] + radius[0] * np.cos(t), centre[1] + radius[1] * np.sin(t)]


def texture(seed: int = 3) -> np.ndarray:
    """A smooth random picture: optical flow finds its way on it, as on hair and skin."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (H // 6, W // 6, 3), dtype=np.uint8)
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)


def shifted(image: np.ndarray, d: tuple[float, float]) -> np.ndarray:
    """``image`` whose pixel x shows what ``image`` has at x + d."""
    m = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
    return cv2.warpAffine(
        image,
        m,
        (image.shape[1], image.shape[0]),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )


def test_the_points_are_spaced_evenly_along_the_outline() -> None:
    square = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]])
    points = outline_ring(square, 16)
    assert np.allclose(points[:5], [[0, 0], [10, 0], [20, 0], [30, 0], [40, 0]])
    assert np.allclose(points[8], [40, 40]) and np.allclose(points[12], [0, 40])
    # Scaled about the vertices' mean.
    assert np.allclose(outline_ring(square, 16, 0.5)[0], [10.0, 10.0])
    assert edge_points(ellipse()).shape == (EDGE_POINTS, 2)


def test_the_field_passes_through_the_corrections_and_is_nothing_inside_and_far_out() -> None:
    o = ellipse()
    rng = np.random.default_rng(0)
    vectors = rng.uniform(-2.0, 2.0, (EDGE_POINTS, 2))
    field = edge_field(o, vectors, (0, 0, W, H))
    assert field.shape == (H, W, 2)

    def at(p: np.ndarray) -> np.ndarray:
        x, y = np.round(p).astype(int).T
        return field[y, x]

    # Within the spline's smoothing (1 px^2) and the grid's interpolation.
    assert np.abs(at(edge_points(o)) - vectors).max() < 0.35
    assert np.abs(at(outline_ring(o, EDGE_POINTS, INNER_REACH))).max() < 0.35
    assert np.abs(at(outline_ring(o, EDGE_POINTS, OUTER_REACH))).max() < 0.35
    # Beyond the fade nothing moves at all: no seam where the field ends.
    far = outline_ring(o, EDGE_POINTS, FADE_REACH + 0.15)
    far = far[(far[:, 0] >= 0) & (far[:, 0] < W) & (far[:, 1] >= 0) & (far[:, 1] < H)]
    assert len(far) > 4 and np.abs(at(far)).max() == 0.0
    assert not edge_field(o, np.zeros((EDGE_POINTS, 2)), (0, 0, W, H)).any()


def test_the_receiver_moves_the_edge_and_keeps_the_face_inside() -> None:
    o = ellipse()
    truth = texture()
    drawn = shifted(truth, (-2.0, 1.0))  # the receiver's picture: truth's x shows at x + (2, -1)
    face = np.zeros((H, W), np.uint8)
    cv2.fillPoly(face, [np.round(o).astype(np.int32)], 1)
    band = 4.0
    vectors = np.tile([2.0, -1.0], (EDGE_POINTS, 1))
    out = correct(drawn.copy(), face.astype(bool), o, vectors, band)  # moved in place
    inside = cv2.distanceTransform(face, cv2.DIST_L2, 3) > band
    assert np.array_equal(out[inside], drawn[inside])
    # Just outside the outline the picture is back where the camera saw it.
    ring = cv2.dilate(face, np.ones((9, 9), np.uint8)).astype(bool) & ~face.astype(bool)

    def error(image: np.ndarray) -> float:
        return float(np.abs(image.astype(int) - truth.astype(int))[ring].mean())

    assert error(out) < 0.35 * error(drawn)
    # No corrections: the very same picture.
    assert correct(drawn, face.astype(bool), o, np.zeros((EDGE_POINTS, 2)), band) is drawn


def test_a_colour_region_moves_as_each_of_its_channels_alone() -> None:
    # The colour picture goes through a fourth channel (OpenCV's fast remap): the same values
    # as each channel moved on its own, in the same order, from a region of a larger picture.
    rng = np.random.default_rng(5)
    picture = rng.integers(0, 256, (300, 260, 3), dtype=np.uint8)
    region = picture[20:260, 10:250]
    coarse = rng.uniform(-6, 6, (16, 16, 2)).astype(np.float32)
    field = cv2.resize(coarse, (240, 240), interpolation=cv2.INTER_LINEAR)
    moved = move(region, field)
    assert moved.shape == region.shape and moved.dtype == np.uint8
    alone = np.dstack([move(np.ascontiguousarray(region[:, :, c]), field) for c in range(3)])
    assert np.array_equal(moved, alone)
    assert not np.array_equal(moved, region)


def test_the_edge_moves_all_round_the_face_its_top_and_bottom_too() -> None:
    # The face's inside is measured from its edge, not from its box's sides: measured on the
    # face's box cut out, the forehead's and the chin's edge, which touch the box, counted as
    # deep inside and stayed where the geometry put them.
    o = ellipse()
    drawn = texture()
    face = np.zeros((H, W), np.uint8)
    cv2.fillPoly(face, [np.round(o).astype(np.int32)], 1)
    band = 6.0
    vectors = np.tile([2.0, -1.0], (EDGE_POINTS, 1))
    out = correct(drawn.copy(), face.astype(bool), o, vectors, band)
    depth = cv2.distanceTransform(np.pad(face, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
    moved = (out != drawn).any(axis=2)
    top, bottom = int(o[:, 1].min()), int(o[:, 1].max())
    for rows in (np.s_[top : top + 4], np.s_[bottom - 3 : bottom + 1]):
        edge = (depth[rows] > 0) & (depth[rows] < band)
        assert edge.sum() > 20 and moved[rows][edge].mean() > 0.9
    # The renderer's own distances (a box of them, at its corner) keep the same inside.
    x0, y0, x1, y1 = 100, 50, 230, 200
    given = correct(
        drawn.copy(), face.astype(bool), o, vectors, band, (x0, y0, depth[y0:y1, x0:x1])
    )
    assert np.array_equal(given, out)


def test_a_hostile_correction_moves_the_picture_no_further_than_the_limit() -> None:
    """The limit is docs/protocol.md's (6.2, `edge`): a tenth of the outline's width, written
    here, not read from the code (a limit four times larger passed that way)."""
    o = ellipse()
    face = np.zeros((H, W), np.uint8)
    cv2.fillPoly(face, [np.round(o).astype(np.int32)], 1)
    picture = texture()
    huge = np.tile([2.0**24, -(2.0**24)], (EDGE_POINTS, 1))  # the channel's largest values
    out = correct(picture.copy(), face.astype(bool), o, huge, 3.0)
    limit = 0.1 * np.ptp(o[:, 0])
    at_limit = np.tile([limit, -limit] / np.hypot(1.0, 1.0), (EDGE_POINTS, 1))
    assert np.array_equal(out, correct(picture.copy(), face.astype(bool), o, at_limit, 3.0))


# --- the sender's measure ---------------------------------------------------------------------


def meter(face_px: float = 80.0) -> tuple[SurroundWarp, object]:
    """The receiver's surroundings of a snapshot, and the sender's meter of the same."""
    from facewire.sender.edge import EdgeMeter

    return SurroundWarp(texture(), ellipse()), EdgeMeter(texture(), ellipse(), None, face_px)


def test_the_sender_measures_how_far_off_the_receivers_edge_is() -> None:
    surround, edge = meter()
    now = ellipse(centre=(166.0, 117.0))  # the face moved; the spline carries the hair along
    shown = surround.warp(now)
    frame = shifted(shown, (1.5, -1.0))  # but the camera sees it 1.5 px left and 1 px down
    vectors = edge.measure(frame, now, None)  # type: ignore[attr-defined]
    assert vectors.shape == (EDGE_POINTS, 2)
    assert np.abs(vectors - [1.5, -1.0]).max() < 0.3, vectors
    # A frame that shows what the receiver shows: nothing to correct.
    assert np.abs(edge.measure(shown, now, None)).max() < 0.1  # type: ignore[attr-defined]


def test_a_large_face_is_measured_on_the_frame_scaled_down() -> None:
    surround, edge = meter(face_px=240.0)
    assert edge.reduce == 3  # type: ignore[attr-defined]
    now = ellipse(centre=(166.0, 117.0))
    frame = shifted(surround.warp(now), (2.0, 1.0))
    vectors = edge.measure(frame, now, None)  # type: ignore[attr-defined]
    assert np.abs(vectors - [2.0, 1.0]).max() < 0.5, vectors


def test_a_large_face_is_measured_with_the_camera_moved_as_the_receiver_moves_it() -> None:
    """The camera's homography is in the frame's pixels; the reduced frame's rebuild must
    move the scene by the same amount on screen."""
    surround, edge = meter(face_px=240.0)
    now = ellipse(centre=(166.0, 117.0))
    camera = np.array([[1.0, 0.0, 9.0], [0.0, 1.0, -6.0], [0.0, 0.0, 1.0]])  # a pan
    frame = shifted(surround.warp(now, camera), (2.0, 1.0))
    vectors = edge.measure(frame, now, camera)  # type: ignore[attr-defined]
    assert np.abs(vectors - [2.0, 1.0]).max() < 0.5, vectors


def test_a_correction_that_would_not_bring_the_picture_closer_is_not_sent() -> None:
    surround, edge = meter()
    now = ellipse()
    shown = surround.warp(now)
    # Around the left of the face the camera sees a plain wall the snapshot never had: the
    # flow carries the right side's motion into it, and moving the picture there does not
    # make it a wall.
    frame = shifted(shown, (2.0, 0.0))
    frame[:, :150] = 128
    vectors = edge.measure(frame, now, None)  # type: ignore[attr-defined]
    points = edge_points(now)
    right = points[:, 0] > 175
    assert np.abs(vectors[right] - [2.0, 0.0]).max() < 0.4
    # Against a plain wall a moved texture may still come a little closer by chance: most of
    # the wall's points send nothing (with the check taken out, all five do).
    wall = points[:, 0] < 135
    assert wall.sum() == 5
    assert (vectors[wall] == 0).all(axis=1).sum() >= 4, vectors[wall]


def test_a_face_out_of_the_frame_gets_no_corrections() -> None:
    surround, edge = meter()
    gone = ellipse(centre=(-200.0, 120.0))
    assert not edge.measure(texture(), gone, None).any()  # type: ignore[attr-defined]


# --- in the call, on a real photographed face -------------------------------------------------


def _hair_moved(face: np.ndarray, d: tuple[float, float]) -> np.ndarray:
    """The photo with what lies around the face (hair, ears, collar) moved by ``d`` px and
    the face itself where it was: the head's surroundings moving on their own."""
    from facewire.models.mesh import load_canonical
    from facewire.sender.landmarks import LandmarkTracker
    from facewire.sender.texture import face_hull_mask

    points = LandmarkTracker().track(face).points  # type: ignore[union-attr]
    hull = face_hull_mask(face.shape[:2], points, load_canonical().triangles).astype(np.uint8)
    near = cv2.dilate(hull, np.ones((61, 61), np.uint8)).astype(np.float32)
    weight = cv2.GaussianBlur(near - hull, (0, 0), 4.0)[..., None]
    moved = shifted(face, (-d[0], -d[1]))
    return np.round(weight * moved + (1.0 - weight) * face).astype(np.uint8)


def _call(first: np.ndarray, moved: np.ndarray, edge: bool) -> tuple[np.ndarray, np.ndarray]:
    """What the receiver shows after 20 frames of ``moved``, and the corrections it drew."""
    from facewire.loopback import Loopback
    from facewire.sender.capture import CapturedFrame
    from facewire.sender.encoder import FaceEncoder

    h, w = first.shape[:2]
    with Loopback(FaceEncoder(w, h, 30.0, edge=edge), CapturedFrame(0, first, 0)) as both:
        for i in range(1, 21):
            both.step(CapturedFrame(i, moved, i * 33_333))
        return both.picture(), both.decoder.edge(both.shown)


def test_in_the_call_the_hair_around_the_face_goes_where_the_camera_saw_it(
    tmp_path: Path,
) -> None:
    from facewire.models.mesh import load_canonical
    from facewire.sender.landmarks import LandmarkTracker
    from facewire.sender.texture import face_hull_mask

    face = cv2.imread(str(FIXTURE))
    moved = _hair_moved(face, (2.5, -2.0))
    rebuilt, sent = _call(face, moved, edge=True)
    without, unsent = _call(face, moved, edge=False)
    cv2.imwrite(str(tmp_path / "edge.png"), np.hstack([moved, rebuilt, without]))
    assert not unsent.any()
    # The hair moved (2.5, -2) px: the receiver's picture shows it back from where the camera
    # sees it, and the corrections point there (less far: at the outline the test's move
    # fades into the still face). Below the cheeks the neck is too plain to measure.
    moving = sent[np.abs(sent).sum(1) > 0]
    assert len(moving) >= 6
    direction = moving.mean(0)
    assert direction @ [-2.5, 2.0] / (np.linalg.norm(direction) * np.hypot(2.5, 2.0)) > 0.8
    assert np.linalg.norm(direction) > 0.8
    # The band around the outline that a viewer sees as the face's edge.
    h, w = face.shape[:2]
    points = LandmarkTracker().track(moved).points  # type: ignore[union-attr]
    hull = face_hull_mask((h, w), points, load_canonical().triangles).astype(np.uint8)
    band = cv2.dilate(hull, np.ones((13, 13), np.uint8)) - cv2.erode(hull, np.ones((5, 5)))

    def error(image: np.ndarray) -> float:
        return float(np.abs(image.astype(int) - moved.astype(int))[band.astype(bool)].mean())

    assert error(rebuilt) < 0.75 * error(without), (error(rebuilt), error(without))
