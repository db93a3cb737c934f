"""One Euro landmark smoothing: less jitter on a still face, no lag on fast moves."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.mesh import load_canonical
from facewire.sender.landmarks import ACQUIRED, TRACKED, LandmarkTracker
from facewire.sender.smoothing import LandmarkSmoother, OneEuroFilter, alpha, face_scale

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"
FPS = 30.0


@pytest.fixture(scope="module")
def face() -> np.ndarray:
    """(468, 3) canonical mesh as a frontal face about 155 px wide, image pixels."""
    v = load_canonical().vertices
    return v * np.array([10.0, -10.0, -10.0]) + [320.0, 240.0, 0.0]


def run(smoother: LandmarkSmoother, frames: list[np.ndarray]) -> np.ndarray:
    return np.array([smoother(f, i / FPS) for i, f in enumerate(frames)])


def test_alpha_is_first_order_lowpass() -> None:
    # At the cutoff equal to the sampling rate / (2 pi), tau == dt: alpha = 1/2.
    assert alpha(1.0 / (2 * np.pi), 1.0) == pytest.approx(0.5)
    assert 0 < alpha(0.1, 1 / 30) < alpha(10.0, 1 / 30) < 1


def test_still_face_jitter_reduced(face: np.ndarray) -> None:
    # 0.5 px noise per coordinate on a still face: the frame-to-frame change (what a viewer
    # sees as jitter) drops at least 3-fold, the spread about the true position 1.8-fold,
    # and the mean stays put.
    rng = np.random.default_rng(0)
    raw = [face + rng.normal(0.0, 0.5, face.shape) for _ in range(300)]
    out = run(LandmarkSmoother(), raw)[30:]
    noisy = np.array(raw)[30:]
    step_raw = np.abs(np.diff(noisy, axis=0)).mean()
    step_out = np.abs(np.diff(out, axis=0)).mean()
    assert step_raw / step_out >= 3.0, step_raw / step_out
    assert np.abs(noisy - face).mean() / np.abs(out - face).mean() >= 1.8
    assert np.abs(out.mean(axis=0) - face).max() < 0.2


@pytest.mark.parametrize(("step", "frames", "reached"), [(0.3, 2, 0.95), (1.0, 1, 0.95)])
def test_fast_step_followed(face: np.ndarray, step: float, frames: int, reached: float) -> None:
    # The whole face jumps by ``step`` face widths between two frames: within ``frames``
    # frames the output has covered ``reached`` of the jump, and it never overshoots.
    width = float(np.ptp(face[:, 0]))
    s = LandmarkSmoother()
    for i in range(30):
        s(face, i / FPS)
    moved = face + [step * width, 0.0, 0.0]
    covered = []
    for i in range(30, 40):
        covered.append(float((s(moved, i / FPS)[:, 0] - face[:, 0]).mean() / (step * width)))
    assert covered[frames - 1] >= reached, covered
    assert max(covered) <= 1.0 + 1e-9


def test_steady_move_lags_under_half_a_frame(face: np.ndarray) -> None:
    # One face width per second, steady: the output trails by less than half a frame.
    width = float(np.ptp(face[:, 0]))
    per_frame = width / FPS
    s = LandmarkSmoother()
    for i in range(60):
        out = s(face + [i * per_frame, 0.0, 0.0], i / FPS)
    lag_px = 59 * per_frame - float((out[:, 0] - face[:, 0]).mean())
    assert 0 <= lag_px < 0.5 * per_frame, lag_px / per_frame


def test_scale_invariant(face: np.ndarray) -> None:
    # The same motion and noise relative to the face's size give the same relative result
    # on a face four times as large.
    rng = np.random.default_rng(3)
    noise = [rng.normal(0.0, 0.01, face.shape) for _ in range(60)]
    results = []
    for k in (1.0, 4.0):
        big = face * k
        sc = face_scale(big)
        frames = [big + sc * n + [sc * 0.05 * i, 0.0, 0.0] for i, n in enumerate(noise)]
        results.append((run(LandmarkSmoother(), frames) - big) / sc)
    assert np.allclose(results[0], results[1], atol=1e-9)


def test_blink_passes(face: np.ndarray) -> None:
    # Only a few points move fast (eyelids closing over 3 frames): one frame after they
    # close they have covered 85 % of the way (90 % measured), and the rest stays put.
    lid = np.array([159, 145, 386, 374])
    s = LandmarkSmoother()
    for i in range(30):
        s(face, i / FPS)
    closed = face.copy()
    closed[lid, 1] += 8.0
    for i, f in enumerate([0.33, 0.66, 1.0, 1.0]):
        out = s(face + (closed - face) * f, (30 + i) / FPS)
    assert (out[lid, 1] - face[lid, 1]).min() > 0.85 * 8.0
    rest = np.setdiff1d(np.arange(len(face)), lid)
    assert np.allclose(out[rest], face[rest])


def test_reset_and_timestamps(face: np.ndarray) -> None:
    f = OneEuroFilter()
    a = f(face, 0.0)
    assert np.array_equal(a, face)  # the first sample passes through
    b = f(face + 5.0, 0.0)  # same time again: nothing learnt
    assert np.array_equal(b, face)
    f.reset()
    assert np.array_equal(f(face + 5.0, 1.0), face + 5.0)
    with pytest.raises(ValueError, match=r"expected \(468, 3\) like the last sample"):
        f(face[:10], 2.0)
    with pytest.raises(ValueError, match=r"expected \(n, d\) float array"):
        f(face[:, 0], 3.0)
    with pytest.raises(ValueError, match="min_cutoff > 0"):
        OneEuroFilter(min_cutoff=0.0)


def test_tracker_smooths_and_restarts_on_reacquisition() -> None:
    # A still real face: the smoothed tracker jitters less than the raw one; after a blank
    # frame the face comes back elsewhere and is given where it is at once, not blended
    # from where it was.
    img = cv2.imread(str(FIXTURE))
    assert img is not None
    rng = np.random.default_rng(5)

    def frame(dx: float) -> np.ndarray:
        m = np.array([[1.0, 0.0, 100.0 + dx], [0.0, 1.0, 30.0]])
        out = cv2.warpAffine(img, m, (640, 480), borderMode=cv2.BORDER_REFLECT)
        noise = rng.normal(0.0, 3.0, out.shape)  # sensor noise makes the tracker jitter
        return np.clip(out + noise, 0, 255).astype(np.uint8)

    frames = [frame(0.0) for _ in range(40)]
    raw_t, smooth_t = LandmarkTracker(), LandmarkTracker(smoother=LandmarkSmoother())
    raw = np.array([raw_t.track(f).points for f in frames])  # type: ignore[union-attr]
    smooth = np.array([smooth_t.track(f).points for f in frames])  # type: ignore[union-attr]
    jitter = [np.abs(np.diff(p[10:, :, :2], axis=0)).mean() for p in (raw, smooth)]
    assert jitter[0] / jitter[1] >= 1.5, jitter

    assert smooth_t.track(np.zeros_like(frames[0])) is None
    back = frame(50.0)
    # Raw and smoothed trackers see the same frame from the same state: same points.
    raw_t.reset()
    expected = raw_t.track(back)
    got = smooth_t.track(back, timestamp_s=10.0)
    assert expected is not None and got is not None and smooth_t.state == ACQUIRED
    assert np.allclose(got.points, expected.points)
    assert smooth_t.track(back) is not None and smooth_t.state == TRACKED
