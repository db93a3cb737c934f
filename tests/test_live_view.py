"""The live view's server on its own (receiver/live_view.py, live_figures.py, window.py):
real HTTP on loopback, real JPEG, pictures handed to the sink as the receive loop does.
"""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from browser import look_at, unavailable

from facewire.receiver.live_figures import LiveFigures
from facewire.receiver.live_view import (
    BOUNDARY,
    MAX_VIEWERS,
    LiveView,
    encode_jpeg,
    listen,
    parse_view_address,
    waiting_still,
)
from facewire.receiver.window import NoDisplay, Window

SIZE = (640, 480)
BROWSER = unavailable()
WAITING = "waiting for a sender"  # what the view says before the receiver says anything


def picture(level: int, noise: bool = False, seed: int = 0) -> np.ndarray:
    """A picture whose top-left block has grey ``level`` (what a viewer checks it got)."""
    if noise:
        image = np.random.default_rng(seed).integers(0, 256, (SIZE[1], SIZE[0], 3), np.uint8)
    else:
        image = np.full((SIZE[1], SIZE[0], 3), 90, np.uint8)
    image[:64, :64] = level
    return image


class Feeder:
    """Hands pictures to a view's sink as the receive loop does, with a report so far."""

    def __init__(self, view: LiveView) -> None:
        self.view = view
        self.report = SimpleNamespace(
            bytes_received={"geometry": 0, "snapshot": 36000}, frames_out=0
        )

    def show(self, image: np.ndarray, latency_ms: float = 20.0) -> None:
        self.report.frames_out += 1
        self.report.bytes_received = {
            "geometry": self.report.bytes_received["geometry"] + 50,
            "snapshot": 36000,
        }
        frame = SimpleNamespace(session_id=7, seq=self.report.frames_out, image=image,
                                capture_us=0, latency_ms=latency_ms)  # fmt: skip
        self.view(frame, self.report)


@pytest.fixture
def view() -> Iterator[LiveView]:
    with LiveView("127.0.0.1", 0) as v:
        yield v


def get(view: LiveView, path: str) -> tuple[int, str, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=10)
    try:
        conn.request("GET", path)
        r = conn.getresponse()
        return r.status, r.getheader("Content-Type") or "", r.read()
    finally:
        conn.close()


class Stream:
    """A viewer of ``/stream.mjpg`` that reads its parts (JPEG pictures) as they come."""

    def __init__(self, view: LiveView) -> None:
        self.conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=10)
        self.conn.request("GET", "/stream.mjpg")
        self.response = self.conn.getresponse()
        assert self.response.status == 200
        kind = self.response.getheader("Content-Type")
        assert kind == f"multipart/x-mixed-replace; boundary={BOUNDARY}", kind
        assert self.response.readline() == f"--{BOUNDARY}\r\n".encode()
        self.received = 0  # bytes

    def next_picture(self) -> np.ndarray:
        headers = {}
        while (line := self.response.readline()) != b"\r\n":
            name, value = line.decode().split(":", 1)
            headers[name.strip().lower()] = value.strip()
        assert headers["content-type"] == "image/jpeg", headers
        data = self.response.read(int(headers["content-length"]))
        assert self.response.readline() == b"\r\n"
        assert self.response.readline() == f"--{BOUNDARY}\r\n".encode()
        self.received += len(data)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape == (SIZE[1], SIZE[0], 3)
        return image

    def close(self) -> None:
        self.conn.close()


