"""``facewire receive --window`` on a display: a call on loopback through the commands, the
receiver's window on a virtual X server (Xvfb, Debian's ``xvfb``), the screen grabbed with
FFmpeg's x11grab (through PyAV) and checked for the rebuilt face as the page's screenshots
are (tests/view_check.py). Without a display, tests/test_call_commands.py and
tests/test_live_view.py check the one-line error.

Skipped, with the reason, only where Xvfb is missing.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator

import av
import numpy as np
import pytest
from cli_call import Facewire, free_ports, hang_up, kill_all
from view_check import MAX_LANDMARK_PX, MIN_FACE_SSIM, see_picture

SCREEN = (1024, 768)


@pytest.fixture
def display() -> Iterator[str]:
    if shutil.which("Xvfb") is None:
        pytest.skip("no Xvfb (Debian package xvfb; scripts/install-system-deps.sh --test)")
    read, write = os.pipe()
    server = subprocess.Popen(
        ["Xvfb", "-displayfd", str(write), "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24",
         "-nolisten", "tcp"],
        pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(write)
    with os.fdopen(read) as chosen:
        number = chosen.readline().strip()
    try:
        assert number, "Xvfb did not start"
        yield f":{number}"
    finally:
        server.terminate()
        server.wait(timeout=10)


def grab(display: str) -> np.ndarray:
    """The whole screen now, (h, w, 3) BGR."""
    size = f"{SCREEN[0]}x{SCREEN[1]}"
    with av.open(display, format="x11grab", options={"video_size": size}) as screen:
        frame = next(screen.decode(video=0))
        return frame.to_ndarray(format="bgr24")


def window_area(screen: np.ndarray) -> np.ndarray:
    """What is drawn on the black root window (no window manager: no frame around it)."""
    ys, xs = np.nonzero(screen.max(axis=2) > 0)
    assert len(xs), "nothing on the screen"
    return screen[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]


def test_window_shows_the_face(display: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DISPLAY", display)
    port = free_ports(2)
    receiver = Facewire("receive", "--bind", f"tcp://127.0.0.1:{port}", "--plain", "--window")
    sender = None
    try:
        receiver.expect("showing the call in a window")
        sender = Facewire("send", "--connect", f"tcp://127.0.0.1:{port}", "--plain", "--loop")
        receiver.expect("session ")
        time.sleep(2.0)  # pictures flow
        first = window_area(grab(display))
        time.sleep(1.0)
        second = window_area(grab(display))
        hang_up(sender, receiver)
    finally:
        kill_all(sender, receiver)
    assert first.shape == second.shape == (480, 640, 3)  # the window took the call's size
    for picture in (first, second):
        seen = see_picture(picture)
        print(f"clip frame {seen.clip_frame}, face SSIM {seen.face_ssim:.3f}")
        assert seen.face_ssim > MIN_FACE_SSIM and seen.landmark_px < MAX_LANDMARK_PX
    assert np.abs(first.astype(np.int16) - second).mean() > 0.5  # a live picture
