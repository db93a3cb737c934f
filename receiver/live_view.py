"""The call in a web browser: a small page with the live picture and the call's figures.

:class:`LiveView` is a frame sink (receiver.session.FrameSink) that serves, over HTTP
(aiohttp, on its own thread and event loop):

- ``/``: the page (receiver/live_page.py);
- ``/stream.mjpg``: the picture as MJPEG (``multipart/x-mixed-replace``, one JPEG per part),
  which an ``<img>`` shows in Chromium and Firefox;
- ``/picture.jpg``: the picture now, once;

Until the first picture comes, the stream and ``/picture.jpg`` show a still that says what the
receiver waits for (its last status line); after a sender leaves they keep its last picture.
A stream with nothing new sends its picture again each REPEAT_S, as a browser shows a part
only once the next one begins: the page loads whether or not a sender is there.
- ``/figures.json``: bit rate per channel, pictures per second, latency
  (receiver/live_figures.py).

The receive loop must not slow down for it: the sink only keeps a reference to the newest
picture and a few numbers. Pictures are JPEG-encoded on a worker thread, only while someone
watches, only the newest, at most MAX_STREAM_FPS a second, once for all viewers. A viewer
whose network is slow is sent the newest picture when it is ready for one; the pictures in
between are dropped for it (nothing queues beyond the socket's own buffers).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import re
import socket
import threading
from typing import Any

import cv2
import numpy as np
from aiohttp import web

from facewire.receiver.live_figures import LiveFigures
from facewire.receiver.live_page import page

logger = logging.getLogger(__name__)

JPEG_QUALITY = 80
#: Pictures are encoded (and streamed) at most this often, whatever the receiver renders.
MAX_STREAM_FPS = 30.0
#: More simultaneous streams than this are refused (503): each costs a socket and its buffers.
MAX_VIEWERS = 8
#: A stream with no new picture for this long is sent its last one (or the still) again.
REPEAT_S = 1.0
#: How long the server may take to start or stop.
START_TIMEOUT_S = 10.0
BOUNDARY = "facewire-picture"
#: The still shown before the first picture: its size and colours (the page's own).
STILL_SIZE = (640, 480)
_STILL_BACKGROUND = (33, 31, 29)  # BGR of the page's #1d1f21
_STILL_TEXT = (232, 232, 232)

_VIEW_ADDRESS = re.compile(
    r"^(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<host>\*|[A-Za-z0-9_.\-]+)):(?P<port>[0-9]{1,5})$"
)
_EXAMPLES = "e.g. 127.0.0.1:8080, or 0.0.0.0:8080 for every interface"


def parse_view_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[IPV6]:PORT``) checked: ValueError with one line when it cannot be.

    HOST ``*`` is every IPv4 interface (0.0.0.0), as in ``--bind tcp://*:PORT``. PORT 0 takes
    any free port (the URL says which).
    """
    match = _VIEW_ADDRESS.match(text.strip())
    if match is None:
        raise ValueError(f"invalid live view address {text!r}: expected HOST:PORT ({_EXAMPLES})")
    port = int(match["port"])
    if port > 65535:
        raise ValueError(f"invalid live view address {text!r}: port {port} outside 0..65535")
    host = match["v6"] or match["host"]
    return ("0.0.0.0" if host == "*" else host), port