def decode(jpeg: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image is not None
    return image


def level_of(image: np.ndarray) -> float:
    return float(image[8:56, 8:56].mean())


def wait_until(condition: object, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_page_and_figures(view: LiveView) -> None:
    status, kind, body = get(view, "/")
    assert status == 200 and kind.startswith("text/html")
    html = body.decode()
    for element in (
        'id="picture"',
        'src="stream.mjpg"',
        'id="fps"',
        'id="latency"',
        "kbps-",
        "carries none",
    ):
        assert element in html
    status, kind, body = get(view, "/picture.jpg")  # no picture yet: the waiting still
    assert status == 200 and kind == "image/jpeg"
    assert np.array_equal(decode(body) > 128, decode(encode_jpeg(waiting_still(WAITING))) > 128)
    figures = json.loads(get(view, "/figures.json")[2])
    assert figures["session"] is None and figures["frames"] == 0 and figures["fps"] == 0
    feeder = Feeder(view)
    for i in range(20):
        feeder.show(picture(i * 10))
        time.sleep(0.01)
    view.event("session 7: 640x480 at 30 fps")
    figures = json.loads(get(view, "/figures.json")[2])
    assert figures["session"] == {"id": 7, "width": 640, "height": 480}
    assert figures["frames"] == 20 and figures["pictures"] == 20
    assert figures["fps"] > 0 and figures["kbps"]["geometry"] > 0
    assert figures["kbps"]["snapshot"] == 0  # nothing came on it in the window
    assert figures["latency_ms"] == {"p50": 20.0, "max": 20.0}
    assert figures["events"] == ["session 7: 640x480 at 30 fps"]


def test_before_the_first_picture_a_still_says_what_the_receiver_waits_for(
    view: LiveView,
) -> None:
    line = "waiting for a sender on tcp://*:5555 (and :5556)"
    view.event(line)
    stream = Stream(view)  # a viewer who came first
    try:
        still = cv2.cvtColor(stream.next_picture(), cv2.COLOR_BGR2GRAY)
        assert np.array_equal(still > 128, decode(encode_jpeg(waiting_still(line))) > 128)
        assert not np.array_equal(still > 128, decode(encode_jpeg(waiting_still(WAITING))) > 128)
        assert view.encoded == 0  # the still is no picture of the call
        Feeder(view).show(picture(200))
        # Then the call (after the still again, if it was due meanwhile).
        assert any(abs(level_of(stream.next_picture()) - 200) < 3 for _ in range(5))
    finally:
        stream.close()
    # The sender left: the last picture stays, for a new viewer too, and comes again (a
    # browser shows a part once the next begins).
    view.event("session ended (bye) after 1 frames; waiting for a new session")
    stream = Stream(view)
    try:
        for _ in range(2):
            assert abs(level_of(stream.next_picture()) - 200) < 3
    finally:
        stream.close()
    status, kind, body = get(view, "/picture.jpg")
    assert status == 200 and abs(float(decode(body)[8:56, 8:56].mean()) - 200) < 3


@pytest.mark.skipif(BROWSER is not None, reason=f"no headless Chromium: {BROWSER}")
def test_the_page_loads_before_a_sender_comes(view: LiveView, tmp_path: Path) -> None:
    view.event("waiting for a sender on tcp://*:5555 (and :5556)")
    loaded = """(() => {
      const img = document.getElementById("picture");
      return document.readyState === "complete" && img.complete && img.naturalWidth > 0
        && document.getElementById("status").textContent.startsWith("waiting for a sender");
    })()"""
    (look,) = look_at(view.url, tmp_path, shots=1, ready=loaded)
    assert look.page["natural"] == list(SIZE)


def test_nothing_is_encoded_until_someone_watches(view: LiveView) -> None:
    feeder = Feeder(view)
    for i in range(30):
        feeder.show(picture(i))
        get(view, "/figures.json")  # the figures alone need no picture
    assert view.encoded == 0
    stream = Stream(view)
    try:
        assert abs(level_of(stream.next_picture()) - 29) < 3  # the newest picture, at once
        assert view.encoded == 1
        feeder.show(picture(200))
        assert abs(level_of(stream.next_picture()) - 200) < 3
    finally:
        stream.close()
    wait_until(lambda: view.viewers == 0)
    before = view.encoded
    for i in range(10):
        feeder.show(picture(i))
    time.sleep(0.2)
    assert view.encoded == before
    status, kind, body = get(view, "/picture.jpg")  # one picture on request: the newest
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert status == 200 and kind == "image/jpeg" and abs(level_of(image) - 9) < 3


def test_pictures_are_encoded_at_most_at_the_stream_rate(view: LiveView) -> None:
    feeder = Feeder(view)
    stream = Stream(view)
    try:
        feeder.show(picture(0))
        stream.next_picture()
        start, shown = time.monotonic(), 0
        while time.monotonic() - start < 1.0:  # as fast as the loop goes
            feeder.show(picture(shown % 250))
            shown += 1
        elapsed = time.monotonic() - start
        encoded = view.encoded - 1
    finally:
        stream.close()
    assert shown > 200  # the sink did not hold the loop up
    assert encoded <= elapsed * 30 + 2, (encoded, elapsed)


def test_a_viewer_that_stops_reading_holds_up_neither_the_loop_nor_other_viewers(
    view: LiveView,
) -> None:
    feeder = Feeder(view)
    noisy = [picture(i * 4, noise=True, seed=i) for i in range(60)]  # ~0.4 MB of JPEG each
    watcher = Stream(view)
    stuck = None
    try:
        for i in range(30):  # warm-up: the encoder's and the server's buffers are made
            feeder.show(noisy[i])
            watcher.next_picture()
        stuck = socket.create_connection(("127.0.0.1", view.port))
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")  # and never reads
        wait_until(lambda: view.viewers == 2)
        rss_before, received_before = _rss_bytes(), watcher.received
        last = 0
        for i in range(150):  # 5 s at 30 fps
            image = noisy[i % len(noisy)]
            feeder.show(image)
            if i % 10 == 9:
                # The reading viewer keeps getting the newest picture.
                got = watcher.next_picture()
                while abs(level_of(got) - level_of(image)) > 1.5:
                    got = watcher.next_picture()
                last = i
            time.sleep(1 / 30)
        assert last == 149
        grown, sent = _rss_bytes() - rss_before, watcher.received - received_before
    finally:
        watcher.close()
        if stuck is not None:
            stuck.close()
    # What the stuck viewer was not sent is dropped, not queued for it. (Measured: 3 MB grown
    # while 30 MB went to the other viewer; with a queue per viewer, 60 MB.)
    assert sent > 10e6
    assert grown < sent / 4, (grown, sent)


def test_more_viewers_than_allowed_are_refused(view: LiveView) -> None:
    Feeder(view).show(picture(1))
    streams = [Stream(view) for _ in range(MAX_VIEWERS)]
    try:
        wait_until(lambda: view.viewers == MAX_VIEWERS)
        assert get(view, "/stream.mjpg")[0] == 503
    finally:
        for stream in streams:
            stream.close()


def test_close_ends_the_streams() -> None:
    view = LiveView("127.0.0.1", 0)
    Feeder(view).show(picture(1))
    stream = Stream(view)
    stream.next_picture()
    view.close()
    assert stream.response.read() == b""  # the stream ended
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", view.port), timeout=2)


def _rss_bytes() -> int:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:8080", ("127.0.0.1", 8080)),
        ("0.0.0.0:0", ("0.0.0.0", 0)),
        ("*:8080", ("0.0.0.0", 8080)),
        ("localhost:80", ("localhost", 80)),
        ("[::1]:8080", ("::1", 8080)),
    ],
)
def test_view_address(text: str, expected: tuple[str, int]) -> None:
    assert parse_view_address(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("8080", "invalid live view address '8080': expected HOST:PORT"),
        ("http://127.0.0.1:8080", "expected HOST:PORT"),
        ("127.0.0.1:", "expected HOST:PORT"),
        ("127.0.0.1:99999", "port 99999 outside 0..65535"),
        ("::1:8080", "expected HOST:PORT"),
    ],
)
def test_bad_view_address(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        parse_view_address(text)


def test_a_port_in_use_is_one_line() -> None:
    busy = listen("127.0.0.1", 0)
    port = busy.getsockname()[1]
    try:
        with pytest.raises(OSError) as error:
            LiveView("127.0.0.1", port)
    finally:
        busy.close()
    assert (
        str(error.value)
        == f"cannot serve the live view on 127.0.0.1:{port}: address already in use"
    )


def test_figures_over_the_last_two_seconds() -> None:
    now = [100.0]
    figures = LiveFigures(clock=lambda: now[0])
    assert figures.as_dict()["kbps"] == {} and figures.as_dict()["age_s"] is None
    for i in range(61):  # 2 s at 30 fps: 1000 bytes of geometry a second, one snapshot
        now[0] = 100.0 + i / 30
        figures.add(1, (640, 480), {"geometry": 1000 * i // 30, "snapshot": 30000}, 40.0 + i % 3, i)
    f = figures.as_dict()
    assert f["fps"] == pytest.approx(30.0, abs=0.5)
    assert f["kbps"]["geometry"] == pytest.approx(8.0, abs=0.3)
    assert f["kbps"]["snapshot"] == 0 and f["kbps"]["total"] == f["kbps"]["geometry"]
    assert f["latency_ms"] == {"p50": 41.0, "max": 42.0}
    assert f["frames"] == 60 and f["age_s"] == 0
    # Two machines: a capture time on the other clock is no latency.
    figures.add(1, (640, 480), {"geometry": 3000}, -5000.0, 61)
    assert figures.as_dict()["latency_ms"] is None
    # Nothing for longer than the window: no rate, and how long it has been.
    now[0] += 5
    f = figures.as_dict()
    assert f["fps"] == 0 and f["kbps"]["geometry"] == 0 and f["age_s"] == pytest.approx(5)
    # A new session starts its rates afresh.
    figures.add(2, (320, 240), {"geometry": 0}, 10.0, 0)
    f = figures.as_dict()
    assert f["session"] == {"id": 2, "width": 320, "height": 240} and f["fps"] == 0


def test_window_without_a_display_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(
        NoDisplay, match=r"^cannot open a window: no display \(DISPLAY is not set\)$"
    ):
        Window()


def test_window_on_a_display_that_does_not_answer_is_one_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("DISPLAY", ":4321")  # no X server there
    with pytest.raises(NoDisplay) as error:
        Window()
    message = str(error.value)
    assert message.startswith("cannot open a window: ") and "\n" not in message, message
    assert threading.active_count() < 50
