"""Ray casting onto the face mesh (models.raycast) and the head pose from 2D points
(models.pose2d), on the canonical mesh and the bundled clip's person mesh and poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facewire.models.mesh import FaceMesh
from facewire.models.pose import Pose
from facewire.models.pose2d import estimate_pose_2d
from facewire.models.raycast import RayCaster, orthographic_rays

TRUTH = Path(__file__).resolve().parent.parent / "sender" / "data" / "demo_clip_truth.npz"


def turned(yaw: float, pitch: float, roll: float, scale: float = 13.5) -> Pose:
    """A pose looking ``yaw``/``pitch``/``roll`` degrees away from the camera, at (320, 240)."""
    own = Rotation.from_euler("YXZ", [yaw, pitch, roll], degrees=True).as_matrix()
    return Pose(np.diag([1.0, -1.0, -1.0]) @ own, scale, np.array([320.0, 240.0, 0.0]))


def same_hits(a, b) -> None:  # noqa: ANN001
    np.testing.assert_array_equal(a.hit, b.hit)
    np.testing.assert_array_equal(a.triangle, b.triangle)
    np.testing.assert_allclose(a.points, b.points, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(a.facing, b.facing, atol=1e-12, equal_nan=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tree_finds_what_testing_every_triangle_finds(mesh: FaceMesh, seed: int) -> None:
    rng = np.random.default_rng(seed)
    caster = RayCaster(mesh.triangles, mesh.vertices)
    pose = turned(*rng.uniform(-30, 30, 3))
    image = pose.apply(mesh.vertices)[:, :2]
    # Rays near vertices (hits), across the whole box (hits and misses) and beside it (misses).
    lo, hi = image.min(axis=0), image.max(axis=0)
    xy = np.vstack(
        [
            image[rng.choice(len(image), 100)] + rng.normal(0, 1.5, (100, 2)),
            rng.uniform(lo - 20, hi + 20, (200, 2)),
        ]
    )
    rays = orthographic_rays(pose, xy)
    fast, slow = caster.cast(*rays), caster.cast_all(*rays)
    assert 100 < fast.hit.sum() < len(xy)
    same_hits(fast, slow)
    # After the face deforms the refitted tree still agrees, and meets the moved surface.
    moved = mesh.vertices + rng.normal(0, 0.3, mesh.vertices.shape)
    caster.update(moved)
    after, slow = caster.cast(*rays), caster.cast_all(*rays)
    same_hits(after, slow)
    both = fast.hit & after.hit
    assert np.median(np.linalg.norm(after.points[both] - fast.points[both], axis=1)) > 0.05


@pytest.mark.parametrize("angles", [(0, 0, 0), (25, -10, 15), (-35, 20, -30)])
def test_ray_through_a_vertex_meets_it(mesh: FaceMesh, angles: tuple[float, ...]) -> None:
    pose = turned(*angles)
    caster = RayCaster(mesh.triangles, mesh.vertices)
    normals = mesh.vertex_normals() @ pose.rotation.T
    # Vertices the camera sees head-on enough (the nose tip, the cheeks, ...).
    front = np.flatnonzero(-normals[:, 2] > 0.6)
    hits = caster.cast(*orthographic_rays(pose, pose.apply(mesh.vertices[front])[:, :2]))
    # A vertex may hide behind the nose when the head turns: most are seen, and each that is
    # met is met at the vertex itself, facing the camera.
    met = np.linalg.norm(hits.points - mesh.vertices[front], axis=1) < 1e-6
    assert met.mean() > 0.9
    assert (hits.facing[met] > 0.0).all()
    np.testing.assert_allclose(hits.barycentric[met].sum(axis=1), 1.0)
    corners = mesh.triangles[hits.triangle[met]]
    assert all(v in c for v, c in zip(front[met], corners, strict=True))


def test_misses_and_back_faces(mesh: FaceMesh) -> None:
    pose = turned(0, 0, 0)
    caster = RayCaster(mesh.triangles, mesh.vertices)
    beside = np.array([[10.0, 10.0], [630.0, 470.0]])
    hits = caster.cast(*orthographic_rays(pose, beside))
    assert not hits.hit.any()
    assert (hits.triangle == -1).all() and np.isnan(hits.points).all()
    assert np.isinf(hits.distance).all()
    # From behind the head the first surface is the face's back: it faces away.
    origins, directions = orthographic_rays(pose, pose.apply(mesh.vertices[[1, 168]])[:, :2])
    back = caster.cast(origins + 2000.0 * directions, -directions)
    assert back.hit.all() and (back.facing < 0).all()


def test_bad_input_says_what_it_got(mesh: FaceMesh) -> None:
    with pytest.raises(ValueError, match=r"expected \(m, 3\) triangles, got \(4,\)"):
        RayCaster(np.arange(4), mesh.vertices)
    with pytest.raises(ValueError, match="out of range for 3 vertices"):
        RayCaster(mesh.triangles, mesh.vertices[:3])
    caster = RayCaster(mesh.triangles, mesh.vertices)
    with pytest.raises(ValueError, match=r"expected \(468, 3\) vertices, got \(467, 3\)"):
        caster.update(mesh.vertices[:-1])
    with pytest.raises(ValueError, match=r"expected image points as \(r, 2\)"):
        orthographic_rays(turned(0, 0, 0), np.zeros((3, 3)))


def test_pose_from_2d_points_of_the_clip() -> None:
    """Every 10th pose of the bundled clip from its pose markers' exact 2D positions."""
    truth = np.load(TRUTH)
    person = truth["person_vertices"]
    pose_vertices = truth["marker_vertices"][truth["marker_roles"] == "pose"]
    previous = None
    for f in range(0, 300, 10):
        true = Pose(truth["rotation"][f], truth["scale"][f], truth["translation"][f])
        xy = true.apply(person[pose_vertices])[:, :2]
        for start in (None, previous):
            got = estimate_pose_2d(person[pose_vertices], xy, initial=start)
            np.testing.assert_allclose(got.rotation, true.rotation, atol=1e-6)
            assert got.scale == pytest.approx(true.scale, rel=1e-6)
            np.testing.assert_allclose(got.translation[:2], true.translation[:2], atol=1e-5)
        previous = got


def test_pose_from_three_points_needs_a_start(mesh: FaceMesh) -> None:
    true = turned(12, -8, 5)
    model = mesh.vertices[[1, 33, 263]]
    xy = true.apply(model)[:, :2]
    with pytest.raises(ValueError, match="need 4 not in one plane, or a start pose"):
        estimate_pose_2d(model, xy)
    # From a nearby start three points give the pose back.
    near = turned(10, -6, 3)
    got = estimate_pose_2d(model, xy, initial=near)
    np.testing.assert_allclose(got.apply(model)[:, :2], xy, atol=1e-6)
    with pytest.raises(ValueError, match="need at least 3 weighted points, got 2"):
        estimate_pose_2d(model, xy, weights=np.array([1.0, 1.0, 0.0]), initial=near)
    with pytest.raises(ValueError, match=r"expected image points as \(3, 2\)"):
        estimate_pose_2d(model, xy[:2], initial=near)
