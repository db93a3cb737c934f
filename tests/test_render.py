"""Offscreen face renderer: pixel alignment, texture orientation, compositing (real EGL)."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from imaging import H, W, gradient_background, save

from facewire.receiver.render import FaceRenderer

T = 512


def smooth_texture(size: int = T) -> np.ndarray:
    """BGR texture whose colour is a smooth, unique-ish function of (u, v).

    R grows with u (left to right), G with v (top to bottom), B is a slow wave: a flipped
    or mirrored UV convention shows up as wrong colours at known vertices.
    """
    u, v = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    tex = np.empty((size, size, 3), np.uint8)
    tex[..., 0] = np.round(128 + 90 * np.sin(2 * np.pi * (u + v))).astype(np.uint8)
    tex[..., 1] = np.round(20 + 215 * v).astype(np.uint8)
    tex[..., 2] = np.round(20 + 215 * u).astype(np.uint8)
    return tex


def frontal(mesh_vertices: np.ndarray, scale: float = 14.0, t=(320.0, 250.0, 500.0)) -> np.ndarray:
    """Image-space vertices of a frontal upright face: scale * diag(1, -1, -1) @ v + t."""
    return mesh_vertices * np.array([scale, -scale, -scale]) + np.asarray(t)


def sample_texture(tex: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """(n, 3) bilinear texture colours at uvs (v = 0 top), texel centres at (i + 0.5) / T."""
    s = tex.shape[0]
    mx = (uvs[:, 0] * s - 0.5).astype(np.float32)[None]
    my = (uvs[:, 1] * s - 0.5).astype(np.float32)[None]
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]


@pytest.fixture(scope="module")
def renderer(mesh):
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as r:
        yield r


def interior_vertices(mesh) -> np.ndarray:
    """Vertices not on the mesh boundary, whose neighbourhood faces the viewer."""
    t = mesh.triangles
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    boundary = np.zeros(mesh.n_vertices, bool)
    boundary[edges[counts == 1].ravel()] = True
    n = mesh.vertex_normals()
    return np.flatnonzero(~boundary & (n[:, 2] > 0.6))


def test_vertex_colours_match_texture(renderer, mesh):
    renderer.set_background(None)
    img = frontal(mesh.vertices)
    frame, mask = renderer.render(img)
    save("render_frontal.png", frame)
    idx = interior_vertices(mesh)
    assert len(idx) > 250
    cols = np.rint(img[idx, 0]).astype(int)
    rows = np.rint(img[idx, 1]).astype(int)
    assert mask[rows, cols].all()
    got = frame[rows, cols].astype(int)
    want = sample_texture(smooth_texture(), mesh.uvs[idx]).astype(int)
    err = np.abs(got - want).max(axis=1)
    # The pixel centre is up to half a pixel from the vertex, and a few vertices hide
    # behind the nose; the texture changes < 1 level per pixel of render.
    assert np.median(err) <= 2, np.median(err)
    assert np.percentile(err, 95) <= 8, np.percentile(err, 95)
    # Orientation spelled out: forehead (10) is top of the texture (low G), chin (152)
    # bottom (high G); the face's right eye corner (33) is on image left (low R).
    g_forehead = frame[int(round(img[151, 1])), int(round(img[151, 0])), 1]
    g_chin = frame[int(round(img[199, 1])), int(round(img[199, 0])), 1]
    assert g_forehead < 80 < 160 < g_chin
    r_right_eye = frame[int(round(img[33, 1])), int(round(img[33, 0])), 2]
    r_left_eye = frame[int(round(img[263, 1])), int(round(img[263, 0])), 2]
    assert r_right_eye < 100 < 160 < r_left_eye


def test_square_lands_on_exact_pixels():
    # Two triangles covering pixel centres columns 100..200 and rows 100..150 exactly.
    verts = np.array(
        [[99.5, 99.5, 0.0], [200.5, 99.5, 0.0], [200.5, 150.5, 0.0], [99.5, 150.5, 0.0]]
    )
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    tex = np.full((4, 4, 3), 200, np.uint8)
    with FaceRenderer(W, H, tris, uvs, tex) as r:
        frame, mask = r.render(verts)
    want = np.zeros((H, W), bool)
    want[100:151, 100:201] = True
    assert np.array_equal(mask, want)
    assert (frame[want] == 200).all()
    assert (frame[~want] < 200).all()


def test_texture_rows_top_to_bottom():
    # A texture whose top half is red and bottom half blue, on a quad with v = 0 at the top.
    verts = np.array([[100, 100, 0], [300, 100, 0], [300, 300, 0], [100, 300, 0]], float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32, :, 2] = 255  # top: red (BGR)
    tex[32:, :, 0] = 255  # bottom: blue
    tex[:, :8, 1] = 255  # left strip: green added
    with FaceRenderer(W, H, tris, uvs, tex) as r:
        frame, _ = r.render(verts)
    assert tuple(frame[150, 200]) == (0, 0, 255)
    assert tuple(frame[250, 200]) == (255, 0, 0)
    assert frame[150, 105, 1] == 255 and frame[150, 295, 1] == 0


def test_mask_covers_projected_hull(renderer, mesh):
    img = frontal(mesh.vertices)
    _, mask = renderer.render(img)
    hull = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.rint(img[:, :2]).astype(np.int32)), 1)
    grown = cv2.dilate(hull, np.ones((3, 3), np.uint8)).astype(bool)
    assert not (mask & ~grown).any()
    # The face outline is nearly convex, and the mesh has no holes (eyes, mouth closed).
    assert mask.sum() > 0.95 * hull.sum()


def test_translation_shifts_render(renderer, mesh):
    img = frontal(mesh.vertices)
    dx, dy = 23, -11
    a, ma = renderer.render(img)
    b, mb = renderer.render(img + [dx, dy, 0])
    shifted = np.roll(a, (dy, dx), axis=(0, 1))
    shifted_mask = np.roll(ma, (dy, dx), axis=(0, 1))
    assert np.array_equal(mb, shifted_mask)
    assert np.abs(b.astype(int) - shifted).max() <= 1
    # Depth translation does not change an orthographic render.
    c, mc = renderer.render(img + [0, 0, 1e4])
    assert np.array_equal(mc, ma) and np.abs(c.astype(int) - a).max() <= 1


def test_composite_over_background(renderer, mesh):
    bg = gradient_background()
    renderer.set_background(bg)
    try:
        frame, mask = renderer.render(frontal(mesh.vertices))
    finally:
        renderer.set_background(None)
    save("render_over_background.png", frame)
    # Where no sample is covered the background shows exactly.
    far = ~cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.array_equal(frame[far], bg[far])
    assert np.abs(frame[mask].astype(int) - bg[mask]).mean() > 30


def test_set_texture_same_and_new_size(renderer, mesh):
    img = frontal(mesh.vertices)
    try:
        renderer.set_texture(np.full((T, T, 3), (10, 200, 30), np.uint8))
        frame, mask = renderer.render(img)
        # Edge pixels are blended with the (black) background by their coverage.
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert np.abs(frame[inner].astype(int) - (10, 200, 30)).max() <= 1
        renderer.set_texture(np.full((64, 64, 3), (250, 5, 90), np.uint8))
        frame, mask = renderer.render(img)
        assert np.abs(frame[inner].astype(int) - (250, 5, 90)).max() <= 1
    finally:
        renderer.set_texture(smooth_texture())
    frame, _ = renderer.render(img)
    r = int(round(img[1, 1])), int(round(img[1, 0]))
    assert abs(int(frame[r][1]) - int(sample_texture(smooth_texture(), mesh.uvs[[1]])[0, 1])) <= 3


def test_two_renderers_in_one_process(mesh):
    img = frontal(mesh.vertices)
    tex_b = np.full((T, T, 3), 77, np.uint8)
    with (
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as a,
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, tex_b) as b,
    ):
        fa1, ma1 = a.render(img)
        fb, mb = b.render(img + [50, 0, 0])
        fa2, ma2 = a.render(img)
        fb2, _ = b.render(img + [50, 0, 0])
    assert np.array_equal(fa1, fa2) and np.array_equal(ma1, ma2)
    assert np.array_equal(fb, fb2)
    inner = cv2.erode(mb.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert (fb[inner] == 77).all()
    assert np.array_equal(np.roll(ma1, 50, axis=1), mb)


def test_a_face_drawn_is_read_from_its_own_renderer_after_others_drew(mesh):
    """The receiver draws the face, warps the surroundings while llvmpipe rasterises, then
    reads it (FaceRenderer.draw, finish): what another renderer draws in between (another
    GL context, a window of another size) changes nothing of the first's picture."""
    img = frontal(mesh.vertices)
    tex_b = np.full((T, T, 3), 77, np.uint8)
    background = gradient_background()
    with (
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as a,
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, tex_b) as b,
    ):
        alone = a.render(img, background.copy(), 6.0)
        a.draw(img)
        b.render(img * [0.5, 0.5, 1.0] + [60, 40, 0])
        later = a.finish(background.copy(), 6.0)
        with pytest.raises(RuntimeError, match="without a draw"):
            a.finish(background.copy(), 6.0)  # each draw is read once
    assert np.array_equal(alone[0], later[0]) and np.array_equal(alone[1], later[1])


