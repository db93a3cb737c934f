"""The picture quality metrics: SSIM and PSNR of luma by region, frames aligned by index."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire import quality
from facewire.quality import (
    HEAD_DOWN,
    HEAD_UP,
    HEAD_WIDTH,
    aligned,
    face_polygon,
    frame_scores,
    head_polygon,
    luma,
    psnr,
    region_masks,
    score_frames,
    score_videos,
    ssim,
    ssim_map,
)
from facewire.sender.landmarks import LandmarkTracker

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


@pytest.fixture(scope="module")
def face() -> np.ndarray:
    img = cv2.imread(str(FIXTURE))
    assert img is not None, FIXTURE
    return img


@pytest.fixture(scope="module")
def points(face: np.ndarray) -> np.ndarray:
    """The tracker's landmarks of the fixture, (468, 3) image pixels."""
    found = LandmarkTracker().track(face)
    assert found is not None
    return found.points


def noisy(image: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0, sigma, image.shape), 0, 255).astype(np.uint8)


def jpeg(image: np.ndarray, q: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, q])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def test_luma_is_bt601_of_bgr() -> None:
    px = np.array([[[10, 20, 30]]], np.uint8)  # B, G, R
    assert luma(px)[0, 0] == pytest.approx(0.299 * 30 + 0.587 * 20 + 0.114 * 10)
    grey = np.full((4, 5), 7, np.uint8)
    assert np.array_equal(luma(grey), grey.astype(np.float64))


def test_identical_frames_score_one_and_infinite_psnr(face: np.ndarray, points: np.ndarray) -> None:
    masks = region_masks(points, face.shape)
    scores = frame_scores(face, face.copy(), masks)
    for region in quality.REGIONS:
        s, p = scores[region]
        assert s == pytest.approx(1.0, abs=1e-12), region
        assert p == math.inf, region
    assert np.allclose(ssim_map(face, face), 1.0)


def test_ssim_map_is_scikit_images_gaussian_ssim(face: np.ndarray) -> None:
    metrics = pytest.importorskip("skimage.metrics")
    for test in (noisy(face, 12), jpeg(face, 20), cv2.GaussianBlur(face, (7, 7), 2)):
        ours = ssim_map(face, test)
        mean, theirs = metrics.structural_similarity(
            luma(face),
            luma(test),
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=255,
            full=True,
        )
        # Same window, constants and reflected edges: the same map, pixel for pixel.
        assert np.abs(ours - theirs).max() < 1e-9
        assert ssim(face, test) == pytest.approx(theirs.mean(), abs=1e-12)
        # scikit-image's own mean leaves out a 5-pixel border.
        assert ours[5:-5, 5:-5].mean() == pytest.approx(mean, abs=1e-12)


def test_psnr_of_a_known_error() -> None:
    a = np.full((20, 20), 100, np.uint8)
    b = a.copy()
    b[:10] += 10  # half the pixels off by 10: MSE 50
    assert psnr(a, b) == pytest.approx(10 * math.log10(255**2 / 50))
    top = np.zeros((20, 20), bool)
    top[:10] = True
    assert psnr(a, b, top) == pytest.approx(10 * math.log10(255**2 / 100))
    assert psnr(a, b, ~top) == math.inf


def test_known_degradations_order(face: np.ndarray, points: np.ndarray) -> None:
    masks = region_masks(points, face.shape)
    for ladder in (
        [noisy(face, s) for s in (2, 8, 20, 40)],
        [jpeg(face, q) for q in (90, 50, 20, 5)],
        [cv2.GaussianBlur(face, (0, 0), s) for s in (0.7, 1.5, 3, 6)],
    ):
        for region in quality.REGIONS:
            s = [frame_scores(face, img, masks)[region][0] for img in ladder]
            p = [frame_scores(face, img, masks)[region][1] for img in ladder]
            assert s == sorted(s, reverse=True) and len(set(s)) == len(s), (region, s)
            assert p == sorted(p, reverse=True) and len(set(p)) == len(p), (region, p)


