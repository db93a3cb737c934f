"""The live view of a call, as a person sees it: ``facewire send`` and ``facewire receive
--view`` in their own processes on loopback, the page opened in headless Chromium, its
screenshots checked for the rebuilt face and the figures (tests/view_check.py).

Skipped, with the reason, only where Chromium cannot run.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
from browser import look_at, unavailable
from cli_call import Facewire, free_ports
from view_check import check_page

REASON = unavailable()


@pytest.mark.skipif(REASON is not None, reason=f"no headless Chromium: {REASON}")
def test_the_page_shows_the_face_and_live_figures(tmp_path: Path) -> None:
    port = free_ports(2)
    stats = tmp_path / "stats.json"
    receiver = Facewire(
        "receive", "--bind", f"tcp://127.0.0.1:{port}", "--plain", "--view", "127.0.0.1:0",
        "--stats", str(stats),
    )  # fmt: skip
    sender = None
    try:
        line = receiver.expect("live view on ")
        url = line.split("live view on ")[1].split()[0]
        sender = Facewire("send", "--connect", f"tcp://127.0.0.1:{port}", "--plain", "--loop")
        receiver.expect("session ")
        looks = look_at(url, tmp_path, shots=2, gap_s=1.5)
        seen = check_page([{"shot": str(look.shot), "page": look.page} for look in looks])
        for s in seen:
            print(f"{s.page} clip frame {s.clip_frame}, face SSIM {s.face_ssim:.3f}")
        # The call goes on after the page was looked at, and ends cleanly.
        sender.signal(signal.SIGTERM)
        assert sender.wait() == 0, sender.output()
        receiver.expect("session ended (bye)")
        receiver.signal(signal.SIGTERM)
        assert receiver.wait() == 0, receiver.output()
    finally:
        for process in (sender, receiver):
            if process is not None:
                process.kill()
    report = json.loads(stats.read_text())
    assert report["frames_out"] >= max(int(s.page["frames"]) for s in seen)
