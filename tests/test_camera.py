"""The camera's motion: measured on the background at the sender, sent as corner shifts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.camera import (
    camera_step,
    corners_from_homography,
    frame_corners,
    homography_from_corners,
)
from facewire.models.face_channels import HYSTERESIS
from facewire.receiver.decoder import FaceDecoder
from facewire.sender.camera_motion import CameraTracker, person_covers, person_mask
from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder

W, H = 352, 288
FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def test_corner_shifts_round_trip_a_similarity() -> None:
    zoom, roll = 1.01, 0.02
    homography = np.array(
        [
            [zoom * np.cos(roll), -zoom * np.sin(roll), 3.5],
            [zoom * np.sin(roll), zoom * np.cos(roll), -2.0],
            [0.0, 0.0, 1.0],
        ]
    )
    shift = corners_from_homography(homography, W, H)
    assert shift.shape == (4,)
    assert np.allclose(homography_from_corners(shift, W, H), homography, atol=1e-12)
    assert np.allclose(corners_from_homography(np.eye(3), W, H), 0.0)
    assert frame_corners(W, H).tolist() == [[0, 0], [W - 1, H - 1]]


def test_a_corner_step_bounds_the_error_inside_the_frame() -> None:
    # Each corner off by the most the quantiser allows: no pixel inside moves further than
    # the budget.
    rng = np.random.default_rng(1)
    step = camera_step(0.5)
    limit = (0.5 + HYSTERESIS) * step
    grid = np.stack(np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 9)), -1)
    points = grid.reshape(1, -1, 2).astype(np.float32)
    for _ in range(200):
        error = rng.choice([-limit, limit], 4)  # the worst case: every value at its limit
        moved = cv2.perspectiveTransform(points, homography_from_corners(error, W, H))
        assert np.abs(moved - points).max() <= 0.5  # the budget, along each axis


def test_a_bad_corner_vector_is_refused() -> None:
    with pytest.raises(ValueError, match=r"expected \(4,\) corner displacements, got \(8,\)"):
        homography_from_corners(np.zeros(8), W, H)


def _scene() -> np.ndarray:
    """A textured scene (the photo tiled and blurred a little) with no face in the middle."""
    photo = cv2.imread(str(FIXTURE))
    tiled = np.tile(photo, (2, 2, 1))[: H + 80, : W + 80]
    return cv2.GaussianBlur(tiled, (3, 3), 0)


def _outline() -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    return np.c_[W / 2 + 30 * np.cos(t), 90 + 38 * np.sin(t)]


def _view(scene: np.ndarray, motion: np.ndarray, person_shift: float) -> np.ndarray:
    """The camera's view of ``scene`` moved by ``motion`` (2, 3), with a grey 'person' that
    moves on its own by ``person_shift`` pixels."""
    image = cv2.warpAffine(scene, motion, (W, H), borderMode=cv2.BORDER_REFLECT)
    mask = person_mask((H, W), _outline() + [person_shift, 0.0])
    image[mask] = (np.arange(mask.sum()) % 97 + 80)[:, None].astype(np.uint8)
    return image


def test_the_camera_shake_is_measured_on_the_background_not_the_person() -> None:
    scene = _scene()
    still = np.array([[1.0, 0.0, -40.0], [0.0, 1.0, -40.0]])
    tracker = CameraTracker(_view(scene, still, 0.0), _outline())
    angle = np.deg2rad(1.5)
    for step in range(1, 6):  # the camera drifts and rolls; the person walks the other way
        shake = still.copy()
        shake[:, :2] = [[np.cos(angle * step / 5), -np.sin(angle * step / 5)],
                        [np.sin(angle * step / 5), np.cos(angle * step / 5)]]  # fmt: skip
        shake[:, 2] += [1.6 * step, -1.0 * step]
        found = tracker.update(_view(scene, shake, -6.0 * step), _outline() + [-6.0 * step, 0])
    # Compare in the frame: where the truth and the estimate put the snapshot's pixels.
    truth = np.vstack([shake, [0, 0, 1]]) @ np.linalg.inv(np.vstack([still, [0, 0, 1]]))
    grid = frame_corners(W, H)[None].astype(np.float32)
    error = cv2.perspectiveTransform(grid, found) - cv2.perspectiveTransform(grid, truth)
    assert np.abs(error).max() < 0.75, error  # the person moved 30 px the other way
    assert np.abs(corners_from_homography(truth, W, H)).max() > 5.0  # it did move


def test_a_shake_seen_once_does_not_shift_the_scene_for_good() -> None:
    """The camera shakes by 3 px once and comes back to rest; from then on most of the
    background is a window whose view scrolls, so its points agree on no motion. The points
    still at rest fit a still camera as well as the shake (better): the scene stops moving."""
    scene = _scene()
    rest = np.array([[1.0, 0.0, -40.0], [0.0, 1.0, -40.0]])
    window = np.zeros((H, W), bool)
    window[:, : int(0.7 * W)] = True
    window &= ~person_mask((H, W), _outline())
    passing = cv2.flip(scene, 1)  # the view through the window: its own texture

    def view(camera: np.ndarray, scroll: float) -> np.ndarray:
        image = _view(scene, camera, 0.0)
        seen = cv2.warpAffine(passing, np.array([[1.0, 0, scroll - 40], [0, 1.0, -40]]), (W, H))
        image[window] = seen[window]
        return image

    tracker = CameraTracker(view(rest, 0.0), _outline())
    shaken = rest + [[0, 0, 3.0], [0, 0, 0]]
    assert corners_from_homography(tracker.update(view(shaken, 3.0), _outline()), W, H)[0] > 2.0
    for step in range(1, 6):
        found = tracker.update(view(rest, 7.0 * step), _outline())
    assert np.abs(corners_from_homography(found, W, H)).max() < 0.75


def test_a_featureless_scene_keeps_the_camera_still() -> None:
    flat = np.full((H, W, 3), 128, np.uint8)
    tracker = CameraTracker(flat, _outline())
    assert np.array_equal(tracker.update(flat, _outline()), np.eye(3))


def test_a_second_person_moving_is_not_taken_for_the_camera() -> None:
    # Someone else fills the left part of the view and sways on their own while the camera
    # drifts. The person segmentation of the snapshot frame (here: the known region) keeps
    # their corners out; without it most points disagree and the camera's motion is lost.
    scene = _scene()
    other = cv2.flip(scene, -1)  # their own texture
    still = np.array([[1.0, 0.0, -40.0], [0.0, 1.0, -40.0]])
    region = np.zeros((H, W), bool)
    region[:, :150] = True

    def view(camera: np.ndarray, sway: float) -> np.ndarray:
        image = cv2.warpAffine(scene, camera, (W, H), borderMode=cv2.BORDER_REFLECT)
        moved = cv2.warpAffine(other, np.array([[1.0, 0, sway - 40], [0, 1.0, -40]]), (W, H))
        image[region] = moved[region]
        return image

    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    face = np.c_[W / 2 + 40 + 15 * np.cos(t), 60 + 19 * np.sin(t)]  # a small face, top right
    people = region.astype(np.float32)
    with_mask = CameraTracker(view(still, 0.0), face, people)
    without = CameraTracker(view(still, 0.0), face)
    for step in range(1, 6):
        shake = still.copy()
        shake[:, 2] += [1.5 * step, -1.2 * step]
        image = view(shake, 5.0 * step)
        found, lost = with_mask.update(image, face), without.update(image, face)
    truth = np.vstack([shake, [0, 0, 1]]) @ np.linalg.inv(np.vstack([still, [0, 0, 1]]))
    grid = frame_corners(W, H)[None].astype(np.float32)

    def error(h: np.ndarray) -> float:
        return float(
            np.abs(cv2.perspectiveTransform(grid, h) - cv2.perspectiveTransform(grid, truth)).max()
        )

    assert error(found) < 0.75
    assert error(lost) > 3.0


def test_the_points_the_person_covers_are_those_of_the_drawn_mask() -> None:
    # Each frame's followed points are checked against the person's shape itself, not a mask
    # of the whole frame drawn for them: the same answer, away from the mask's pixel edges.
    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    outline = np.c_[176 + 30 * np.cos(t), 110 + 40 * np.sin(t)]
    mask = person_mask((H, W), outline)
    ys, xs = np.mgrid[0:H, 0:W]
    points = np.c_[xs.ravel(), ys.ravel()].astype(np.float32)
    covers = person_covers(points, outline).reshape(H, W)
    edge = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))
    assert 0.2 < mask.mean() < 0.8
    assert np.array_equal(covers[edge == 0], mask[edge == 0])


def test_a_large_frame_is_followed_scaled_down_to_a_tenth_of_a_pixel() -> None:
    # A 1280x720 frame's points are followed in it scaled to FOLLOW_SIDE: a zoom and a roll
    # with a shift still come out to a tenth of a pixel at the frame's corners.
    width, height = 1280, 720
    photo = cv2.imread(str(FIXTURE))
    scene = cv2.GaussianBlur(np.tile(photo, (3, 4, 1))[: height + 80, : width + 80], (3, 3), 0)
    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    outline = np.c_[width / 2 + 90 * np.cos(t), 260 + 115 * np.sin(t)]
    still = np.array([[1.0, 0.0, -40.0], [0.0, 1.0, -40.0]])
    tracker = CameraTracker(
        cv2.warpAffine(scene, still, (width, height), borderMode=cv2.BORDER_REFLECT), outline
    )
    zoom, roll = 1.004, np.deg2rad(0.4)
    moved = still.copy()
    moved[:, :2] = zoom * np.array([[np.cos(roll), -np.sin(roll)], [np.sin(roll), np.cos(roll)]])
    moved[:, 2] += [2.3, -1.7]
    view = cv2.warpAffine(scene, moved, (width, height), borderMode=cv2.BORDER_REFLECT)
    found = tracker.update(view, outline)
    truth = np.vstack([moved, [0, 0, 1]]) @ np.linalg.inv(np.vstack([still, [0, 0, 1]]))
    grid = frame_corners(width, height)[None].astype(np.float32)
    error = cv2.perspectiveTransform(grid, found) - cv2.perspectiveTransform(grid, truth)
    assert np.abs(error).max() < 0.1, error
    assert np.abs(corners_from_homography(truth, width, height)).max() > 4.0  # it did move


def test_a_panning_camera_reaches_the_receiver_as_the_scenes_motion() -> None:
    """The sender follows the scene on a thread beside its face tracker (sender/encoder.py):
    the bundled clip panned 0.5 px right and 0.3 px down a frame comes out of the receiver's
    decoder as the camera's motion, the face's own motion apart."""
    with VideoSource(demo_clip_path()) as video:
        frames = list(video.frames(limit=20))
        encoder = FaceEncoder(video.width, video.height, video.fps)
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    decoder = FaceDecoder(snapshot)
    try:
        shown = None
        for i, frame in enumerate(frames[1:], start=1):
            pan = np.float32([[1, 0, 0.5 * i], [0, 1, 0.3 * i]])
            size = (video.width, video.height)
            panned = cv2.warpAffine(frame.image, pan, size, borderMode=cv2.BORDER_REFLECT)
            packet = encoder.encode(dataclasses.replace(frame, image=panned))
            if packet is not None:
                shown = decoder.decode(packet)
        assert shown is not None
        moved = corners_from_homography(decoder.camera(shown), video.width, video.height)
    finally:
        decoder.close()
    assert np.allclose(moved, [9.5, 5.7, 9.5, 5.7], atol=1.5), moved