def test_region_ignores_damage_outside_and_catches_damage_inside(
    face: np.ndarray, points: np.ndarray
) -> None:
    masks = region_masks(points, face.shape)
    # The SSIM window reaches 5 pixels: keep the damage 6 pixels clear of the face.
    near = cv2.dilate(masks["face"].astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    outside = face.copy()
    outside[~near] = noisy(face, 40)[~near]
    scores = frame_scores(face, outside, masks)
    assert scores["face"] == (pytest.approx(1.0, abs=1e-12), math.inf)
    assert scores["frame"][0] < 0.8 and scores["head"][0] < 1.0

    inside = face.copy()
    inner = cv2.erode(masks["face"].astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
    inside[inner] = noisy(face, 40)[inner]
    scores = frame_scores(face, inside, masks)
    assert scores["face"][0] < 0.8
    # The same damage is diluted over the larger regions.
    assert scores["face"][0] < scores["head"][0] < scores["frame"][0] < 1.0
    assert scores["face"][1] < scores["head"][1] < scores["frame"][1]


def test_face_and_head_regions(face: np.ndarray, points: np.ndarray) -> None:
    masks = region_masks(points, face.shape)
    f, h = masks["face"], masks["head"]
    assert f.sum() > 0.03 * f.size  # the fixture face is about 95 px wide in 420
    assert np.all(h[f]), "the head takes in the whole face"
    assert 1.5 * f.sum() < h.sum() < 3.0 * f.sum()
    assert masks["frame"].all()
    # The face mask is the landmarks' hull: every landmark is in the hull, and the pixel of
    # every landmark more than a pixel inside it is in the mask.
    hull32 = face_polygon(points).astype(np.float32)
    depth = np.array([cv2.pointPolygonTest(hull32, (x, y), True) for x, y in points[:, :2]])
    assert depth.min() > -1e-3
    xy = np.round(points[depth > 1, :2]).astype(int)
    assert len(xy) > 400 and f[xy[:, 1], xy[:, 0]].all()
    assert not f[0, 0] and not h[0, 0]
    # The rule, on an upright face: the head reaches HEAD_UP above the centre, HEAD_DOWN below.
    hull = face_polygon(points)
    head = head_polygon(points)
    top, bottom = hull[:, 1].min(), hull[:, 1].max()
    cy = (top + bottom) / 2
    tilt = abs(np.degrees(np.arctan2(*(points[263, 1::-1] - points[33, 1::-1]))))
    assert tilt < 5, "the fixture face is upright"
    assert cy - head[:, 1].min() == pytest.approx(HEAD_UP * (cy - top), rel=0.03)
    assert head[:, 1].max() - cy == pytest.approx(HEAD_DOWN * (bottom - cy), rel=0.03)
    width = np.ptp(hull[:, 0])
    assert np.ptp(head[:, 0]) == pytest.approx(HEAD_WIDTH * width, rel=0.03)


def test_head_turns_with_a_rolled_face(points: np.ndarray) -> None:
    """The head region is built in the face's own upright frame."""
    angle = np.radians(35)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centre = np.array([200.0, 200.0])
    rolled = points.copy()
    rolled[:, :2] = (points[:, :2] - centre) @ rot.T + centre
    expected = (head_polygon(points) - centre) @ rot.T + centre
    got = head_polygon(rolled)
    # Same polygon: every vertex of one lies on (within 0.01 px of) the other's vertex set.
    d = np.linalg.norm(got[:, None] - expected[None], axis=2)
    assert d.min(axis=1).max() < 0.01 and d.min(axis=0).max() < 0.01


def test_no_face_gives_empty_face_and_head() -> None:
    masks = region_masks(None, (30, 40, 3))
    assert not masks["face"].any() and not masks["head"].any() and masks["frame"].all()
    a = np.zeros((30, 40, 3), np.uint8)
    scores = frame_scores(a, a + 1, masks)
    assert math.isnan(scores["face"][0]) and math.isnan(scores["head"][1])
    assert scores["frame"][1] < math.inf


def test_aligned_holds_dropped_and_missing_frames() -> None:
    a, b, c = (np.full((2, 2), v, np.uint8) for v in (1, 2, 3))
    got = list(aligned([a, None, b, None, None, c, c], 6))
    assert [int(f[0, 0]) for f, _ in got] == [1, 1, 2, 2, 2, 3]
    assert [h for _, h in got] == [False, True, False, True, True, False]
    # Past the end of the output: the last frame is held.
    got = list(aligned([a, b], 4))
    assert [int(f[0, 0]) for f, _ in got] == [1, 2, 2, 2]
    with pytest.raises(ValueError, match="output frame 0 is missing"):
        list(aligned([None, a], 2))


def test_score_frames_aligns_by_index_and_holds(face: np.ndarray, points: np.ndarray) -> None:
    frames = [face, np.roll(face, 3, axis=1), np.roll(face, 6, axis=1)]
    report = score_frames(frames, [frames[0], None], [points, points, points])
    assert report.frames == 3 and report.held == 2
    # Frame 1 and 2 are scored against the held frame 0, not skipped.
    expected = [frame_scores(f, frames[0], region_masks(points, f.shape)) for f in frames]
    for region in quality.REGIONS:
        assert report.ssim[region] == pytest.approx([e[region][0] for e in expected])
    assert report.ssim["face"][0] == pytest.approx(1.0)
    assert report.ssim["face"][2] < report.ssim["face"][1] < 1.0
    # Scored by index: output shifted one frame later scores worse than the same frames in place.
    in_place = score_frames(frames, frames, [points] * 3).mean_ssim("face")
    late = score_frames(frames, [frames[0], *frames[:2]], [points] * 3).mean_ssim("face")
    assert in_place == pytest.approx(1.0) and late < in_place - 0.05


def test_untracked_input_frames_leave_face_and_head_out_of_the_mean(
    face: np.ndarray, points: np.ndarray
) -> None:
    damaged = noisy(face, 20)
    report = score_frames([face, face], [face, damaged], [points, None])
    assert report.untracked == 1
    assert report.mean_ssim("face") == pytest.approx(1.0)  # frame 1 had no face to score
    assert report.mean_ssim("frame") < 1.0
    assert report.mean_psnr("face") == quality.PSNR_CAP_DB
    summary = report.as_dict()
    assert summary["untracked"] == 1 and summary["frames"] == 2


def test_different_sizes_are_one_readable_error(face: np.ndarray, points: np.ndarray) -> None:
    small = cv2.resize(face, (200, 100))
    with pytest.raises(ValueError, match=r"output frame 1 is 200x100, the input is 420x420"):
        score_frames([face, face], [face, small], [points, points])
    with pytest.raises(ValueError, match=r"images differ in size: 200x100 against .* 420x420"):
        ssim(face, small)
    with pytest.raises(ValueError, match=r"mask is 3x3, images are 420x420"):
        ssim(face, face, np.ones((3, 3), bool))
    with pytest.raises(ValueError, match=r"expected \(468, 2 or 3\) landmarks, got \(10, 2\)"):
        region_masks(np.zeros((10, 2)), face.shape)


def _write(path: Path, frames: list[np.ndarray]) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"FFV1"), 30.0, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()


def test_score_videos_on_real_files(tmp_path: Path, face: np.ndarray) -> None:
    """Lossless files through OpenCV: the same file scores 1; a shorter output is held."""
    frames = [np.roll(face, 2 * i, axis=1) for i in range(4)]
    src, short = tmp_path / "in.avi", tmp_path / "short.avi"
    _write(src, frames)
    _write(short, frames[:2])
    same = score_videos(src, src)
    assert same.frames == 4 and same.held == 0 and same.untracked == 0
    for region in quality.REGIONS:
        assert same.mean_ssim(region) == pytest.approx(1.0)
        assert same.mean_psnr(region) == quality.PSNR_CAP_DB
    held = score_videos(src, short)
    assert held.held == 2
    assert held.ssim["face"][:2] == pytest.approx([1.0, 1.0])
    assert held.ssim["face"][3] < held.ssim["face"][2] < 1.0
    first_two = score_videos(src, short, limit=2)
    assert first_two.frames == 2 and first_two.held == 0
    with pytest.raises(OSError, match="cannot read video"):
        score_videos(src, tmp_path / "missing.avi")