def test_a_renderer_dropped_without_closing_breaks_no_other(mesh):
    """A FaceRenderer nobody closed is freed whenever the garbage collector gets to it: that
    must not end the EGL display the other renderers of the process still draw with."""
    img = frontal(mesh.vertices)
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as a:
        first, _ = a.render(img)
        dropped = FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture())
        dropped.render(img)
        del dropped
        gc.collect()
        again, _ = a.render(img + [1, 0, 0])
        again, _ = a.render(img)
    assert np.array_equal(first, again)


_CHILD = """
import json, sys
import numpy as np
from facewire.models.mesh import load_canonical
from facewire.receiver.render import FaceRenderer
m = load_canonical()
img = m.vertices * np.array([14.0, -14.0, -14.0]) + [320.0, 250.0, 500.0]
with FaceRenderer(640, 480, m.triangles, m.uvs, np.full((64, 64, 3), 90, np.uint8)) as r:
    frame, mask = r.render(img)
print(json.dumps({"mask": int(mask.sum()), "value": int(np.median(frame[mask]))}))
"""


def test_renders_in_subprocess(renderer, mesh):
    # The demo runs the receiver in a child process; no display is available there either.
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    _, mask = renderer.render(frontal(mesh.vertices))
    assert got == {"mask": int(mask.sum()), "value": 90}


