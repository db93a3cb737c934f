"""The eye model's lid contours (sender.eyes) on a real face and on the bundled clip's blinks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.mesh import FaceMesh
from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.eyes import (
    EYE_REGION,
    EYE_REGION_LEFT,
    LEFT_CORNERS,
    LIDS,
    RIGHT_CORNERS,
    EyeRefiner,
    eye_crop,
)
from facewire.sender.landmarks import LandmarkTracker

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"
LID_VERTICES = np.concatenate([EYE_REGION[LIDS], EYE_REGION_LEFT[LIDS]])


def lid_gaps(points: np.ndarray) -> np.ndarray:
    """Upper-to-lower lid distance at the middle of each eye (right, left), px."""
    return np.array(
        [np.linalg.norm(points[a, :2] - points[b, :2]) for a, b in ((159, 145), (386, 374))]
    )


def test_left_eye_is_the_mirror_of_the_right(mesh: FaceMesh) -> None:
    v = mesh.vertices
    mirrored = v[EYE_REGION] * np.array([-1.0, 1.0, 1.0])
    nearest = np.linalg.norm(v[None, :, :] - mirrored[:, None, :], axis=2).argmin(axis=1)
    assert nearest.tolist() == EYE_REGION_LEFT.tolist()
    assert len(set(EYE_REGION.tolist())) == len(EYE_REGION) == 71
    # The lids are points 1-7 and 9-15: 145 and 159 (mid lower and upper lid) among them.
    assert {145, 159} <= set(EYE_REGION[LIDS].tolist())
    assert not set(RIGHT_CORNERS) & set(EYE_REGION[LIDS].tolist())


def test_crop_puts_the_eye_in_the_middle_and_mirrors_the_left_one() -> None:
    points = np.zeros((468, 3))
    points[33, :2], points[133, :2] = (100.0, 200.0), (140.0, 200.0)  # right eye, picture left
    points[362, :2], points[263, :2] = (180.0, 200.0), (220.0, 200.0)
    m = eye_crop(points, RIGHT_CORNERS, mirrored=False)
    centre = m[:, :2] @ np.array([31.5, 31.5]) + m[:, 2]
    assert np.allclose(centre, (120.0, 200.0))
    assert m[0, 0] > 0  # crop +x runs outer -> inner corner: picture right for this eye
    m = eye_crop(points, LEFT_CORNERS, mirrored=True)
    assert np.allclose(m[:, :2] @ np.array([31.5, 31.5]) + m[:, 2], (200.0, 200.0))
    # Mirrored: crop +x runs from the outer corner (picture right) to the inner one.
    assert m[0, 0] < 0
    assert np.isclose(abs(m[0, 0]) * 64, 2.3 * 40)


def test_lids_only_are_moved_and_stay_on_the_eye() -> None:
    face = cv2.imread(str(FIXTURE))
    assert face is not None
    tracker = LandmarkTracker(refine_eyes=False)
    assert tracker.track(face) is not None
    found = tracker.track(face)
    assert found is not None
    refined = EyeRefiner().refine(face, found.points)
    others = np.setdiff1d(np.arange(468), LID_VERTICES)
    assert np.array_equal(refined[others], found.points[others])
    assert np.array_equal(refined[:, 2], found.points[:, 2])
    # An open eye in a sharp photo: both models agree to a tenth of the eye's width.
    width = np.linalg.norm(found.points[33, :2] - found.points[133, :2])
    moved = np.linalg.norm(refined[LID_VERTICES, :2] - found.points[LID_VERTICES, :2], axis=1)
    assert np.median(moved) < 0.1 * width
    assert np.all(np.abs(lid_gaps(refined) - lid_gaps(found.points)) < 0.15 * width)


@pytest.fixture(scope="module")
def blink_run() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Lid markers of frames 90-145 of the bundled clip (two blinks), without and with the
    eye model, and the clip's truth."""
    truth = dict(np.load(demo_clip_path().with_name("demo_clip_truth.npz")))
    plain, refined = LandmarkTracker(refine_eyes=False), LandmarkTracker()
    out: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    with VideoSource(demo_clip_path()) as video:
        for frame in video.frames():
            if frame.index < 90:
                continue
            if frame.index > 145:
                break
            for tracker, rows in zip((plain, refined), out, strict=True):
                found = tracker.track(frame.image)
                assert found is not None, frame.index
                rows.append(found.points)
    return np.array(out[0]), np.array(out[1]), truth


def test_blinks_come_through_deeper_and_lids_nearer_the_truth(
    blink_run: tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]],
) -> None:
    plain, refined, truth = blink_run
    frames = np.arange(90, 90 + len(plain))
    names = truth["marker_names"].tolist()
    lids = [names.index(n) for n in names if "_lid_" in n]
    vertices = truth["marker_vertices"][lids]
    want = truth["marker_xy"][frames][:, lids]
    err_plain = np.linalg.norm(plain[:, vertices, :2] - want, axis=2)
    err_refined = np.linalg.norm(refined[:, vertices, :2] - want, axis=2)
    assert np.median(err_refined) < 0.75 * np.median(err_plain)
    for blink in (100, 140):
        i = blink - 90
        gap_plain, gap_refined = lid_gaps(plain[i]).mean(), lid_gaps(refined[i]).mean()
        assert gap_refined < gap_plain - 1.5, (blink, gap_plain, gap_refined)
