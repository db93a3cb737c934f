"""Face detector and landmark tracker on a real face (the astronaut photo, public domain)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.sender.detector import Detection, FaceDetector, largest_first, ssd_anchors, tile_grid
from facewire.sender.landmarks import (
    ACQUIRED,
    BLANK,
    LOST,
    NO_FACE,
    TRACKED,
    Crop,
    LandmarkTracker,
    crop_from_points,
)

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


class CountingDetector(FaceDetector):
    """The real detector, counting how often the tracker falls back to it."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def detect(self, frame_bgr):  # type: ignore[no-untyped-def]
        self.calls += 1
        return super().detect(frame_bgr)


@pytest.fixture(scope="module")
def face() -> np.ndarray:
    img = cv2.imread(str(FIXTURE))
    assert img is not None, FIXTURE
    return img


@pytest.fixture(scope="module")
def detector() -> CountingDetector:
    return CountingDetector()


@pytest.fixture()
def tracker(detector: CountingDetector) -> LandmarkTracker:
    detector.calls = 0
    return LandmarkTracker(detector=detector)


@pytest.fixture(scope="module")
def upright(face: np.ndarray) -> np.ndarray:
    """Steady-state (second frame) landmarks of the upright fixture, (468, 3)."""
    t = LandmarkTracker()
    assert t.track(face) is not None
    lm = t.track(face)
    assert lm is not None
    return lm.points


def steady(tracker: LandmarkTracker, frame: np.ndarray) -> np.ndarray:
    """Track the same frame twice (detector crop, then landmark crop); (468, 3) points."""
    tracker.reset()
    assert tracker.track(frame) is not None
    lm = tracker.track(frame)
    assert lm is not None
    return lm.points


