"""Offscreen rendering of the textured face mesh, pixel-aligned with the input frame.

This is the only module that imports pyrender / OpenGL. It defaults to EGL so it runs
with no display (Mesa llvmpipe on CPU-only machines).

Frames: the renderer takes vertices in *image space* (pixels, x right, y down, z away from
the camera, same scale as x) and draws them with an orthographic camera so that a vertex
at image (x, y) lands exactly on pixel (column x, row y), pixel centres at integer
coordinates (the OpenCV convention).
"""

from __future__ import annotations

import ctypes
import logging
import os
import threading
import weakref
from types import TracebackType

import cv2
import numpy as np

# pyrender picks its GL platform at import time; EGL needs no display.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# pyrender 0.1.45 still uses np.infty, which numpy 2 removed.
if not hasattr(np, "infty"):
    setattr(np, "infty", np.inf)  # noqa: B010

import pyrender  # noqa: E402
from OpenGL import GL  # noqa: E402

logger = logging.getLogger(__name__)

_FLOAT_SIZE = 4
# Live renderers in this process. pyrender's EGL platform calls eglTerminate on the shared
# default display when one renderer is deleted, which breaks every other renderer; we only
# let the last one terminate it.
_live_lock = threading.Lock()
_live_count = 0


def _release(renderer: pyrender.OffscreenRenderer) -> None:
    """Free one renderer's GL objects and context; only the process's last live renderer
    ends the shared EGL display. Called once per renderer, by close() or when a FaceRenderer
    nobody closed is collected (pyrender's own __del__ would end the display for all)."""
    global _live_count
    with _live_lock:
        _live_count -= 1
        last = _live_count == 0
        platform = renderer._platform
        egl_display = getattr(platform, "_egl_display", None)
        if last or egl_display is None:
            renderer.delete()
            return
        # Free this context's GL objects and the context, but keep the display.
        from OpenGL.EGL import eglDestroyContext

        platform.make_current()
        renderer._renderer.delete()
        eglDestroyContext(egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None


# Camera distance in front of the nearest vertex, in pixels (image-space z units).
_NEAR_MARGIN = 16.0
# The framebuffer covers the face's box, its sides rounded up to this many pixels.
_VIEWPORT_STEP = 64


def _check_uint8_image(name: str, img: np.ndarray, shape: tuple[int, ...] | None) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected {name} (h, w, 3) uint8, got {img.shape} {img.dtype}")
    if shape is not None and img.shape != shape:
        raise ValueError(f"expected {name} of shape {shape}, got {img.shape}")
    return img


def _check_square_texture(texture_bgr: np.ndarray) -> np.ndarray:
    tex = _check_uint8_image("texture_bgr", texture_bgr, None)
    if tex.shape[0] != tex.shape[1]:
        raise ValueError(f"expected a square texture (T, T, 3), got {tex.shape}")
    return tex


class FaceRenderer:
    """Renders a textured triangle mesh given in image space, over a background.

    width, height : output size in pixels
    triangles : (m, 3) int, vertex indices
    uvs : (n, 2) float, texture coordinates in [0, 1]; u to the right and v = 0 at the
        TOP row of the texture image (image convention, as the canonical mesh's UVs are in
        practice)
    texture_bgr : (T, T, 3) uint8, BGR texture image
    background_bgr : (height, width, 3) uint8 or None (black)

    Shading is unlit (the texture comes from video and already holds the lighting), the
    surface is double-sided and the texture is sampled bilinearly without mipmaps. The edge
    of the face is antialiased (4x multisampling) and blended with the background; with
    ``multisample=False`` one sample a pixel is drawn, for a caller that feathers the face
    (:meth:`render`'s ``feather_px``): the feather gives the outline's pixels no weight (the
    fade starts inside them), and at a 400 px face 4x samples took 3.4 ms more a frame on
    llvmpipe. (The lips' edge over the mouth's inside, the one edge left, scored as well:
    docs/what-we-tried.md, "Real time at camera sizes".)

    Vertex positions are re-uploaded into the existing GL vertex buffer each frame
    (``glBufferData``, which orphans the old storage instead of waiting for it), rather than
    rebuilding the pyrender mesh: 220 against 195 fps at 468 vertices, equal at 7,257
    (benchmarks/bench_render.py).

    Only the face's box is drawn: the framebuffer is the size of that box (rounded up), not
    of the frame, so the work grows with the face's area. At 1280x720 the whole frame cost
    4-10 ms more a frame on llvmpipe, loaded (clearing and resolving 4x-multisampled pixels
    that the face never covers).

    Each renderer owns its own EGL context, so several can live in one process; use one
    renderer from the thread that made it.
    """

    def __init__(
        self,
        width: int,
        height: int,
        triangles: np.ndarray,
        uvs: np.ndarray,
        texture_bgr: np.ndarray,
        background_bgr: np.ndarray | None = None,
        multisample: bool = True,
    ) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"expected a positive size, got {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        self.multisample = multisample
        tris = np.asarray(triangles)
        if tris.ndim != 2 or tris.shape[1] != 3 or not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"expected (m, 3) int triangles, got {tris.shape} {tris.dtype}")
        uv = np.asarray(uvs, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"expected (n, 2) uvs, got {uv.shape}")
        if tris.size and (tris.min() < 0 or tris.max() >= len(uv)):
            raise ValueError(f"triangle index out of range 0..{len(uv) - 1}")
        self.n_vertices = len(uv)
        self._triangles = tris.astype(np.int64)
        # pyrender flips the texture image on upload (GL t = 0 is the image's bottom row),
        # so image-convention v becomes t = 1 - v.
        self._texcoords = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)
        self._interleaved = np.zeros((self.n_vertices, 5), dtype=np.float32)
        self._interleaved[:, 3:] = self._texcoords

        self._background: np.ndarray | None = None
        self.set_background(background_bgr)

        tex = _check_square_texture(texture_bgr)
        self._texture = self._make_texture(tex)
        self._material = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=[1.0, 1.0, 1.0, 1.0],
            baseColorTexture=self._texture,
            doubleSided=True,
        )
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[1.0, 1.0, 1.0])
        self._primitive = self._make_primitive(np.zeros((self.n_vertices, 3), dtype=np.float32))
        self._mesh_node = self._scene.add(pyrender.Mesh([self._primitive]))
        # Orthographic: one world unit = one pixel; xmag/ymag are half the view size.
        self._camera = pyrender.OrthographicCamera(xmag=1.0, ymag=1.0, znear=1.0, zfar=100.0)
        self._camera_node = self._scene.add(self._camera, pose=np.eye(4))
        self._viewport = (0, 0)  # the framebuffer's size: made at the first render
        self._renderer: pyrender.OffscreenRenderer | None = pyrender.OffscreenRenderer(
            _VIEWPORT_STEP, _VIEWPORT_STEP
        )
        global _live_count
        with _live_lock:
            _live_count += 1
        # Runs _release once: at close(), or when this object is collected unclosed.
        self._release = weakref.finalize(self, _release, self._renderer)
        # pyrender reads back and linearises depth for every frame; the mask comes from
        # alpha, so read colour only, and only the face's bounding box: resolving the
        # multisampled frame and reading it back cost 6 ms at 640x480 on llvmpipe (pyrender is
        # pinned to 0.1.45, whose private Renderer._read_main_framebuffer(scene, flags) this
        # replaces for this instance).
        inner = self._renderer._renderer
        self._window = (0, 0, 0, 0)  # x0, y0, x1, y1 drawn and read back, frame pixels
        #: The last frame's distance of each pixel to the face's edge, in a box whose corner
        #: is the frame's pixel (x, y): (x, y, distances); None without a feathered face. The
        #: edge's correction keeps the face's inside by it (models/edge.py).
        self.depth: tuple[int, int, np.ndarray] | None = None

        self._inner = inner
        self._drawn_window: tuple[int, int, int, int] | None = None  # drawn, not read yet

        def read(scene: object, flags: int) -> tuple[None, None]:
            # Not now: pyrender has flushed the drawing, and llvmpipe rasterises it on its own
            # threads while the caller does other work; :meth:`finish` reads it.
            return None, None

        inner._read_main_framebuffer = read
        if not multisample:
            configure = inner._configure_main_framebuffer

            def configure_single_sample() -> None:
                made = (inner._main_fb_ms, inner._main_fb_dims)
                configure()
                # New buffers for a new size (GL may reuse the old ones' names): one sample each.
                if (inner._main_fb_ms, inner._main_fb_dims) != made:
                    width, height = inner._main_fb_dims
                    for buffer, kind in (
                        (inner._main_cb_ms, GL.GL_RGBA),
                        (inner._main_db_ms, GL.GL_DEPTH_COMPONENT24),
                    ):
                        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
                        GL.glRenderbufferStorageMultisample(
                            GL.GL_RENDERBUFFER, 0, kind, width, height
                        )

            inner._configure_main_framebuffer = configure_single_sample
        self._uploaded = False  # GL buffers exist only after the first render
        self._flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.RGBA
        logger.debug(
            "FaceRenderer %dx%d, %d vertices, %d triangles, texture %s",
            self.width,
            self.height,
            self.n_vertices,
            len(self._triangles),
            tex.shape,
        )

    # -- scene pieces -------------------------------------------------------------------

    @staticmethod
    def _make_texture(texture_bgr: np.ndarray) -> pyrender.Texture:
        # Unlit flat shading passes texels through unchanged, so the BGR bytes can go in
        # as they are and come back out as BGR.
        sampler = pyrender.Sampler(
            magFilter=GL.GL_LINEAR,
            minFilter=GL.GL_LINEAR,
            wrapS=GL.GL_CLAMP_TO_EDGE,
            wrapT=GL.GL_CLAMP_TO_EDGE,
        )
        return pyrender.Texture(
            source=np.ascontiguousarray(texture_bgr), source_channels="RGB", sampler=sampler
        )

    def _make_primitive(self, gl_positions: np.ndarray) -> pyrender.Primitive:
        return pyrender.Primitive(
            positions=gl_positions,
            texcoord_0=self._texcoords,
            indices=self._triangles,
            material=self._material,
            mode=pyrender.constants.GLTF.TRIANGLES,
        )

    # -- public API ---------------------------------------------------------------------

    def set_background(self, background_bgr: np.ndarray | None) -> None:
        """Background to composite over: (height, width, 3) uint8 BGR, or None for black."""
        if background_bgr is None:
            self._background = None
            return
        bg = _check_uint8_image("background_bgr", background_bgr, (self.height, self.width, 3))
        self._background = bg.copy()

    def set_texture(self, texture_bgr: np.ndarray) -> None:
        """Replace the face texture: (T, T, 3) uint8 BGR, v = 0 at the top row.

        A texture of the same size is re-uploaded in place (cheap enough per frame for
        live eye patches); a new size replaces the GL texture.
        """
        tex = _check_square_texture(texture_bgr)
        same_size = tex.shape == self._texture.source.shape
        if self._uploaded and same_size and self._texture._texid is not None:
            self._texture.source = np.ascontiguousarray(tex)
            self._make_current()
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._texture._texid)
            GL.glTexSubImage2D(
                GL.GL_TEXTURE_2D,
                0,
                0,
                0,
                tex.shape[1],
                tex.shape[0],
                GL.GL_RGB,
                GL.GL_UNSIGNED_BYTE,
                np.ascontiguousarray(tex[::-1]),
            )
            GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
            return
        # pyrender notices the new texture object at the next render, uploads it and
        # frees the old one.
        self._texture = self._make_texture(tex)
        self._material.baseColorTexture = self._texture

    def render(
        self,
        image_vertices: np.ndarray,
        background_bgr: np.ndarray | None = None,
        feather_px: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Draw the mesh at ``image_vertices`` and composite it over the background: a
        :meth:`draw` and its :meth:`finish` at once.

        image_vertices : (n, 3) float, image space (pixels, x right, y down, z away from
            the camera)
        background_bgr : (height, width, 3) uint8 for this frame only, drawn into (not
            copied); default: the one from :meth:`set_background`
        feather_px : the face fades into the background over this many pixels inside its
            edge (0: a hard, antialiased edge)
        returns frame_bgr (height, width, 3) uint8 and mask (height, width) bool, True where
            the face covers the pixel centre (more than half of the multisample coverage).
        """
        self.draw(image_vertices)
        return self.finish(background_bgr, feather_px)

    def draw(self, image_vertices: np.ndarray) -> None:
        """Start drawing the mesh at ``image_vertices`` (as :meth:`render`): the rasterising
        goes on in llvmpipe's threads until :meth:`finish` reads it back, so the caller's work
        in between (the surroundings' warp) costs the frame nothing more; at 1280x720 the
        read then waited 0.05 ms instead of 1.6."""
        if self._renderer is None:
            raise RuntimeError("FaceRenderer is closed")
        v = np.asarray(image_vertices, dtype=np.float64)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"expected ({self.n_vertices}, 3) image_vertices, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("image_vertices contain NaN or infinite values")

        # Image (x, y, z) -> GL world (x, -y, -z): a rotation by 180 degrees about x.
        gl = np.empty((self.n_vertices, 3), dtype=np.float32)
        gl[:, 0] = v[:, 0]
        gl[:, 1] = -v[:, 1]
        gl[:, 2] = -v[:, 2]
        # Nothing is drawn outside the vertices' bounding box (plus the antialiased edge).
        lo = np.floor(v[:, :2].min(axis=0)) - 2
        hi = np.ceil(v[:, :2].max(axis=0)) + 3
        x0, y0 = (int(np.clip(c, 0, n)) for c, n in zip(lo, (self.width, self.height), strict=True))
        x1, y1 = (int(np.clip(c, 0, n)) for c, n in zip(hi, (self.width, self.height), strict=True))
        self._window = (x0, y0, max(x0, x1), max(y0, y1))
        self._fit_viewport(max(x1 - x0, 1), max(y1 - y0, 1))
        self._place_camera(float(v[:, 2].min()), float(v[:, 2].max()))
        self._set_positions(gl)

        self._renderer.render(self._scene, flags=self._flags)
        self._uploaded = True
        self._drawn_window = self._window

    def finish(
        self, background_bgr: np.ndarray | None = None, feather_px: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """The face of the last :meth:`draw` read back and composited over the background
        (the arguments and the result as :meth:`render`'s)."""
        if self._renderer is None:
            raise RuntimeError("FaceRenderer is closed")
        if self._drawn_window is None:
            raise RuntimeError("FaceRenderer.finish without a draw to finish")
        self._window, self._drawn_window = self._drawn_window, None
        self._make_current()
        rgba = self._read_rgba(self._inner)
        background: np.ndarray | None
        if background_bgr is not None:
            shape = (self.height, self.width, 3)
            background = _check_uint8_image("background_bgr", background_bgr, shape)
        else:
            background = None if self._background is None else self._background.copy()
        return self._composite(rgba, background, feather_px)

    def close(self) -> None:
        """Free the GL context; the renderer cannot be used afterwards."""
        if self._renderer is None:
            return
        self._renderer = None
        self._release()

    def __enter__(self) -> FaceRenderer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------

    def _make_current(self) -> None:
        assert self._renderer is not None
        self._renderer._platform.make_current()

    def _fit_viewport(self, width: int, height: int) -> None:
        """A framebuffer that holds a ``width`` x ``height`` box, its sides rounded up to
        _VIEWPORT_STEP: a frame's picture depends on its own box alone (the projection
        differs in the last bits with the framebuffer's size). Making a new one costs nothing
        measurable on llvmpipe."""
        vw = -(-width // _VIEWPORT_STEP) * _VIEWPORT_STEP
        vh = -(-height // _VIEWPORT_STEP) * _VIEWPORT_STEP
        if (vw, vh) == self._viewport:
            return
        self._viewport = (vw, vh)
        assert self._renderer is not None
        self._renderer.viewport_width, self._renderer.viewport_height = vw, vh
        self._camera.xmag, self._camera.ymag = vw / 2.0, vh / 2.0

    def _read_rgba(self, inner: pyrender.Renderer) -> np.ndarray:
        """Resolve the multisampled framebuffer (its top left corner is the frame's pixel
        ``self._window``[:2]), or take the single-sampled one as it is, and read the window:
        (y1 - y0, x1 - x0, 4) uint8, top row first."""
        x0, y0, x1, y1 = self._window
        if x1 <= x0 or y1 <= y0:
            return np.zeros((max(y1 - y0, 0), max(x1 - x0, 0), 4), np.uint8)
        _, height = inner._main_fb_dims
        w, h = x1 - x0, y1 - y0
        gy0 = height - h  # GL rows start at the bottom
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, inner._main_fb_ms)
        if self.multisample:
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, inner._main_fb)
            GL.glBlitFramebuffer(
                0, gy0, w, height, 0, gy0, w, height, GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR
            )
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, inner._main_fb)
        buf = GL.glReadPixels(0, gy0, w, h, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
        rgba = np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 4)
        return rgba[::-1]

    def _place_camera(self, z_min: float, z_max: float) -> None:
        # The framebuffer's (vw x vh) top left pixel is the frame's (x0, y0). GL window
        # x = X - cx + vw/2 must equal x - x0 + 0.5 (pixel centre), so cx = x0 + vw/2 - 0.5;
        # likewise for the flipped rows (window y = vh - (y - y0) - 0.5 from the bottom),
        # cy = -(y0 + vh/2 - 0.5). The camera sits _NEAR_MARGIN in front of the nearest
        # vertex and the far plane just behind the farthest one, so the depth range always
        # fits the data whatever the pose's translation in z.
        x0, y0 = self._window[:2]
        vw, vh = self._viewport
        pose = np.eye(4)
        pose[0, 3] = x0 + vw / 2.0 - 0.5
        pose[1, 3] = -(y0 + vh / 2.0 - 0.5)
        pose[2, 3] = -z_min + _NEAR_MARGIN
        self._scene.set_pose(self._camera_node, pose)
        self._camera.znear = _NEAR_MARGIN / 2.0
        self._camera.zfar = (z_max - z_min) + 2.0 * _NEAR_MARGIN

    def _set_positions(self, gl_positions: np.ndarray) -> None:
        prim = self._primitive
        if not self._uploaded or prim._vaid is None:
            prim.positions = gl_positions
            return
        # Same layout pyrender created: interleaved float32 [x y z u v] per vertex, in the
        # first buffer of the primitive (no normals, tangents or colours).
        prim._positions = gl_positions  # keeps pyrender's CPU copy consistent, no bounds
        prim._bounds = None
        self._interleaved[:, :3] = gl_positions
        self._make_current()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, prim._buffers[0])
        GL.glBufferData(
            GL.GL_ARRAY_BUFFER,
            self._interleaved.nbytes,
            ctypes.c_void_p(self._interleaved.ctypes.data),
            GL.GL_DYNAMIC_DRAW,
        )
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def _composite(
        self, rgba: np.ndarray, background: np.ndarray | None, feather_px: float
    ) -> tuple[np.ndarray, np.ndarray]:
        # Cleared to transparent black, so after the multisample resolve the colour is
        # premultiplied by coverage: out = colour + background * (1 - alpha). ``rgba`` is the
        # window read back (``self._window``); only the face's bounding box needs blending.
        x0, y0, x1, y1 = self._window
        self.depth = None
        mask = np.zeros((self.height, self.width), bool)
        mask[y0:y1, x0:x1] = rgba[:, :, 3] > 127
        out = np.zeros((self.height, self.width, 3), np.uint8) if background is None else background
        alpha = rgba[:, :, 3]
        rows = np.flatnonzero(alpha.any(axis=1))
        if len(rows) == 0:
            return out, mask
        cols = np.flatnonzero(alpha[rows[0] : rows[-1] + 1].any(axis=0))
        inner = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]  # in the window
        box = np.s_[y0 + rows[0] : y0 + rows[-1] + 1, x0 + cols[0] : x0 + cols[-1] + 1]
        color = rgba[inner][:, :, :3]
        alpha = alpha[inner]
        if background is None:
            out[box] = color
            return out, mask
        if feather_px > 0:
            # Weight by the distance to the face's edge: a pixel d inside it shows d / feather
            # of the face, all of it from the feather on, and outside it the background; the
            # colour is premultiplied by alpha, so both scale together. Integer multiplies of
            # the whole box by weights in 255ths: indexing the band's pixels cost 3-4 ms on a
            # 400-px face, cv2.blendLinear's float weights 1-2.
            inside = cv2.copyMakeBorder(
                (alpha > 127).view(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0
            )
            distance = cv2.distanceTransform(inside, cv2.DIST_L2, 3)[1:-1, 1:-1]
            self.depth = (x0 + int(cols[0]), y0 + int(rows[0]), distance)
            weight = cv2.convertScaleAbs(distance, alpha=255.0 / feather_px)  # rounded, <= 255
            alpha = np.ascontiguousarray(alpha)
            face = cv2.multiply(np.ascontiguousarray(color), cv2.merge([weight] * 3), scale=1 / 255)
            behind = cv2.bitwise_not(cv2.multiply(alpha, weight, scale=1 / 255))
            under = cv2.multiply(out[box], cv2.merge([behind] * 3), scale=1 / 255)
            cv2.add(face, under, dst=out[box])
            return out, mask
        keep = (255 - alpha).astype(np.uint16)[:, :, None]
        blended = color + ((out[box] * keep + 127) // 255).astype(np.uint8)
        out[box] = blended
        return out, mask
