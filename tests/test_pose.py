"""Head pose value object and the weighted Umeyama similarity fit."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facewire.models.mesh import load_canonical
from facewire.models.pose import FRONTAL, Pose, estimate_pose, residual_rms

logger = logging.getLogger(__name__)
FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def random_pose(rng: np.random.Generator) -> Pose:
    r = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
    return Pose(r, float(rng.uniform(0.5, 20.0)), rng.normal(0, 100, 3))


@pytest.fixture(scope="module")
def canonical() -> np.ndarray:
    return load_canonical().vertices


def test_apply_inverse_round_trip() -> None:
    rng = np.random.default_rng(0)
    pose = random_pose(rng)
    x = rng.normal(0, 5, (50, 3))
    assert np.allclose(pose.inverse(pose.apply(x)), x, atol=1e-12)
    assert np.allclose(pose.apply(x), x @ (pose.scale * pose.rotation).T + pose.translation)


def test_matrix_and_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    pose = random_pose(rng)
    m = pose.as_matrix()
    x = rng.normal(0, 5, (10, 3))
    assert np.allclose((np.c_[x, np.ones(10)] @ m.T)[:, :3], pose.apply(x))
    back = Pose.from_matrix(m)
    assert np.allclose(back.rotation, pose.rotation, atol=1e-12)
    assert back.scale == pytest.approx(pose.scale, rel=1e-12)
    assert np.allclose(back.translation, pose.translation)
    q = pose.as_quaternion()
    assert q.shape == (4,) and np.linalg.norm(q) == pytest.approx(1.0)
    again = Pose.from_quaternion(q, pose.scale, pose.translation)
    assert np.allclose(again.rotation, pose.rotation, atol=1e-12)


def test_frontal_maps_model_axes_to_image_axes() -> None:
    pose = Pose.frontal(2.0, np.array([320.0, 240.0, 0.0]))
    # Face's left (+x) -> image right, up (+y) -> image up (smaller y), towards viewer -> nearer.
    out = pose.apply(np.eye(3))
    assert np.allclose(out, [[322, 240, 0], [320, 238, 0], [320, 240, -2]])
    assert np.allclose(pose.as_quaternion(), [1, 0, 0, 0])  # 180 degrees about x


@pytest.mark.parametrize("seed", range(5))
def test_estimate_recovers_random_similarity(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = random_pose(rng)
    m = rng.normal(0, 5, (30, 3))
    w = rng.uniform(0.1, 2.0, 30) if seed % 2 else None
    est = estimate_pose(m, pose.apply(m), w)
    assert np.abs(est.rotation - pose.rotation).max() < 1e-9
    assert est.scale == pytest.approx(pose.scale, rel=1e-9)
    assert np.abs(est.translation - pose.translation).max() < 1e-9
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)


def test_weights_ignore_outliers() -> None:
    rng = np.random.default_rng(7)
    pose = random_pose(rng)
    m = rng.normal(0, 5, (20, 3))
    p = pose.apply(m)
    p[:3] += rng.normal(0, 50, (3, 3))
    w = np.ones(20)
    w[:3] = 0.0
    est = estimate_pose(m, p, w)
    assert np.abs(est.rotation - pose.rotation).max() < 1e-9
    assert np.abs(estimate_pose(m, p).rotation - pose.rotation).max() > 1e-3


def test_reflection_gives_proper_rotation() -> None:
    rng = np.random.default_rng(3)
    m = rng.normal(0, 5, (20, 3))
    mirrored = m * [-1, 1, 1]
    est = estimate_pose(m, mirrored)
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)


def test_frontal_canonical_mesh(canonical: np.ndarray) -> None:
    truth = Pose.frontal(6.0, np.array([320.0, 240.0, 50.0]))
    est = estimate_pose(canonical, truth.apply(canonical))
    assert np.allclose(est.rotation, FRONTAL, atol=1e-9)
    assert est.scale == pytest.approx(6.0)


def test_pose_of_astronaut_landmarks(canonical: np.ndarray) -> None:
    cv2 = pytest.importorskip("cv2")
    from facewire.sender.landmarks import LandmarkTracker

    img = cv2.imread(str(FIXTURE))
    tracker = LandmarkTracker()
    tracker.track(img)
    lm = tracker.track(img)
    assert lm is not None
    pose = estimate_pose(canonical, lm.points)
    # Deviation from a frontal pose, as a rotation in model space.
    dev = Rotation.from_matrix(FRONTAL.T @ pose.rotation)
    assert np.degrees(dev.magnitude()) < 20.0
    # About 6.4 px/cm: the fixture's eye corners are ~77 px apart, the mesh's ~8.9 cm.
    assert 5.0 < pose.scale < 8.0
    rms = residual_rms(pose, canonical, lm.points)
    logger.info("astronaut pose %s, residual RMS %.3f cm", pose, rms)
    # A smiling, non-canonical face: well under a centimetre, but not zero.
    assert 0.2 < rms < 1.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((np.zeros((4, 2)), np.zeros((4, 3))), r"model points as \(n, 3\).*\(4, 2\)"),
        ((np.zeros((4, 3)), np.zeros((5, 3))), "counts differ: 4 vs 5"),
        ((np.eye(3), np.eye(3), np.ones(2)), r"expected \(3,\) weights, got \(2,\)"),
        ((np.eye(3), np.eye(3), -np.ones(3)), "non-negative"),
        ((np.ones((4, 3)), np.eye(4, 3)), "coincident"),
    ],
)
def test_estimate_rejects_bad_input(args: tuple, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        estimate_pose(*args)


def test_pose_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="proper rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), 1.0, np.zeros(3))
    with pytest.raises(ValueError, match=r"\(3,\) translation, got \(2,\)"):
        Pose(np.eye(3), 1.0, np.zeros(2))
    with pytest.raises(ValueError, match="positive finite scale, got -1"):
        Pose(np.eye(3), -1.0, np.zeros(3))
    with pytest.raises(ValueError, match="det"):
        Pose.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))
