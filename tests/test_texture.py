"""Texture unwrap and background: round trips through the real renderer (EGL)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from imaging import H, W, gradient_background, psnr, save

from facewire.models.fill import fill_invalid
from facewire.receiver.render import FaceRenderer
from facewire.sender.texture import (
    UvRasteriser,
    face_hull_mask,
    make_background,
    scan_triangles,
    z_buffer,
)

T = 512
FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def checker_texture(size: int = T) -> np.ndarray:
    """BGR gradient with a checker on top: sharp edges show misregistration."""
    u, v = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    check = ((u * 8).astype(int) + (v * 8).astype(int)) % 2
    tex = np.empty((size, size, 3), np.uint8)
    tex[..., 0] = (40 + 160 * check).astype(np.uint8)
    tex[..., 1] = np.round(30 + 200 * v).astype(np.uint8)
    tex[..., 2] = np.round(30 + 200 * u).astype(np.uint8)
    return tex


def posed(vertices: np.ndarray, yaw_deg: float = 0.0, scale: float = 14.0, t=(320, 250, 0)):
    """Image-space vertices: scale * diag(1, -1, -1) @ R_y(yaw) @ v + t."""
    a = np.deg2rad(yaw_deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    r = np.diag([1.0, -1.0, -1.0]) @ ry
    return scale * vertices @ r.T + np.asarray(t, float)


@pytest.fixture(scope="module")
def rasteriser(mesh):
    return UvRasteriser(mesh.triangles, mesh.uvs, T)


@pytest.fixture(scope="module")
def renderer(mesh):
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, checker_texture()) as r:
        yield r


def test_rasteriser_barycentrics_reproduce_texel_centres(rasteriser, mesh):
    cov = rasteriser.covered
    # The canonical UV layout covers a face-shaped two thirds of the square.
    assert 0.55 < cov.mean() < 0.75
    rows, cols = np.nonzero(cov)
    tri = rasteriser.triangle[rows, cols]
    b = rasteriser.bary[rows, cols].astype(np.float64)
    assert (b >= -1e-5).all() and np.allclose(b.sum(axis=1), 1.0, atol=1e-5)
    corners = mesh.uvs[mesh.triangles[tri]] * T - 0.5  # (k, 3, 2) texel coordinates
    p = np.einsum("kj,kjd->kd", b, corners)
    assert np.abs(p[:, 0] - cols).max() < 1e-3
    assert np.abs(p[:, 1] - rows).max() < 1e-3
    # Uncovered: outside the UV triangles, e.g. the corners of the square.
    assert not cov[0, 0] and not cov[-1, -1] and rasteriser.triangle[0, 0] == -1


def test_scan_triangles_covers_exact_centres():
    tri = np.array([[[1.5, 1.5], [5.5, 1.5], [5.5, 3.5]], [[1.5, 1.5], [5.5, 3.5], [1.5, 3.5]]])
    t, px, py, bary = scan_triangles(tri, 10, 10)
    cells = set(zip(px.tolist(), py.tolist(), strict=True))
    assert cells == {(x, y) for x in range(2, 6) for y in range(2, 4)}
    assert np.allclose(bary.sum(axis=1), 1.0)
    assert len(scan_triangles(np.zeros((1, 3, 2)), 10, 10)[0]) == 0  # degenerate


def test_z_buffer_keeps_nearest_surface():
    # Two overlapping squares, the second nearer (smaller z) on the right half only.
    v = np.array(
        [[0, 0, 10], [9, 0, 10], [9, 9, 10], [0, 9, 10]]
        + [[5, 0, 2], [9, 0, 2], [9, 9, 2], [5, 9, 2]],
        float,
    )
    tris = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    z = z_buffer(v, tris, 12, 12)
    assert z[4, 2] == 10 and z[4, 7] == 2 and np.isinf(z[11, 11])


def test_unwrap_frontal_recovers_texture(renderer, rasteriser, mesh):
    tex = checker_texture()
    img = posed(mesh.vertices)
    frame, _ = renderer.render(img)
    got, valid = rasteriser.unwrap(frame, img)
    save("unwrap_frontal.png", np.hstack([tex, got, cv2.cvtColor(valid * np.uint8(255), 8)]))
    assert got.shape == (T, T, 3) and valid.shape == (T, T)
    assert valid.sum() > 0.9 * rasteriser.covered.sum()
    assert not (valid & ~rasteriser.covered).any()
    # The face spans ~240 px for 512 texels, so a texel is resampled from a coarser
    # image: compare away from the checker edges, where the resampling blur shows.
    edges = cv2.Canny(tex, 30, 90) > 0
    far = valid & ~cv2.dilate(edges.astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    err = np.abs(got[far].astype(int) - tex[far]).max(axis=1)
    assert np.median(err) <= 2 and np.percentile(err, 99) <= 8


@pytest.mark.parametrize("yaw", [0.0, 30.0])
def test_unwrap_then_render_reproduces_frame(renderer, rasteriser, mesh, yaw):
    renderer.set_background(gradient_background())
    renderer.set_texture(checker_texture())
    img = posed(mesh.vertices, yaw)
    first, mask = renderer.render(img)
    tex, _ = rasteriser.unwrap(first, img)
    renderer.set_texture(tex)
    second, mask2 = renderer.render(img)
    renderer.set_texture(checker_texture())
    renderer.set_background(None)
    save(f"roundtrip_yaw{int(yaw)}.png", np.hstack([first, second]))
    assert np.array_equal(mask, mask2)
    assert psnr(first[mask], second[mask]) > 30


def test_turned_face_marks_far_side_and_occlusion_invalid(renderer, rasteriser, mesh):
    img = posed(mesh.vertices, 50.0)
    frame, _ = renderer.render(img)
    tex, valid = rasteriser.unwrap(frame, img)
    save("unwrap_yaw50.png", np.hstack([tex, cv2.cvtColor(valid * np.uint8(255), 8)]))
    cov = rasteriser.covered
    # Turned by +50 degrees about y the face's left side (texture right, u > 0.5) moves
    # away from the camera; its outer cheek cannot be seen.
    right = cov.copy()
    right[:, : int(0.8 * T)] = False
    left = cov.copy()
    left[:, int(0.2 * T) :] = False
    assert valid[right].mean() < 0.3 and valid[left].mean() > 0.9
    # Every texel is filled: nothing black, even where invalid (the seam fill).
    assert tex.reshape(-1, 3).sum(axis=1).min() > 60


def test_what_the_nose_hides_is_found_on_a_smaller_picture_too(mesh):
    """The test for texels behind another part of the face, made on the face scaled down (a
    coarse texture needs no finer one: the occlusion finder's 64 texels on a 400-px face took
    60 ms a measurement at full size) finds what the nose and cheek hide at a 45-degree turn
    as at full size, but for a rim of the outline a few pixels wider."""
    small = UvRasteriser(mesh.triangles, mesh.uvs, 64)
    img = posed(mesh.vertices, 45.0, scale=30.0, t=(640, 480, 0))  # a face 400 px wide
    frame = np.zeros((960, 1280, 3), np.uint8)
    _, full = small.sample(frame, img, 0.15)
    _, scaled = small.sample(frame, img, 0.15, hidden_scale=128 / float(np.ptp(img[:, 0])))
    _, facing_only = small.sample(frame, img, 0.15, hidden=False)
    hidden = facing_only & ~full  # what the full-size test finds hidden
    assert hidden.sum() > 40
    assert (scaled[hidden] == 0).mean() > 0.9  # found hidden on the smaller picture too
    assert (scaled & ~full).sum() < 0.02 * full.sum()
    assert (full & ~scaled).sum() < 0.1 * full.sum()  # the wider rim, and little else


def test_texels_outside_frame_are_invalid(renderer, rasteriser, mesh):
    img = posed(mesh.vertices, t=(20, 250, 0))  # right half of the face off the left edge
    frame, _ = renderer.render(img)
    _, valid = rasteriser.unwrap(frame, img)
    # Image left = face's right = texture left.
    assert valid[:, : int(0.3 * T)].sum() == 0
    assert valid[:, int(0.6 * T) :].sum() > 0


def test_fill_invalid_keeps_valid_and_interpolates_holes():
    img = np.zeros((64, 64, 3), np.uint8)
    img[:, :32] = (10, 20, 30)
    img[:, 32:] = (210, 220, 230)
    valid = np.ones((64, 64), bool)
    valid[20:40, 20:44] = False
    damaged = img.copy()
    damaged[~valid] = 0
    out = fill_invalid(damaged, valid)
    assert np.array_equal(out[valid], img[valid])
    hole = out[~valid].astype(int)
    assert (hole >= (10, 20, 30)).all() and (hole <= (210, 220, 230)).all()
    # Left edge of the hole resembles its left neighbours, right edge its right ones.
    assert out[30, 20, 0] < 110 < out[30, 43, 0]
    assert np.array_equal(fill_invalid(img, np.ones((64, 64), bool)), img)
    with pytest.raises(ValueError, match=r"valid of shape \(64, 64\)"):
        fill_invalid(img, np.ones((8, 8), bool))


def test_background_removes_face(renderer, mesh):
    bg = gradient_background()
    renderer.set_background(bg)
    img = posed(mesh.vertices, 20.0)
    frame, mask = renderer.render(img)
    renderer.set_background(None)
    clean = make_background(frame, img, mesh.triangles)
    save("background.png", np.hstack([frame, clean]))
    hull = face_hull_mask((H, W), img, mesh.triangles)
    assert mask[hull].mean() > 0.9
    # Inside the hull the face is gone: close to the true background, far from the face.
    err = np.abs(clean[hull].astype(int) - bg[hull]).max(axis=1)
    assert np.median(err) <= 6 and np.percentile(err, 95) <= 20
    assert np.abs(frame[hull].astype(int) - bg[hull]).max(axis=1).mean() > 40
    # Away from the (dilated) face the frame is untouched.
    far = ~face_hull_mask((H, W), img, mesh.triangles, dilate=60)
    assert np.array_equal(clean[far], frame[far])


def test_rejects_bad_inputs(rasteriser):
    with pytest.raises(ValueError, match=r"\(468, 3\) image_vertices, got \(468, 2\)"):
        rasteriser.unwrap(np.zeros((H, W, 3), np.uint8), np.zeros((468, 2)))
    with pytest.raises(ValueError, match="uint8"):
        rasteriser.unwrap(np.zeros((H, W), np.uint8), np.zeros((468, 3)))
    with pytest.raises(ValueError, match=r"\(n, 2\) uvs"):
        UvRasteriser(np.array([[0, 1, 2]]), np.zeros((3, 3)))


def test_real_face_round_trip(rasteriser, mesh):
    landmarks = pytest.importorskip(
        "facewire.sender.landmarks", reason="landmark tracker not landed"
    )
    face = cv2.imread(str(FIXTURE))
    if face is None:
        pytest.skip(f"fixture {FIXTURE} missing")
    tracker = landmarks.LandmarkTracker()
    tracker.track(face)
    lm = tracker.track(face)  # second frame: the tracker's own crop
    assert lm is not None
    pts = lm.points
    h, w = face.shape[:2]
    tex, valid = rasteriser.unwrap(face, pts)
    bg = make_background(face, pts, mesh.triangles)
    with FaceRenderer(w, h, mesh.triangles, mesh.uvs, tex, bg) as r:
        out, mask = r.render(pts)
    save("real_face.png", np.hstack([face, out, bg]))
    save("real_face_texture.png", np.hstack([tex, cv2.cvtColor(valid * np.uint8(255), 8)]))
    # Small face (one pixel is ~5 texels): the hidden 1-px outline rim costs a lot.
    assert valid.sum() > 0.7 * rasteriser.covered.sum()
    assert mask.sum() > 0.03 * h * w  # the face is ~90 px wide in a 420 px photo
    # The face re-rendered from its own unwrapped texture matches the photo.
    assert psnr(out[mask], face[mask]) > 28
    # Its eyes stay where they were: the rendered texture is not flipped.
    hull = face_hull_mask((h, w), pts, mesh.triangles)
    assert psnr(out[hull & mask], face[hull & mask]) > 28