def test_rejects_bad_inputs(renderer, mesh):
    with pytest.raises(ValueError, match=r"\(468, 3\) image_vertices, got \(468, 2\)"):
        renderer.render(np.zeros((468, 2)))
    with pytest.raises(ValueError, match="NaN"):
        renderer.render(np.full((468, 3), np.nan))
    with pytest.raises(ValueError, match=r"background_bgr of shape \(480, 640, 3\)"):
        renderer.set_background(np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="square texture"):
        renderer.set_texture(np.zeros((10, 20, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        renderer.set_texture(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match="out of range"):
        FaceRenderer(W, H, np.array([[0, 1, 5]]), np.zeros((3, 2)), np.zeros((4, 4, 3), np.uint8))


def test_closed_renderer_refuses(mesh):
    r = FaceRenderer(64, 48, mesh.triangles, mesh.uvs, smooth_texture(16))
    r.close()
    r.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        r.render(frontal(mesh.vertices, 1.0, (32, 24, 0)))


def test_edge_pixels_follow_the_blend_formula(mesh):
    # A flat-coloured face: after the multisample resolve an edge pixel holds K * a / 255 and
    # the background keeps (1 - a / 255) of itself. Over black the frame is K * a / 255 and
    # over white that plus 255 - a, so the two give each pixel's coverage a and the colour
    # it must have. Blending the colour by alpha a second time darkens every edge pixel to
    # K * a^2 / 255^2: a dark outline round the face.
    colour = np.array([60.0, 170.0, 230.0])
    flat = np.empty((64, 64, 3), np.uint8)
    flat[:] = colour.astype(np.uint8)
    verts = frontal(mesh.vertices)
    black, white = np.zeros((H, W, 3), np.uint8), np.full((H, W, 3), 255, np.uint8)
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, flat) as r:
        for feather in (0.0, 6.0):
            over_black = r.render(verts, black.copy(), feather_px=feather)[0].astype(float)
            over_white = r.render(verts, white.copy(), feather_px=feather)[0].astype(float)
            grey = gradient_background()
            over_grey = r.render(verts, grey.copy(), feather_px=feather)[0].astype(float)
            a = (255.0 - (over_white - over_black)).mean(axis=2)  # effective coverage
            edge = (a > 20) & (a < 235)
            assert edge.sum() > 200, (feather, edge.sum())
            want = colour[None, :] * (a[edge] / 255.0)[:, None]
            assert np.abs(over_black[edge] - want).max() <= 2.0, feather
            # And the background's share is the rest, over any background.
            mixed = over_black + grey * (1.0 - a / 255.0)[:, :, None]
            assert np.abs(over_grey[edge] - mixed[edge]).max() <= 2.0, feather


def test_a_frame_owes_nothing_to_the_frame_before(mesh):
    # Two frames through one renderer over the same background: the second is exactly what a
    # fresh renderer draws for it alone. A renderer that drew into its stored background, or
    # kept the last frame's pixels, leaves the old face burned in where the head was.
    bg = gradient_background()
    first = frontal(mesh.vertices, t=(260.0, 250.0, 500.0))
    second = frontal(mesh.vertices, scale=12.0, t=(380.0, 230.0, 500.0))
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as used:
        used.set_background(bg)
        used.render(first, feather_px=6.0)
        again, _ = used.render(second, feather_px=6.0)
        per_frame, _ = used.render(second, bg.copy(), feather_px=6.0)
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as fresh:
        fresh.set_background(bg)
        alone, mask = fresh.render(second, feather_px=6.0)
    assert np.array_equal(again, alone)
    assert np.array_equal(per_frame, alone)
    # Away from the second face (where the first one was, too) the background shows exactly.
    far = ~cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.array_equal(again[far], bg[far])


def test_the_face_drawn_in_a_large_frame_is_the_face_drawn_in_a_small_one(mesh):
    # Only the face's box is drawn, wherever it lies in the frame: a face at the bottom right
    # of a 1280x720 frame (its framebuffer there, not at the frame's corner) comes out as the
    # same face in a 640x480 frame, pixel for pixel, feathered edge and mask too.
    small_at, large_at = (320.0, 250.0, 500.0), (900.5, 470.25, 500.0)
    shift = (int(large_at[0] - small_at[0]), int(large_at[1] - small_at[1]))
    small_at = (small_at[0] + large_at[0] % 1, small_at[1] + large_at[1] % 1, small_at[2])
    large_bg = cv2.resize(gradient_background(), (1280, 720))
    small_bg = large_bg[shift[1] : shift[1] + H, shift[0] : shift[0] + W].copy()
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as small:
        want, want_mask = small.render(frontal(mesh.vertices, t=small_at), small_bg, 8.0)
    with FaceRenderer(1280, 720, mesh.triangles, mesh.uvs, smooth_texture()) as large:
        got, mask = large.render(frontal(mesh.vertices, t=large_at), large_bg.copy(), 8.0)
    part = np.s_[shift[1] : shift[1] + H, shift[0] : shift[0] + W]
    assert want_mask.sum() > 20000
    assert np.array_equal(mask[part], want_mask) and mask.sum() == want_mask.sum()
    assert np.abs(got[part].astype(int) - want).max() <= 1
    outside = np.ones(mask.shape, bool)
    outside[part] = False
    assert np.array_equal(got[outside], large_bg[outside])


def test_the_face_fades_in_over_the_feather(mesh):
    # With a feather of F pixels, a pixel d pixels inside the face's edge shows d / F of the
    # face (over black and over white alike), and all of it from F on: only that band is
    # blended, and all of it is.
    flat = np.full((64, 64, 3), 200, np.uint8)
    verts = frontal(mesh.vertices)
    feather = 10.0
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, flat) as r:
        over_black, mask = r.render(verts, np.zeros((H, W, 3), np.uint8), feather_px=feather)
        over_white, _ = r.render(verts, np.full((H, W, 3), 255, np.uint8), feather_px=feather)
    shown = 1.0 - (over_white.astype(float) - over_black).mean(axis=2) / 255.0
    inside = np.pad(mask.astype(np.uint8), 1)
    depth = cv2.distanceTransform(inside, cv2.DIST_L2, 3)[1:-1, 1:-1]
    band = (depth >= 1.0) & (depth < feather)
    assert band.sum() > 1000
    assert np.abs(shown[band] - depth[band] / feather).max() < 0.02
    assert (shown[depth >= feather] > 0.99).all()
    # The distances it blended by are kept for the edge's correction (models/edge.py).
    x, y, kept = r.depth
    assert np.array_equal(kept, depth[y : y + kept.shape[0], x : x + kept.shape[1]])
    beyond = depth.copy()
    beyond[y : y + kept.shape[0], x : x + kept.shape[1]] = 0
    assert kept.size < 0.5 * H * W and not beyond.any()  # the face's box, all of the face


def test_one_sample_a_pixel_draws_the_same_feathered_face(mesh):
    """``multisample=False`` (the decoder's: its face is feathered) draws one sample a pixel:
    no pixel half covered, where 4x multisampling has many along the outline; over the
    feather the two pictures agree, since the fade gives the outline's pixels no weight; and
    a larger face, which needs a new framebuffer, is drawn single-sampled too."""
    bg = gradient_background()
    with (
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture()) as four,
        FaceRenderer(W, H, mesh.triangles, mesh.uvs, smooth_texture(), multisample=False) as one,
    ):
        for scale in (14.0, 20.0):  # the second face needs a larger framebuffer
            verts = frontal(mesh.vertices, scale=scale)
            partly = {}
            for name, r in (("four", four), ("one", one)):
                # out = colour * a + background * (1 - a): over black and over white, a pixel
                # fully covered or not at all differs by 0 or 255, one partly covered between.
                over_black, mask = r.render(verts, np.zeros_like(bg))
                over_white, _ = r.render(verts, np.full_like(bg, 255))
                gap = (over_white.astype(int) - over_black).max(axis=2)
                partly[name] = np.count_nonzero((gap > 8) & (gap < 247))
                if name == "four":
                    mask_four = mask
                else:
                    mask_one = mask
                    save(f"render_one_sample_{scale:g}.png", over_black)
            assert partly["four"] > 300 and partly["one"] == 0, partly
            # Covered pixels, the mask: the same but for a few along the outline.
            assert np.count_nonzero(mask_four != mask_one) < 0.02 * mask_four.sum()
            soft_four, _ = four.render(verts, bg.copy(), feather_px=6.0)
            soft_one, _ = one.render(verts, bg.copy(), feather_px=6.0)
            diff = np.abs(soft_four.astype(int) - soft_one.astype(int))
            # (Where the two count an outline pixel covered differently, the fade there starts
            # a pixel over: a sixth of the face against the background, at most.)
            assert diff.max() <= 40 and diff.mean() < 0.05, (diff.max(), diff.mean())
