"""The call in a window on this machine's display (pyglet, which pyrender already brings).

:class:`Window` is a frame sink (receiver.session.FrameSink): the receive loop hands it each
picture and goes on; the window's own thread (with its own OpenGL context, apart from the
renderer's offscreen EGL one) draws the newest picture, scaled to the window, and handles the
window's events. Closing the window sets :attr:`Window.closed`: the caller ends the call.

Where there is no display (no ``DISPLAY``, or an X server that does not answer), the
constructor raises :class:`NoDisplay` with one line saying so.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import sys
import threading
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

#: The window's first size, until the first picture gives it the call's.
FIRST_SIZE = (640, 480)
#: How often the window's events are looked at while no new picture comes (s).
IDLE_S = 1 / 60
START_TIMEOUT_S = 10.0


class NoDisplay(RuntimeError):
    """No display to open a window on."""


def display_problem() -> str | None:
    """Why no window can be opened here (None: try it). Only X11 is looked at: pyglet draws
    through it on Linux (under Wayland, through XWayland's ``DISPLAY``)."""
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        return "no display (DISPLAY is not set)"
    return None


class Window:
    """A window titled ``title`` showing the newest picture; :meth:`close` to remove it."""

    def __init__(self, title: str = "facewire") -> None:
        problem = display_problem()
        if problem is not None:
            raise NoDisplay(f"cannot open a window: {problem}")
        self.closed = False  # the person watching closed it
        self.shown = 0  # pictures drawn
        self._title = title
        self._lock = threading.Lock()
        self._image: np.ndarray | None = None
        self._version = 0
        self._new = threading.Event()
        self._stopping = False
        started: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(
            target=self._run, args=(started,), name="window", daemon=True
        )
        self._thread.start()
        try:
            started.result(timeout=START_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            self.close()
            raise NoDisplay("cannot open a window: the display did not answer") from None

    def __call__(self, frame: Any, report: Any) -> None:
        """FrameSink: keeps a reference to the newest picture for the window's thread."""
        with self._lock:
            self._image = frame.image
            self._version += 1
        self._new.set()

    def close(self) -> None:
        self._stopping = True
        self._new.set()
        self._thread.join(timeout=START_TIMEOUT_S)

    def __enter__(self) -> Window:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self, started: concurrent.futures.Future[None]) -> None:
        try:
            window = self._open()
        except Exception as exc:  # no such display, no GLX, ...: one line for the caller
            logger.debug("window failed", exc_info=True)
            started.set_exception(NoDisplay(f"cannot open a window: {_one_line(exc)}"))
            return
        started.set_result(None)
        try:
            self._show(window)
        finally:
            window.close()

    def _open(self) -> Any:
        import pyglet

        # No hidden extra window at import: it would want a display before we checked.
        pyglet.options["shadow_window"] = False
        import pyglet.window

        window = pyglet.window.Window(*FIRST_SIZE, caption=self._title, resizable=True)

        @window.event
        def on_close() -> None:
            self.closed = True

        return window

    def _show(self, window: Any) -> None:
        import pyglet

        drawn, size = 0, FIRST_SIZE
        while not (self._stopping or self.closed):
            self._new.wait(IDLE_S)
            self._new.clear()
            window.dispatch_events()
            with self._lock:
                image, version = self._image, self._version
            if image is None or version == drawn:
                continue
            height, width = image.shape[:2]
            if (width, height) != size:
                window.set_size(width, height)
                size = (width, height)
            # Rows top to bottom: a negative pitch tells pyglet so (OpenGL counts from below).
            picture = pyglet.image.ImageData(
                width, height, "BGR", np.ascontiguousarray(image).tobytes(), pitch=-width * 3
            )
            window.switch_to()
            window.clear()
            picture.blit(0, 0, width=window.width, height=window.height)
            window.flip()
            drawn = version
            self.shown += 1


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