def warp(img: np.ndarray, m: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.warpAffine(img, m, size, borderMode=cv2.BORDER_REFLECT)


def apply_affine(m: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ m[:, :2].T + m[:, 2]


def test_anchor_layout() -> None:
    a = ssd_anchors()
    assert a.shape == (896, 2)
    assert np.allclose(a[0], [0.5 / 16, 0.5 / 16]) and np.allclose(a[1], a[0])
    assert np.allclose(a[512], [0.5 / 8, 0.5 / 8]) and np.allclose(a[517], a[512])
    assert np.allclose(a[-1], [7.5 / 8, 7.5 / 8])


def test_detector_finds_one_face(face: np.ndarray, detector: FaceDetector) -> None:
    dets = detector.detect(face)
    assert len(dets) == 1
    d = dets[0]
    assert d.score > 0.9
    x0, y0, x1, y1 = d.box
    # The face spans roughly x 160-260, y 70-180 in the fixture.
    assert 140 < x0 < 180 and 240 < x1 < 285 and 50 < y0 < 100 and 160 < y1 < 200
    right_eye, left_eye, nose, mouth = d.keypoints[:4]
    assert right_eye[0] < nose[0] < left_eye[0]
    assert max(right_eye[1], left_eye[1]) < nose[1] < mouth[1]


def test_detector_non_square_frame_maps_back(face: np.ndarray, detector: FaceDetector) -> None:
    # A non-square frame is padded (black, centred) to a square: the square made by hand
    # must give the same network input, so the same detection shifted by the padding.
    for h, w in [(480, 640), (700, 420)]:
        frame = np.full((h, w, 3), 90, np.uint8)
        top, left = (h - 420) // 2 + 7, max((w - 420) // 2 - 9, 0)
        frame[top : top + 420, left : left + 420] = face
        side = max(h, w)
        pad_y, pad_x = (side - h) // 2, (side - w) // 2
        square = np.zeros((side, side, 3), np.uint8)
        square[pad_y : pad_y + h, pad_x : pad_x + w] = frame
        d, ds = detector.detect(frame)[0], detector.detect(square)[0]
        assert np.allclose(d.keypoints, ds.keypoints - [pad_x, pad_y], atol=1e-6)
        assert np.allclose(d.box, ds.box - [pad_x, pad_y, pad_x, pad_y], atol=1e-6)
        # And it is the fixture's face, up to BlazeFace's coarseness on a face this small
        # (15-20 % of the frame side).
        ref = detector.detect(face)[0]
        eye_dist = np.linalg.norm(ref.keypoints[1] - ref.keypoints[0])
        err = np.linalg.norm(d.keypoints[:4] - (ref.keypoints[:4] + [left, top]), axis=1)
        assert err.max() < 0.5 * eye_dist, (err, eye_dist)


def test_landmarks_plausible(face: np.ndarray, tracker: LandmarkTracker) -> None:
    lm = tracker.track(face)
    assert lm is not None
    assert lm.points.shape == (468, 3) and lm.points.dtype == np.float64
    assert lm.presence > 0.9
    p = lm.points
    assert p[33, 0] < p[133, 0] < p[362, 0] < p[263, 0]
    eyes_y = max(p[[33, 133, 362, 263], 1])
    assert eyes_y < p[1, 1] < p[13, 1] <= p[14, 1] < p[152, 1]
    assert p[10, 1] < eyes_y
    assert p[61, 0] < p[1, 0] < p[291, 0]
    # Image z points away from the camera: the nose tip is nearer than the eye corners.
    assert p[1, 2] < p[33, 2] and p[1, 2] < p[263, 2]
    # z has the same scale as x: nose-to-eye depth is a sizeable fraction of eye distance.
    eye_dist = p[263, 0] - p[33, 0]
    assert 0.2 * eye_dist < (p[33, 2] + p[263, 2]) / 2 - p[1, 2] < 0.8 * eye_dist


def test_roll_25_degrees(face: np.ndarray, tracker: LandmarkTracker, upright: np.ndarray) -> None:
    for angle in (25.0, -25.0):
        m = cv2.getRotationMatrix2D((210.0, 120.0), angle, 1.0)
        rolled = warp(face, m, (420, 420))
        p = steady(tracker, rolled)
        back = apply_affine(cv2.invertAffineTransform(m), p[:, :2])
        err = np.linalg.norm(back - upright[:, :2], axis=1)
        assert err.mean() < 1.0 and err.max() < 3.0, (angle, err.mean(), err.max())
        # Roll is about the camera axis: depths are unchanged.
        dz = (p[:, 2] - p[:, 2].mean()) - (upright[:, 2] - upright[:, 2].mean())
        assert np.abs(dz).max() < 3.0


def test_first_frame_after_detection_handles_roll(
    face: np.ndarray, tracker: LandmarkTracker, upright: np.ndarray
) -> None:
    m = cv2.getRotationMatrix2D((210.0, 120.0), 25.0, 1.0)
    lm = tracker.track(warp(face, m, (420, 420)))
    assert lm is not None
    back = apply_affine(cv2.invertAffineTransform(m), lm.points[:, :2])
    assert np.linalg.norm(back - upright[:, :2], axis=1).mean() < 2.0


@pytest.mark.parametrize(("scale", "offset"), [(1.3, (50.0, 20.0)), (1.0, (-60.0, 100.0))])
def test_shifted_scaled_copy(
    face: np.ndarray,
    tracker: LandmarkTracker,
    upright: np.ndarray,
    scale: float,
    offset: tuple[float, float],
) -> None:
    m = np.array([[scale, 0.0, offset[0]], [0.0, scale, offset[1]]])
    frame = warp(face, m, (640, 480))
    p = steady(tracker, frame)
    back = (p[:, :2] - offset) / scale
    err = np.linalg.norm(back - upright[:, :2], axis=1)
    assert err.mean() < 1.0 and err.max() < 3.0, (err.mean(), err.max())
    # z scales with the image like x and y.
    z = p[:, 2] / scale
    dz = (z - z.mean()) - (upright[:, 2] - upright[:, 2].mean())
    assert np.abs(dz).max() < 3.0


def test_blank_and_noise_give_none(tracker: LandmarkTracker) -> None:
    rng = np.random.default_rng(1)
    frames = [
        np.zeros((480, 640, 3), np.uint8),
        np.full((480, 640, 3), 200, np.uint8),
        rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
        rng.integers(0, 256, (37, 53, 3), dtype=np.uint8),
    ]
    for frame in frames:
        assert tracker.track(frame) is None
        assert tracker.crop is None


def test_loss_then_redetect(face: np.ndarray, detector: CountingDetector) -> None:
    # Whole-frame detections only (the tile search would count its tiles too).
    tracker = LandmarkTracker(detector=detector, min_face=None)
    assert tracker.track(face) is not None
    assert tracker.crop is not None and tracker.detector is not None
    calls = tracker.detector.calls  # type: ignore[attr-defined]
    # The crop from the face's last position is fed a frame with no face (not a flat one):
    # presence must drop, and the detector looks at once in the same frame.
    no_face = cv2.GaussianBlur(face, (0, 0), 25)
    assert tracker.track(no_face) is None
    assert tracker.state == LOST and tracker.crop is None
    assert tracker.detector.calls == calls + 1  # type: ignore[attr-defined]
    assert tracker.track(no_face) is None and tracker.state == NO_FACE
    assert tracker.track(face) is not None and tracker.state == ACQUIRED
    assert tracker.detector.calls == calls + 3  # type: ignore[attr-defined]
    assert tracker.track(face) is not None and tracker.state == TRACKED
    assert tracker.detector.calls == calls + 3  # type: ignore[attr-defined]


def test_flat_frame_is_blank_without_detection(face: np.ndarray, tracker: LandmarkTracker) -> None:
    assert tracker.track(face) is not None
    calls = tracker.detector.calls  # type: ignore[attr-defined]
    for value in (0, 255, 93):
        assert tracker.track(np.full((480, 640, 3), value, np.uint8)) is None
        assert tracker.state == BLANK and tracker.crop is None
    assert tracker.detector.calls == calls  # type: ignore[attr-defined]
    # Camera noise on black is not flat: the detector runs and finds nothing.
    rng = np.random.default_rng(2)
    dark = rng.integers(0, 30, (480, 640, 3), dtype=np.uint8)
    assert tracker.track(dark) is None and tracker.state == NO_FACE


def det(x: float, y: float, size: float, score: float) -> Detection:
    box = np.array([x - size / 2, y - size / 2, x + size / 2, y + size / 2])
    return Detection(box, np.zeros((6, 2)), score)


def test_largest_face_first() -> None:
    small_sure, big_unsure = det(100, 100, 60, 0.99), det(500, 300, 120, 0.6)
    assert largest_first([small_sure, big_unsure], 640, 480) == [big_unsure, small_sure]
    # Within 15 % of each other's size they count as equal: nearest the centre first.
    near, far = det(330, 250, 100, 0.7), det(600, 50, 110, 0.99)
    assert largest_first([far, near], 640, 480) == [near, far]
    assert largest_first([]) == []


@pytest.mark.parametrize(("w", "h"), [(640, 480), (641, 481), (1920, 1080), (3840, 2160)])
def test_tiles_cover_every_small_face(w: int, h: int) -> None:
    tiles = tile_grid(w, h, 48.0)
    assert tiles and all(0 <= x and 0 <= y and x < w and y < h for x, y, _ in tiles)
    assert all(x + s <= w or x == 0 for x, _, s in tiles)
    assert all(y + s <= h or y == 0 for _, y, s in tiles)
    # Any face from 48 px to the whole-frame pass's reach, anywhere, lies wholly inside a
    # tile it fills at least 14 % of and at most 45 % of (its box: 1.1 x its width).
    rng = np.random.default_rng(0)
    t = np.array(tiles, dtype=np.float64)
    for _ in range(300):
        f = rng.uniform(48.0, 0.16 * max(w, h))
        b = 1.1 * f
        x, y = rng.uniform(0, w - b), rng.uniform(0, h - b)
        inside = (t[:, 0] <= x) & (t[:, 1] <= y)
        inside &= (x + b <= t[:, 0] + t[:, 2]) & (y + b <= t[:, 1] + t[:, 2])
        fits = inside & (f >= 0.14 * t[:, 2]) & (f <= 0.45 * t[:, 2])
        assert fits.any(), (f, x, y)
    assert tile_grid(176, 144) == []  # small frames: the whole-frame pass sees 48 px faces


def test_slowly_moving_face_stays_locked(
    face: np.ndarray, tracker: LandmarkTracker, upright: np.ndarray
) -> None:
    centre = (210.0, 120.0)
    for k in range(10):
        # 1.5 degrees and (4, 2) px per frame, placed in a 640x480 frame.
        m = cv2.getRotationMatrix2D(centre, 1.5 * k, 1.0)
        m[:, 2] += (100 + 4 * k, 20 + 2 * k)
        lm = tracker.track(warp(face, m, (640, 480)))
        assert lm is not None, k
        expected = apply_affine(m, upright[:, :2])
        err = np.linalg.norm(lm.points[:, :2] - expected, axis=1)
        assert err.mean() < 1.5, (k, err.mean())
    assert tracker.detector.calls == 1  # type: ignore[attr-defined]


def test_crop_from_points_is_roll_invariant(upright: np.ndarray) -> None:
    c0 = crop_from_points(upright)
    centre = upright[:, :2].mean(axis=0)
    m = cv2.getRotationMatrix2D(tuple(centre), 30.0, 1.0)
    c1 = crop_from_points(apply_affine(m, upright[:, :2]))
    assert c1.size == pytest.approx(c0.size, rel=1e-9)
    assert np.allclose(c1.centre, apply_affine(m, c0.centre[None])[0])
    assert np.degrees(c0.angle - c1.angle) == pytest.approx(30.0)


def test_crop_affine_maps_centre_and_axis() -> None:
    crop = Crop(np.array([100.0, 50.0]), 192.0 * 2, np.pi / 2)
    m = crop.crop_to_image()
    assert np.allclose(apply_affine(m, np.array([[95.5, 95.5]])), [[100.0, 50.0]])
    # Crop +x goes to image +y (rotated by 90 degrees), twice as long.
    d = apply_affine(m, np.array([[96.5, 95.5]])) - [100.0, 50.0]
    assert np.allclose(d, [[0.0, 2.0]])


@pytest.mark.parametrize("shape", [(480, 640), (480, 640, 4), (480, 640, 1)])
def test_rejects_bad_frames(tracker: LandmarkTracker, shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match=r"expected \(h, w, 3\) uint8"):
        tracker.track(np.zeros(shape, np.uint8))
    with pytest.raises(ValueError, match="float32"):
        tracker.track(np.zeros((48, 64, 3), np.float32))