def listen(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host``:``port``; OSError with one line if it cannot be."""
    where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError):
        raise OSError(f"cannot serve the live view on {where}: cannot resolve {host!r}") from None
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        # Lets a restarted receiver take its port back at once; a port another program
        # listens on still fails.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        reason = (exc.strerror or str(exc)).lower()
        raise OSError(f"cannot serve the live view on {where}: {reason}") from None
    sock.setblocking(False)
    return sock


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """(h, w, 3) uint8 BGR -> JPEG bytes."""
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} picture as JPEG")
    return data.tobytes()


def waiting_still(line: str) -> np.ndarray:
    """(h, w, 3) uint8 BGR: the still the view shows before any picture, saying ``line``."""
    width, height = STILL_SIZE
    image = np.full((height, width, 3), _STILL_BACKGROUND, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(image, "facewire", (40, 80), font, 1.2, _STILL_TEXT, 2, cv2.LINE_AA)
    rows: list[str] = []
    for word in line.split():
        if rows and cv2.getTextSize(f"{rows[-1]} {word}", font, 0.7, 1)[0][0] < width - 80:
            rows[-1] += f" {word}"
        else:
            rows.append(word)
    for i, row in enumerate(rows[:8]):
        cv2.putText(image, row, (40, 150 + 34 * i), font, 0.7, _STILL_TEXT, 1, cv2.LINE_AA)
    return image


class LiveView:
    """Serves the page on ``host``:``port`` from construction until :meth:`close`.

    Call it with each picture (it is a FrameSink) and give it the receiver's status lines with
    :meth:`event`. Raises OSError (one line) when it cannot listen there.
    """

    def __init__(
        self,
        host: str,
        port: int,
        max_fps: float = MAX_STREAM_FPS,
        quality: int = JPEG_QUALITY,
    ) -> None:
        self.figures = LiveFigures()
        self.encoded = 0  # pictures encoded so far
        self._min_interval = 1.0 / max_fps
        self._quality = quality
        self._lock = threading.Lock()
        self._image: np.ndarray | None = None
        self._version = 0  # pictures received so far
        self._jpeg = b""
        self._jpeg_version = 0  # the picture ``_jpeg`` shows
        self._viewers = 0  # streams open (read from the receive loop's thread)
        self._still_for: tuple[str, bytes] = ("", b"")  # the waiting still's line and JPEG
        self._closing = False
        sock = listen(host, port)
        self.host = host
        self.port: int = sock.getsockname()[1]
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="live-jpeg")
        self._loop = asyncio.new_event_loop()
        started: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(
            target=self._serve, args=(sock, started), name="live-view", daemon=True
        )
        self._thread.start()
        try:
            started.result(timeout=START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise
        logger.info("live view on %s", self.url)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def viewers(self) -> int:
        return self._viewers

    # --- the receive loop's side ---------------------------------------------------------

    def __call__(self, frame: Any, report: Any) -> None:
        """FrameSink: ``frame`` a receiver.session.RenderedFrame, ``report`` the figures so far.

        Keeps a reference to the picture (the receive loop does not change it afterwards) and
        wakes the encoder only when someone is watching.
        """
        image = frame.image
        with self._lock:
            self._image = image
            self._version += 1
        self.figures.add(
            frame.session_id,
            (image.shape[1], image.shape[0]),
            report.bytes_received,
            frame.latency_ms,
            report.frames_out,
        )
        if self._viewers and not self._closing:
            try:
                self._loop.call_soon_threadsafe(self._wake)
            except RuntimeError:  # closed meanwhile
                pass

    def event(self, line: str) -> None:
        """A status line for the page ("session 42: 640x480 at 30 fps")."""
        self.figures.event(line)

    def close(self) -> None:
        """Ends the streams and stops serving (idempotent)."""
        if self._thread.is_alive() and not self._closing:
            self._closing = True
            try:
                asyncio.run_coroutine_threadsafe(self._stop(), self._loop).result(
                    timeout=START_TIMEOUT_S
                )
            except (concurrent.futures.TimeoutError, RuntimeError) as exc:
                logger.warning("live view did not stop cleanly: %s", exc)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=START_TIMEOUT_S)
        self._closing = True
        self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the server's thread -------------------------------------------------------------

    def _serve(self, sock: socket.socket, started: concurrent.futures.Future[None]) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._start(sock))
        except BaseException as exc:  # handed to the constructor
            sock.close()
            started.set_exception(exc)
            self._loop.close()
            return
        started.set_result(None)
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    async def _start(self, sock: socket.socket) -> None:
        self._picture = asyncio.Event()  # a newer picture than the JPEG may be there
        self._encoded = asyncio.Condition()  # a new JPEG is there
        self._encoder = asyncio.get_running_loop().create_task(self._encode_loop())
        app = web.Application()
        app.router.add_get("/", self._page)
        app.router.add_get("/stream.mjpg", self._stream)
        app.router.add_get("/picture.jpg", self._still)
        app.router.add_get("/figures.json", self._figures)
        # A viewer that goes away ends its stream at once (handler cancelled), not at the next
        # picture, which may be long in coming when the call is between sessions.
        self._runner = web.AppRunner(
            app, access_log=None, shutdown_timeout=1.0, handler_cancellation=True
        )
        await self._runner.setup()
        await web.SockSite(self._runner, sock).start()

    async def _stop(self) -> None:
        async with self._encoded:
            self._encoded.notify_all()  # streams see _closing and end
        self._encoder.cancel()
        await self._runner.cleanup()

    def _wake(self) -> None:
        self._picture.set()

    async def _encode_loop(self) -> None:
        loop = asyncio.get_running_loop()
        next_at = 0.0
        while True:
            await self._picture.wait()
            self._picture.clear()
            if (pause := next_at - loop.time()) > 0:
                await asyncio.sleep(pause)  # pictures coming meanwhile: only the newest counts
            with self._lock:
                image, version = self._image, self._version
            if image is None or version == self._jpeg_version:
                continue
            next_at = loop.time() + self._min_interval
            try:
                jpeg = await loop.run_in_executor(self._pool, encode_jpeg, image, self._quality)
            except (ValueError, cv2.error) as exc:
                logger.warning("live view: %s", exc)
                continue
            self.encoded += 1
            self._jpeg, self._jpeg_version = jpeg, version
            async with self._encoded:
                self._encoded.notify_all()

    async def _fresh_jpeg(self, after: int) -> tuple[bytes, int]:
        """The newest JPEG once it shows a picture newer than ``after`` (or the server closes:
        then b"")."""
        async with self._encoded:
            await self._encoded.wait_for(lambda: self._jpeg_version > after or self._closing)
        return (b"", after) if self._closing else (self._jpeg, self._jpeg_version)

    def _already_sent(self) -> int:
        """What a new viewer counts as seen: the current JPEG if it shows the newest picture,
        else nothing (it waits for the newest, which this asks for)."""
        with self._lock:
            newest = self._version
        if self._jpeg_version == newest:
            return newest - 1 if newest else 0
        self._picture.set()
        return self._jpeg_version

    async def _page(self, request: web.Request) -> web.Response:
        return web.Response(text=page(), content_type="text/html", headers=_NO_STORE)

    async def _figures(self, request: web.Request) -> web.Response:
        return web.json_response(self.figures.as_dict(), headers=_NO_STORE)

    def _waiting_jpeg(self) -> bytes:
        """The still for before the first picture, saying the receiver's last status line."""
        said = [e for e in self.figures.as_dict()["events"] if not e.startswith("no sound")]
        line = said[-1] if said else "waiting for a sender"
        if self._still_for[0] != line:
            self._still_for = (line, encode_jpeg(waiting_still(line), self._quality))
        return self._still_for[1]

    async def _still(self, request: web.Request) -> web.Response:
        if self._version == 0:
            return web.Response(
                body=self._waiting_jpeg(), content_type="image/jpeg", headers=_NO_STORE
            )
        jpeg, _ = await self._fresh_jpeg(self._already_sent())
        if not jpeg:
            raise web.HTTPServiceUnavailable(text="the live view is closing\n")
        return web.Response(body=jpeg, content_type="image/jpeg", headers=_NO_STORE)

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        if self._viewers >= MAX_VIEWERS:
            raise web.HTTPServiceUnavailable(text=f"at most {MAX_VIEWERS} viewers at once\n")
        response = web.StreamResponse(
            headers={
                "Content-Type": f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                **_NO_STORE,
            }
        )
        await response.prepare(request)
        self._viewers += 1
        try:
            sent = self._already_sent()
            await response.write(f"--{BOUNDARY}\r\n".encode())
            if self._version == 0:
                await response.write(_part(self._waiting_jpeg()))
            while True:
                try:
                    jpeg, sent = await asyncio.wait_for(self._fresh_jpeg(sent), REPEAT_S)
                except TimeoutError:
                    # Nothing new (no sender yet, or it left): the same picture again, since a
                    # browser shows a part once the next one begins; the page then loads.
                    if self._closing:
                        break
                    jpeg = self._jpeg if self._jpeg_version else self._waiting_jpeg()
                if not jpeg:
                    break
                await response.write(_part(jpeg))
        except ConnectionError:
            logger.debug("a viewer went away")
        finally:
            self._viewers -= 1
        return response


_NO_STORE = {"Cache-Control": "no-store"}


def _part(jpeg: bytes) -> bytes:
    """One picture of the MJPEG stream. The boundary right after it tells the browser it is
    whole, so it shows it now rather than when the next one starts."""
    head = f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
    return head.encode() + jpeg + f"\r\n--{BOUNDARY}\r\n".encode()
